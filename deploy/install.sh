#!/usr/bin/env bash
# Installs hapticd for the systemd unit (deploy/hapticd.service), after
# `cargo build --release --workspace`:
#   sudo deploy/install.sh
# What it installs (PREFIX defaults to /usr/local):
#   PREFIX/bin/                    hapticd and the client programs found in BIN_DIR
#   /etc/hapticd/hapticd.toml      deploy/hapticd.toml; an existing one is kept (the new one is
#                                  written beside it as hapticd.toml.new)
#   PREFIX/share/hapticd/meshes/   the data directory client scenes may read meshes from
#   PREFIX/share/doc/hapticd/      README.md, docs/deploy.md, docs/security.md (the unit's
#                                  Documentation=)
#   /etc/systemd/system/hapticd.service
# The scene directory /var/lib/hapticd/scenes is made by systemd when the unit starts
# (StateDirectory=). Environment: BIN_DIR (default target/release), PREFIX, DESTDIR (a staging
# root prepended to every path, for packaging and for tests/tests/installed.rs), UNIT_DIR
# (default /etc/systemd/system). Nothing outside these paths is touched; systemctl is not run.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
bin_dir="${BIN_DIR:-$repo/target/release}"
prefix="${PREFIX:-/usr/local}"
dest="${DESTDIR:-}"
unit_dir="${UNIT_DIR:-/etc/systemd/system}"

if [ ! -x "$bin_dir/hapticd" ]; then
    echo "no $bin_dir/hapticd: run \`cargo build --release --workspace\` first (or set BIN_DIR)" >&2
    exit 1
fi
if [ "$prefix" != /usr/local ]; then
    # The unit and the configuration name /usr/local paths: keep them in step.
    echo "PREFIX=$prefix: edit ExecStart= in the unit and data_dirs in hapticd.toml to match" >&2
fi

install -d -m 755 "$dest$prefix/bin"
install -m 755 "$bin_dir/hapticd" "$dest$prefix/bin/hapticd"
for b in hapticctl haptic-bridge haptic-viewer haptic-solve haptic-mesh haptic-calibrate; do
    if [ -x "$bin_dir/$b" ]; then
        install -m 755 "$bin_dir/$b" "$dest$prefix/bin/$b"
    fi
done

install -d -m 755 "$dest/etc/hapticd"
if [ -e "$dest/etc/hapticd/hapticd.toml" ]; then
    install -m 644 "$repo/deploy/hapticd.toml" "$dest/etc/hapticd/hapticd.toml.new"
    echo "kept /etc/hapticd/hapticd.toml; the shipped one is hapticd.toml.new beside it"
else
    install -m 644 "$repo/deploy/hapticd.toml" "$dest/etc/hapticd/hapticd.toml"
fi

install -d -m 755 "$dest$prefix/share/hapticd/meshes"
install -d -m 755 "$dest$prefix/share/doc/hapticd"
install -m 644 "$repo/README.md" "$repo/docs/deploy.md" "$repo/docs/security.md" \
    "$dest$prefix/share/doc/hapticd/"

install -d -m 755 "$dest$unit_dir"
install -m 644 "$repo/deploy/hapticd.service" "$dest$unit_dir/hapticd.service"
echo "installed hapticd under ${dest:-/}: next \`systemctl daemon-reload && systemctl enable --now hapticd\`"
