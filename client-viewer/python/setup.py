"""Build hook: generate the haptics.v1 stubs from the repository's proto/ at build time.

`pip install ./client-viewer/python` builds in the source tree, so ../../proto is the contract the
daemon was built from. The generated modules land in the wheel as haptics/v1/*.py (the proto
package haptics.v1 maps onto this package's subpackage), never in the source tree.
"""

import os
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
# HAPTICD_PROTO_ROOT (older name HAPTICS_PROTO_ROOT): the proto/ folder of a checkout.
PROTO_ROOT = Path(
    os.environ.get("HAPTICD_PROTO_ROOT")
    or os.environ.get("HAPTICS_PROTO_ROOT")
    or HERE.parent.parent / "proto"
)
PROTO = Path("haptics") / "v1" / "haptics.proto"


class BuildWithStubs(build_py):
    def run(self):
        super().run()
        source = PROTO_ROOT / PROTO
        if not source.is_file():
            raise SystemExit(
                f"haptics-client: {source} not found; install from the repository "
                "(pip install ./client-viewer/python) or set HAPTICD_PROTO_ROOT to its proto/ folder"
            )
        from grpc_tools import protoc
        import grpc_tools

        out = Path(self.build_lib)
        well_known = Path(grpc_tools.__file__).parent / "_proto"
        args = [
            "grpc_tools.protoc",
            f"-I{PROTO_ROOT}",
            f"-I{well_known}",
            f"--python_out={out}",
            f"--pyi_out={out}",
            f"--grpc_python_out={out}",
            str(PROTO),
        ]
        self.announce(f"generating stubs: {' '.join(args[1:])}", level=2)
        if protoc.main(args) != 0:
            raise SystemExit(f"haptics-client: protoc failed on {source}")
        (out / "haptics" / "v1" / "__init__.py").write_text(
            '"""Generated from proto/haptics/v1/haptics.proto at build time."""\n'
        )


setup(cmdclass={"build_py": BuildWithStubs})
