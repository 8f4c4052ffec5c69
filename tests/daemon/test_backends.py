"""Building the rig from a config: the right backend classes, a sim sensor that renders at the arm's actual pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from spadscan.daemon.arm.sim import SimArm
from spadscan.daemon.rig import TrackedArm, build_devices, rig_record, sensor_model
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.devices import Arm, ArmState
from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_presets import sensor_preset

HAND_EYE = [[1, 0, 0, 0.01], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]
UR = {"backend": "ur", "host": "127.0.0.1", "workspace_min": [-1, -1, 0], "workspace_max": [1, 1, 1],
      "hand_eye": HAND_EYE}


def cfg_of(tmp_path, arm: dict, sensor: dict):
    # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long where
    # TMPDIR is.
    return config_from_dict({"captures": str(tmp_path / "caps"), "arm": arm, "sensor": sensor}, tmp_path / "rig.toml")


def test_sim_rig_renders_at_the_arms_actual_pose(tmp_path, arun):
    cfg = cfg_of(tmp_path, {"backend": "sim", "hand_eye": HAND_EYE, "motion_time_s": 0},
                 {"backend": "sim", "mesh": "builtin:sphere", "rays_per_zone": 8, "cycles": 1000, "ambient": 1e-5,
                  "power": 2.0})
    arm, sensor = build_devices(cfg)
    assert isinstance(arm, SimArm) and type(sensor).__name__ == "SimSensor"
    base = sensor_preset("tmf8820")
    assert sensor.model.cycles == 1000 and sensor.model.background == 1e-5
    assert sensor.model.signal_scale == pytest.approx(2 * base.signal_scale)
    assert sensor_model(cfg) == sensor.model  # what the captures store is what is simulated

    async def scenario():
        goal = np.eye(4)
        goal[:3, :3] = np.diag([1.0, -1.0, -1.0])
        goal[:3, 3] = [0.1, 0.2, 0.5]
        await arm.move_to(goal, 0.1, 0.5)
        await sensor.prepare()
        frame = await sensor.next_frame(5.0)
        await sensor.release()
        return goal, np.array(frame.extra["render_pose"])

    goal, rendered = arun(scenario())
    np.testing.assert_allclose(rendered, goal @ np.array(HAND_EYE), atol=1e-12)


class BareArm(Arm):
    """An arm without `actual_pose` (like the UR backend)."""

    def __init__(self):
        self.pose = np.eye(4)
        self.name = "bare arm"

    async def move_to(self, tcp_pose, speed, accel):
        self.pose = np.array(tcp_pose, float)

    async def state(self):
        return ArmState(self.pose + 0.0, np.zeros(6), 0.0)

    async def stop(self):
        pass


def test_tracked_arm_remembers_the_latest_pose(arun):
    tracked = TrackedArm(BareArm())
    assert tracked.name == "bare arm"
    goal = np.eye(4)
    goal[:3, 3] = [0.3, 0.0, 0.4]

    async def scenario():
        await tracked.move_to(goal, 0.1, 0.5)
        after_move = tracked.actual_pose()
        tracked.inner.pose[0, 3] = 0.31  # the arm reports a slightly different actual pose
        await tracked.state()
        return after_move, tracked.actual_pose()

    after_move, after_state = arun(scenario())
    np.testing.assert_allclose(after_move, goal)
    assert after_state[0, 3] == 0.31


def test_hardware_backends_are_built_without_touching_hardware(tmp_path):
    arm, sensor = build_devices(cfg_of(tmp_path, UR, {"backend": "serial", "port": "/dev/ttyNOPE", "baud": 115200}))
    assert type(arm).__name__ == "URArm" and type(sensor).__name__ == "SerialSensor"
    image = tmp_path / "app.hex"
    image.write_text(":00000001FF\n")
    cfg = cfg_of(tmp_path, UR, {"backend": "i2c", "bus": 7, "firmware": str(image)})
    arm, sensor = build_devices(cfg)
    assert type(sensor).__name__ == "I2CSensor"
    rig, scene = rig_record(cfg)
    assert rig["arm"]["host"] == "127.0.0.1" and rig["sensor"]["bus"] == 7 and scene == {}
    # A UR arm with a simulated sensor: the sensor needs the arm's pose, so the arm is tracked.
    cfg = cfg_of(tmp_path, UR, {"backend": "sim", "mesh": "builtin:cup", "rays_per_zone": 8,
                                "mesh_offset_m": [0.4, 0, 0]})
    arm, sensor = build_devices(cfg)
    assert isinstance(arm, TrackedArm) and type(arm.inner).__name__ == "URArm"
    assert rig_record(cfg)[1]["builtin"] == "cup" and rig_record(cfg)[1]["mesh_offset_m"] == [0.4, 0, 0]


def test_unknown_builtin_scene_is_a_config_error(tmp_path):
    cfg = cfg_of(tmp_path, {"backend": "sim"}, {"backend": "sim", "mesh": "builtin:teapot"})
    with pytest.raises(ConfigError, match=r"rig.toml: \[sensor\] mesh: unknown built-in scene 'teapot'"):
        build_devices(cfg)


def test_every_backend_module_is_registered_by_its_name():
    """The registry is the package: each module that defines BACKEND is found under the name it declares, with
    its own keys (none shadowing a key every backend shares) and the methods the daemon calls."""
    import importlib
    import pkgutil

    from spadscan.daemon import backends
    from spadscan.daemon.backends import ARM_BACKENDS, SENSOR_BACKENDS, ArmBackend, SensorBackend
    from spadscan.daemon.config import ArmConfig, SensorConfig
    from spadscan.daemon.config_keys import key_names

    declared = [getattr(importlib.import_module(f"spadscan.daemon.backends.{m.name}"), "BACKEND", None)
                for m in pkgutil.iter_modules(backends.__path__)]
    declared = {cls for cls in declared if cls is not None}
    assert declared == {*ARM_BACKENDS.values(), *SENSOR_BACKENDS.values()}
    assert sorted(ARM_BACKENDS) == ["sim", "ur"] and sorted(SENSOR_BACKENDS) == ["i2c", "serial", "sim"]
    for registry, base, section in ((ARM_BACKENDS, ArmBackend, ArmConfig), (SENSOR_BACKENDS, SensorBackend,
                                                                           SensorConfig)):
        for name, cls in registry.items():
            assert cls.name == name and issubclass(cls, base) and cls.build is not base.build
            assert not set(key_names(cls)) & set(key_names(section)), f"{name} shadows a common key"


def test_the_section_keeps_the_chosen_backends_settings(tmp_path):
    cfg = cfg_of(tmp_path, UR, {"backend": "serial", "port": "/dev/ttyACM0"})
    assert type(cfg.arm.device).__name__ == "URArmSettings" and cfg.arm.device.host == "127.0.0.1"
    assert type(cfg.sensor.device).__name__ == "SerialSensorSettings" and cfg.sensor.device.baud == 1_000_000
    assert not hasattr(cfg.arm, "host") and not hasattr(cfg.sensor, "port")  # no flat union of every backend's keys


@pytest.mark.parametrize("arm, sensor, message", [
    ({**UR, "colour": "red"}, {"backend": "sim", "mesh": "builtin:cup"},
     r"\[arm\] unknown key 'colour' for backend 'ur' \(known: backend, speed, .*, host"),
    ({"backend": "sim"}, {"backend": "sim", "mesh": "builtin:cup", "baudrate": 9600},
     r"\[sensor\] unknown key 'baudrate' for backend 'sim'"),
    ({**UR, "time_scale": 0.5}, {"backend": "sim", "mesh": "builtin:cup"},
     r"\[arm\] time_scale applies only to backend 'sim', not 'ur'"),
    ({"backend": "sim"}, {"backend": "serial", "port": "/dev/ttyACM0", "mesh": "builtin:cup"},
     r"\[sensor\] mesh applies only to backend 'sim', not 'serial'"),
])
def test_a_key_the_chosen_backend_lacks_is_one_line_naming_it(tmp_path, arm, sensor, message):
    with pytest.raises(ConfigError, match=message) as err:
        cfg_of(tmp_path, arm, sensor)
    assert "\n" not in str(err.value)


def test_choosing_a_backend_loads_no_other_backends_library(tmp_path, sock_dir):
    """A sim rig never imports ur_rtde, pyserial or smbus2; reading any config imports none of them."""
    code = ("import sys, json\n"
            "from spadscan.daemon.config import config_from_dict\n"
            "from spadscan.daemon.rig import build_devices\n"
            "from pathlib import Path\n"
            f"cfg = config_from_dict({{'captures': {str(tmp_path / 'c')!r}, 'socket': {str(sock_dir / 's')!r}, "
            "'sensor': {'backend': 'sim', 'mesh': 'builtin:cup', 'rays_per_zone': 8}}, Path('rig.toml'))\n"
            "build_devices(cfg)\n"
            "print(json.dumps(sorted(m for m in ('rtde_control', 'rtde_receive', 'serial', 'smbus2') "
            "if m in sys.modules)))\n")
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_the_rig_record_names_its_config_by_its_whole_path(tmp_path, monkeypatch):
    """`spadscan daemon --config rig.toml` started in its folder: the dashboard's hint to start a daemon again read
    `spadscan daemon --config rig.toml`, which fails from any other folder."""
    monkeypatch.chdir(tmp_path)
    cfg = config_from_dict({"captures": "caps", "sensor": {"backend": "sim", "mesh": "builtin:sphere"}},
                           Path("rig.toml"))
    rig, _ = rig_record(cfg)
    assert rig["config"] == str(tmp_path / "rig.toml")
