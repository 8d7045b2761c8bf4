"""The typed layer: :class:`Client` (SessionControl), :class:`Session` (one running session:
forces, statistics, a scripted probe over DeviceLink, surface frames from SurfaceStream).

Errors: every call raises ``grpc.RpcError`` with the server's status (``NOT_FOUND`` for an
unknown session, ``INVALID_ARGUMENT`` for a malformed scene or force) and ``ValueError`` for
arguments refused before anything is sent.
"""

from __future__ import annotations

import csv
import math
import os
import queue
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence, Union

import grpc
import numpy as np

from .v1 import haptics_pb2 as pb
from .v1 import haptics_pb2_grpc as rpc

Vec = Sequence[float]


def _vec3(v: Vec, what: str) -> pb.Vec3:
    values = [float(c) for c in v]
    if len(values) != 3 or not all(math.isfinite(c) for c in values):
        raise ValueError(f"{what} must be three finite numbers, got {v!r}")
    return pb.Vec3(x=values[0], y=values[1], z=values[2])


def _target(address: str) -> str:
    """``http://host:port`` (as hapticd prints it) or ``host:port``."""
    for prefix in ("http://", "https://"):
        if address.startswith(prefix):
            address = address[len(prefix):]
    return address.rstrip("/")


@dataclass(frozen=True)
class SceneInfo:
    """A scene the daemon can start by name (``ListScenes``)."""

    name: str
    description: str
    nodes: int
    tetrahedra: int


@dataclass(frozen=True)
class Press:
    """What a scripted press recorded, one row per device sample sent.

    ``t_s`` (n,), ``position_m`` (n, 3) the haptic interaction point sent, ``force_n`` (n, 3) the
    force of the command answering that sample (NaN where none came), ``in_contact`` (n,) bool,
    ``proxy_m`` (n, 3) the god-object position the server reported.
    """

    t_s: np.ndarray
    position_m: np.ndarray
    force_n: np.ndarray
    in_contact: np.ndarray
    proxy_m: np.ndarray

    @property
    def depth_m(self) -> np.ndarray:
        """Travel from the first sample along the press direction, m (n,)."""
        d = self.position_m - self.position_m[0]
        return np.linalg.norm(d, axis=1)


@dataclass(frozen=True)
class Frame:
    """One surface frame: ``positions_m`` (n, 3) float32, ``triangles`` (m, 3) uint32 (the last
    keyframe's), ``rest_positions_m`` (n, 3) or None, probe and contact force as (3,) arrays."""

    frame: int
    sim_time_s: float
    keyframe: bool
    positions_m: np.ndarray
    triangles: np.ndarray
    rest_positions_m: Optional[np.ndarray]
    probe_position_m: np.ndarray
    contact_force_n: np.ndarray
    in_contact: bool
    max_displacement_m: float
    topology_version: int

    @property
    def displacement_m(self) -> Optional[np.ndarray]:
        """Per-vertex displacement magnitude from rest, m (n,), when rest positions are known."""
        if self.rest_positions_m is None:
            return None
        return np.linalg.norm(self.positions_m - self.rest_positions_m, axis=1)


@dataclass
class ToolFigures:
    """One tool slot's figures from ``SessionStats.tools`` (SI units in the names)."""

    tool_id: str
    slot: int
    connected: bool
    in_contact: bool
    force_n: float
    pose_to_force_p50_us: float
    pose_to_force_p99_us: float
    device_samples: int
    rejected_samples: int
    out_of_workspace_samples: int

    @classmethod
    def of(cls, t) -> "ToolFigures":
        """The figures of a ``pb.ToolStats``."""
        return cls(
            tool_id=t.tool_id,
            slot=int(t.slot),
            connected=bool(t.connected),
            in_contact=bool(t.in_contact),
            force_n=float(t.force_n),
            pose_to_force_p50_us=float(t.pose_to_force_p50_us),
            pose_to_force_p99_us=float(t.pose_to_force_p99_us),
            device_samples=int(t.device_samples),
            rejected_samples=int(t.rejected_samples),
            out_of_workspace_samples=int(t.out_of_workspace_samples),
        )


def _env(name: str) -> Optional[str]:
    """``HAPTICD_<name>``, else the older ``HAPTICS_<name>`` (the daemon's binaries read the same
    names: docs/tools.md, "Environment variables")."""
    value = os.environ.get(f"HAPTICD_{name}")
    return value if value is not None else os.environ.get(f"HAPTICS_{name}")


def _token_metadata(token: Optional[str]) -> list:
    """The bearer token, from the argument, ``HAPTICD_TOKEN`` or the file ``HAPTICD_TOKEN_FILE``
    (older names ``HAPTICS_TOKEN``, ``HAPTICS_TOKEN_FILE`` still read).

    Tokens never come from the command line of the examples (they would show in ``ps``)."""
    if token is None:
        token = _env("TOKEN")
    if token is None and _env("TOKEN_FILE"):
        lines = Path(_env("TOKEN_FILE")).read_text().splitlines()
        token = next((l.strip() for l in lines if l.strip() and not l.strip().startswith("#")), None)
    return [("authorization", f"Bearer {token}")] if token else []


class Client:
    """A connection to ``hapticd`` (insecure channel on a trusted lab network).

    ``address``: ``host:port`` or ``http://host:port``. ``token``: bearer token for daemons with
    authentication (default: ``HAPTICD_TOKEN`` or the file named by ``HAPTICD_TOKEN_FILE``).
    ``timeout_s``: deadline of unary calls.
    """

    def __init__(self, address: str, token: Optional[str] = None, timeout_s: float = 30.0):
        self.address = _target(address)
        self.timeout_s = float(timeout_s)
        self.metadata = _token_metadata(token)
        self.channel = grpc.insecure_channel(self.address)
        self.control = rpc.SessionControlStub(self.channel)
        self.device = rpc.DeviceLinkStub(self.channel)
        self.surface = rpc.SurfaceStreamStub(self.channel)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.channel.close()

    def _call(self, method, request):
        return method(request, timeout=self.timeout_s, metadata=self.metadata)

    def list_scenes(self) -> list[SceneInfo]:
        """The built-in and shipped scenes (``ListScenes``)."""
        r = self._call(self.control.ListScenes, pb.ListScenesRequest())
        return [SceneInfo(s.name, s.description, s.nodes, s.tetrahedra) for s in r.scenes]

    def list_sessions(self) -> list[str]:
        """Ids of the running sessions (``ListSessions``)."""
        return list(self._call(self.control.ListSessions, pb.ListSessionsRequest()).session_ids)

    def start(
        self,
        scene: Optional[str] = None,
        *,
        toml: Optional[str] = None,
        toml_file: Union[str, Path, None] = None,
    ) -> "Session":
        """Start a session from a scene name, scene TOML text, or a TOML file read here (the
        text is sent; the daemon never opens client-named files)."""
        if sum(x is not None for x in (scene, toml, toml_file)) != 1:
            raise ValueError("give exactly one of scene, toml, toml_file")
        if toml_file is not None:
            toml = Path(toml_file).read_text()
        request = pb.StartSessionRequest(scene=scene or "", scene_toml=toml or "")
        r = self._call(self.control.StartSession, request)
        return Session(self, r.session_id, r)

    def session(self, session_id: str) -> "Session":
        """A handle on a session started elsewhere."""
        return Session(self, session_id, None)


class Session:
    """One running session. ``info`` is the ``StartSessionResponse`` when this client started
    it (nodes, tetrahedra, substeps, critical_dt_s)."""

    def __init__(self, client: Client, session_id: str, info):
        self.client = client
        self.id = session_id
        self.info = info

    def __repr__(self) -> str:
        return f"Session({self.id!r})"

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """Stop the session (``StopSession``)."""
        self.client._call(self.client.control.StopSession, pb.StopSessionRequest(session_id=self.id))

    def stats(self) -> pb.SessionStats:
        """Loop rate, step-time percentiles, overruns, counts (``GetStats``; fields as in the
        proto, SI units in their names)."""
        return self.client._call(self.client.control.GetStats, pb.GetStatsRequest(session_id=self.id))

    def tools(self) -> list["ToolFigures"]:
        """Per-tool figures of ``GetStats`` (issue 50: one per tool slot of the session, in
        slot order): tool id ("" = the default tool), slot, connected, contact, force (N),
        pose-to-force p50/p99 (us), samples accepted, rejected and outside the workspace."""
        return [ToolFigures.of(t) for t in self.stats().tools]

    def apply_force(self, point_m: Vec, force_n: Vec, duration_s: float) -> None:
        """Inject ``force_n`` (N) at the surface near ``point_m`` (m) for ``duration_s``
        simulated seconds (``ApplyForce``)."""
        if not (math.isfinite(duration_s) and duration_s > 0):
            raise ValueError(f"duration_s must be finite and positive, got {duration_s!r}")
        request = pb.ApplyForceRequest(
            session_id=self.id,
            point_m=_vec3(point_m, "point_m"),
            force_n=_vec3(force_n, "force_n"),
            duration_s=float(duration_s),
        )
        self.client._call(self.client.control.ApplyForce, request)

    def press(
        self,
        start_m: Vec = (0.014, 0.0, -0.005),
        direction: Vec = (-1.0, 0.0, 0.0),
        depth_m: float = 0.004,
        speed_m_per_s: float = 0.01,
        hold_s: float = 0.2,
        rate_hz: float = 500.0,
        tool: str = "",
    ) -> Press:
        """A scripted probe on ``DeviceLink.Connect``: from ``start_m`` along ``direction`` to
        ``depth_m`` at ``speed_m_per_s``, hold ``hold_s``, back out. Samples are paced at
        ``rate_hz`` and sent one at a time (each waits up to 50 ms for its answer), so the
        recording pairs every pose with the force that answers it. The defaults press the
        built-in ``lv`` from 14 mm off its axis towards the epicardium (9.68 mm at z = -5 mm).
        ``tool`` names the tool this probe drives (``DeviceSample.tool_id``; "" = the default
        tool): a session takes several tools at once up to its scene's ``probe.max_tools``.
        """
        if len(tool) > 64 or not all(c.isascii() and (c.isalnum() or c in "-_.:") for c in tool):
            raise ValueError("tool must be at most 64 ASCII letters, digits, '-', '_', '.' or ':'")
        start = np.asarray([float(c) for c in start_m])
        n = np.asarray([float(c) for c in direction])
        if start.shape != (3,) or n.shape != (3,) or not np.all(np.isfinite(np.r_[start, n])):
            raise ValueError("start_m and direction must be three finite numbers each")
        norm = float(np.linalg.norm(n))
        if norm == 0.0:
            raise ValueError("direction must not be zero")
        n /= norm
        for name, v in (("depth_m", depth_m), ("speed_m_per_s", speed_m_per_s), ("rate_hz", rate_hz)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and positive, got {v!r}")
        if not (math.isfinite(hold_s) and hold_s >= 0):
            raise ValueError(f"hold_s must be finite and non-negative, got {hold_s!r}")
        dt = 1.0 / rate_hz
        t_move = depth_m / speed_m_per_s
        t = np.arange(0.0, 2 * t_move + hold_s + dt / 2, dt)
        travel = np.minimum(t, t_move) * speed_m_per_s
        back = np.clip(t - t_move - hold_s, 0.0, t_move) * speed_m_per_s
        positions = start + np.outer(travel - back, n)
        v = np.gradient(positions, dt, axis=0) if len(t) > 1 else np.zeros((len(t), 3))
        count = len(t)

        answered: "queue.Queue[int]" = queue.Queue()
        force = np.full((count, 3), np.nan)
        proxy = np.full((count, 3), np.nan)
        contact = np.zeros(count, dtype=bool)

        def samples():
            t0 = time.perf_counter()
            for i, p in enumerate(positions):
                yield pb.DeviceSample(
                    session_id=self.id,
                    seq=i + 1,
                    device_time_us=int(t[i] * 1e6),
                    position_m=pb.Vec3(x=p[0], y=p[1], z=p[2]),
                    velocity_m_per_s=pb.Vec3(x=v[i, 0], y=v[i, 1], z=v[i, 2]),
                    tool_id=tool if i == 0 else "",
                )
                try:
                    answered.get(timeout=0.05)
                except queue.Empty:
                    pass
                wait = t0 + (i + 1) * dt - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)

        stream = self.client.device.Connect(samples(), metadata=self.client.metadata)
        try:
            for cmd in stream:
                i = int(cmd.seq) - 1
                if 0 <= i < count:
                    force[i] = (cmd.force_n.x, cmd.force_n.y, cmd.force_n.z)
                    proxy[i] = (cmd.proxy_position_m.x, cmd.proxy_position_m.y, cmd.proxy_position_m.z)
                    contact[i] = cmd.in_contact
                answered.put(i)
                if i == count - 1:
                    break
        finally:
            stream.cancel()
        return Press(t, positions, force, contact, proxy)

    def watch(self, frames: Optional[int] = None, max_rate_hz: float = 30.0) -> Iterator[Frame]:
        """Surface frames (``SurfaceStream.Watch``, full encoding) as numpy arrays; stops after
        ``frames`` frames (None: until the session ends or the caller stops iterating)."""
        if not (math.isfinite(max_rate_hz) and 0.1 <= max_rate_hz <= 120.0):
            raise ValueError(f"max_rate_hz must be in 0.1..=120, got {max_rate_hz!r}")
        request = pb.WatchRequest(session_id=self.id, max_rate_hz=float(max_rate_hz))
        stream = self.client.surface.Watch(request, metadata=self.client.metadata)
        triangles = np.zeros((0, 3), dtype=np.uint32)
        rest = None
        seen = 0
        try:
            for f in stream:
                if f.keyframe and len(f.triangles):
                    triangles = np.asarray(f.triangles, dtype=np.uint32).reshape(-1, 3)
                if f.keyframe and len(f.rest_positions_m):
                    rest = np.asarray(f.rest_positions_m, dtype=np.float32).reshape(-1, 3)
                positions = np.asarray(f.positions_m, dtype=np.float32).reshape(-1, 3)
                yield Frame(
                    frame=f.frame,
                    sim_time_s=f.sim_time_s,
                    keyframe=f.keyframe,
                    positions_m=positions,
                    triangles=triangles,
                    rest_positions_m=rest if rest is not None and len(rest) == len(positions) else None,
                    probe_position_m=np.array([f.probe_position_m.x, f.probe_position_m.y, f.probe_position_m.z]),
                    contact_force_n=np.array([f.contact_force_n.x, f.contact_force_n.y, f.contact_force_n.z]),
                    in_contact=f.in_contact,
                    max_displacement_m=f.max_displacement_m,
                    topology_version=f.topology_version,
                )
                seen += 1
                if frames is not None and seen >= frames:
                    break
        finally:
            stream.cancel()


def read_recording(path: Union[str, Path]) -> dict:
    """A ``haptic-bridge --record`` CSV as numpy arrays: ``t_s`` (n,), ``position_m`` (n, 3),
    ``force_n`` (n, 3), ``in_contact`` (n,) bool, ``rtt_us``, ``age_us`` (n,) and ``state``
    (list of str). Raises ``ValueError`` on a file that is not such a recording."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    need = {"t_s", "x_m", "y_m", "z_m", "fx_n", "fy_n", "fz_n", "in_contact", "rtt_us", "age_us", "state"}
    if not rows or not need.issubset(rows[0].keys()):
        raise ValueError(f"{path}: not a haptic-bridge recording (columns {sorted(need)})")

    def col(name):
        # rtt_us and age_us are empty on ticks without a command: NaN there.
        return np.array([float(r[name]) if r[name] != "" else math.nan for r in rows])

    return {
        "t_s": col("t_s"),
        "position_m": np.column_stack([col("x_m"), col("y_m"), col("z_m")]),
        "force_n": np.column_stack([col("fx_n"), col("fy_n"), col("fz_n")]),
        "in_contact": np.array([r["in_contact"].strip().lower() in ("1", "true") for r in rows]),
        "rtt_us": col("rtt_us"),
        "age_us": col("age_us"),
        "state": [r["state"] for r in rows],
    }
