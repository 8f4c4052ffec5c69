"""The scan runner driving the UR backend (the real ur_rtde client) against the simulated UR controller on loopback,
with a simulated sensor: the moves arrive at the planned TCP poses, a protective stop pauses the scan."""

from __future__ import annotations

import asyncio
import gc
import itertools
import os
import time

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.backends import TrackedArm, build_devices
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_plan import tcp_from_sensor
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import DeviceError

pytest.importorskip("spadscan.daemon.arm.ur")
pytest.importorskip("rtde_control")

HAND_EYE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.045], [0, 0, 0, 1]]
_hosts = itertools.count(1)


@pytest.fixture
def controller():
    from spadscan.daemon.ursim.remote import SimURProcess

    for _ in range(10):
        try:
            sim = SimURProcess(f"127.78.{os.getpid() % 250}.{next(_hosts) % 240 + 1}", time_scale=0.05)
            break
        except DeviceError:  # address in use
            continue
    else:
        raise AssertionError("no free loopback address for the simulated controller")
    yield sim
    gc.collect()  # let go of ur_rtde's interfaces before the controller goes
    sim.close()


async def until(pred, what: str, timeout_s: float = 60.0) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout_s, f"timed out waiting for {what}"
        await asyncio.sleep(0.01)


@pytest.mark.slow
def test_scan_on_the_ur_controller_with_a_protective_stop(tmp_path, controller, arun):
    cfg = config_from_dict({
        "captures": str(tmp_path / "caps"), "socket": str(tmp_path / "s.sock"),
        "arm": {"backend": "ur", "host": controller.host, "speed": 0.5, "acceleration": 2.0, "hand_eye": HAND_EYE,
                "workspace_min": [0.0, -0.5, 0.02], "workspace_max": [0.9, 0.5, 0.7], "min_reach_m": 0.1,
                "max_reach_m": 0.85, "move_timeout_s": 30.0},
        "sensor": {"backend": "sim", "mesh": "builtin:pyramid", "mesh_offset_m": [0.4, 0, 0], "rays_per_zone": 8},
        "scan": {"views": 8, "frames_per_pose": 1, "settle_s": 0.0, "radius_m": 0.25, "target": [0.4, 0, 0.05],
                 "min_elevation_deg": 30, "max_elevation_deg": 80}}, tmp_path / "rig.toml")

    async def scenario():
        arm, sensor = build_devices(cfg)
        assert isinstance(arm, TrackedArm)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("ur")
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                await asyncio.to_thread(controller.protective_stop)
                await until(lambda: runner.state == "paused", "the pause")
                reason = runner.status()["reason"]
                await asyncio.to_thread(controller.clear_protective_stop)
                await runner.resume()
                done = await runner.wait("ur")
            finally:
                await runner.shutdown()
        return reason, done, await asyncio.to_thread(lambda: controller.moves)

    reason, done, moves = arun(scenario(), timeout_s=180)
    assert "protective stop" in reason and done["state"] == "complete"
    reader = CaptureReader(tmp_path / "caps" / "ur")
    data = reader.load()
    assert sorted(data.pose_indices.tolist()) == list(range(8))
    planned_tcp = tcp_from_sensor(reader.planned_poses(), np.array(HAND_EYE))
    # Every pose was reached: the actual TCP pose recorded is the planned one (the simulated controller is exact).
    for m in data.meta:
        np.testing.assert_allclose(np.array(m["tcp_pose"]), planned_tcp[m["pose_index"]], atol=1e-5)
    # Every moveL the controller took went to a planned TCP pose (one may have been cut short by the stop and sent
    # again after resume).
    targets = [np.array(mv.target[:3]) for mv in moves if mv.name == "moveL"]
    assert len(targets) >= 8
    for t in targets:
        assert np.min(np.linalg.norm(planned_tcp[:, :3, 3] - t, axis=1)) < 1e-6
