"""Python client for hapticd, the networked haptic soft-body server.

A small typed layer over the generated ``haptics.v1`` gRPC stubs (built from the repository's
``proto/`` when the package is installed)::

    from haptics import Client

    with Client("127.0.0.1:50051") as client:
        print([s.name for s in client.list_scenes()])
        session = client.start("lv")
        session.apply_force(point_m=(0.0097, 0, -0.005), force_n=(-0.02, 0, 0), duration_s=0.2)
        press = session.press(depth_m=0.004)           # a scripted probe on the DeviceLink
        print(press.force_n[:, 0].max(), session.stats().loop_rate_hz)
        for frame in session.watch(frames=3):          # surface frames as numpy arrays
            print(frame.positions_m.shape, frame.max_displacement_m)
        session.stop()

All quantities are SI (metres, newtons, seconds), as on the wire.
"""

from .client import Client, Frame, Press, SceneInfo, Session, ToolFigures, read_recording

__all__ = ["Client", "Frame", "Press", "SceneInfo", "Session", "ToolFigures", "read_recording"]
