"""The Python client against a real hapticd (run by tests/tests/python.rs in a fresh venv).

Environment: HAPTICS_SERVER (host:port of a daemon on loopback), optionally HAPTICS_RECORDING
(a bridge --record CSV to read back) and HAPTICS_MCAP (a `hapticctl record` file).
"""

import os
import time
import unittest

import grpc
import numpy as np

from haptics import Client, read_recording

SERVER = os.environ["HAPTICS_SERVER"]


class Live(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.client = Client(SERVER)

    @classmethod
    def tearDownClass(cls):
        cls.client.close()

    def test_scenes_list_the_lv(self):
        scenes = {s.name: s for s in self.client.list_scenes()}
        self.assertIn("lv", scenes)
        self.assertGreater(scenes["lv"].tetrahedra, 10)
        self.assertGreater(scenes["lv"].nodes, scenes["lv"].tetrahedra // 10)

    def test_session_force_frames_press_stats_stop(self):
        session = self.client.start("lv")
        self.assertIn(session.id, self.client.list_sessions())
        self.assertGreater(session.info.nodes, 0)

        rest = next(session.watch(frames=1))
        self.assertTrue(rest.keyframe)
        self.assertEqual(rest.positions_m.shape[1], 3)
        self.assertGreater(len(rest.triangles), 0)
        self.assertLess(int(rest.triangles.max()), len(rest.positions_m))
        self.assertLess(rest.max_displacement_m, 1e-6)

        # An injected force dents the surface: frames show displacement while it acts.
        t_load = session.stats().sim_time_s
        session.apply_force((0.0097, 0.0, -0.005), (-0.03, 0.0, 0.0), duration_s=0.3)
        dents = [f.max_displacement_m for f in session.watch(frames=8, max_rate_hz=30)]
        self.assertGreater(max(dents), 1e-4, dents)
        # Let the load end and the wall swing back (simulated time: a loaded machine runs late).
        deadline = time.monotonic() + 30.0
        while session.stats().sim_time_s < t_load + 1.0 and time.monotonic() < deadline:
            time.sleep(0.05)

        # A scripted press: the force pushes the probe back out (+x) and grows with depth.
        press = session.press(depth_m=0.004, hold_s=0.1)
        answered = ~np.isnan(press.force_n[:, 0])
        self.assertGreater(answered.mean(), 0.8, "most samples answered")
        fx = press.force_n[:, 0]
        deep = answered & (press.depth_m > 0.0035)
        shallow = answered & (press.depth_m < 0.001)
        self.assertTrue(deep.any() and shallow.any())
        self.assertGreater(np.nanmean(fx[deep]), 0.01)
        self.assertLess(np.nanmax(np.abs(fx[shallow])), 1e-6)
        self.assertTrue(press.in_contact[deep].all())

        stats = session.stats()
        self.assertEqual(stats.session_id, session.id)
        self.assertGreater(stats.device_samples, 100)
        self.assertGreater(stats.loop_rate_hz, 0.0)
        self.assertGreater(stats.steps, 1000)  # over a second of 1 ms ticks (the load, the press)
        self.assertGreater(stats.peak_force_n, 0.01)

        session.stop()
        with self.assertRaises(grpc.RpcError) as err:
            session.stats()
        self.assertEqual(err.exception.code(), grpc.StatusCode.NOT_FOUND)

    def test_a_named_tool_gets_its_own_figures(self):
        session = self.client.start("lv")
        try:
            press = session.press(depth_m=0.003, hold_s=0.05, tool="left")
            self.assertGreater(np.nanmax(press.force_n[:, 0]), 0.005)
            # Statistics are published every 100 ticks: wait for the press's last ones.
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                tools = session.tools()
                if tools and tools[0].device_samples >= 0.8 * len(press.t_s) and not tools[0].connected:
                    break
                time.sleep(0.05)
            first = tools[0]
            self.assertEqual((first.tool_id, first.slot), ("left", 0))
            self.assertFalse(first.connected)
            self.assertGreater(first.device_samples, 0.8 * len(press.t_s))
            self.assertGreater(first.pose_to_force_p99_us, 0.0)
            self.assertEqual(first.rejected_samples, 0)
            self.assertEqual(len(tools), session.stats().max_tools)
            with self.assertRaises(ValueError):
                session.press(tool="x" * 65)
        finally:
            session.stop()

    def test_bad_arguments_are_refused_before_sending(self):
        session = self.client.session("no-such-session")
        with self.assertRaises(ValueError):
            session.apply_force((float("nan"), 0, 0), (0, 0, 0), 0.1)
        with self.assertRaises(grpc.RpcError) as err:
            session.stats()
        self.assertEqual(err.exception.code(), grpc.StatusCode.NOT_FOUND)

    def test_scene_toml_text_starts_a_session(self):
        toml = """
name = "tiny"
[mesh]
builtin = "lv"
target_tets = 200
order = 1
[material]
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0
[boundary]
clamped = ["BASE"]
touchable = ["EPI"]
"""
        with self.client.start(toml=toml) as session:
            self.assertGreater(session.info.tetrahedra, 50)
        with self.assertRaises(grpc.RpcError) as err:
            self.client.start(toml="this is not a scene")
        self.assertEqual(err.exception.code(), grpc.StatusCode.INVALID_ARGUMENT)

    def test_reflection_v1alpha_lists_the_services(self):
        # grpcio-reflection speaks grpc.reflection.v1alpha.
        from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
            ProtoReflectionDescriptorDatabase,
        )

        with grpc.insecure_channel(SERVER.removeprefix("http://")) as channel:
            db = ProtoReflectionDescriptorDatabase(channel)
            services = set(db.get_services())
            self.assertIn("haptics.v1.SessionControl", services)
            self.assertIn("haptics.v1.DeviceLink", services)
            self.assertIn("haptics.v1.SurfaceStream", services)

    @unittest.skipUnless(os.environ.get("HAPTICS_MCAP"), "no MCAP recording given")
    def test_mcap_recording_decodes_with_its_own_schemas(self):
        # An independent reader (Foxglove's mcap + mcap-protobuf-support) decodes hapticctl's
        # recording from the schemas inside the file, not from our stubs.
        from mcap.reader import make_reader
        from mcap_protobuf.decoder import DecoderFactory

        counts, sim_times = {}, []
        with open(os.environ["HAPTICS_MCAP"], "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for schema, channel, _message, proto in reader.iter_decoded_messages():
                counts[channel.topic] = counts.get(channel.topic, 0) + 1
                if channel.topic == "/surface":
                    self.assertEqual(schema.name, "haptics.v1.SurfaceFrame")
                    self.assertEqual(len(proto.positions_m) % 3, 0)
                    sim_times.append(proto.sim_time_s)
                elif channel.topic == "/stats":
                    self.assertEqual(schema.name, "haptics.v1.SessionStats")
        self.assertGreater(counts.get("/surface", 0), 5, counts)
        self.assertGreater(counts.get("/stats", 0), 3, counts)
        self.assertEqual(sim_times, sorted(sim_times))

    @unittest.skipUnless(os.environ.get("HAPTICS_RECORDING"), "no recording given")
    def test_recording_reads_back(self):
        rec = read_recording(os.environ["HAPTICS_RECORDING"])
        n = len(rec["t_s"])
        self.assertGreater(n, 100)
        self.assertEqual(rec["position_m"].shape, (n, 3))
        self.assertTrue(np.all(np.diff(rec["t_s"]) > 0))
        self.assertTrue(rec["in_contact"].any())
        self.assertGreater(np.linalg.norm(rec["force_n"], axis=1).max(), 0.01)


if __name__ == "__main__":
    unittest.main(verbosity=2)
