"""Rig configs: the examples load, every problem is one line naming the file and key, and nothing moves."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from spadscan.cli import main
from spadscan.daemon.arm.pose_convert import pose_to_vector
from spadscan.daemon.config import ScanConfig, config_from_dict, load_config, scan_request, scan_with
from spadscan.daemon.scan_plan import generate_sensor_poses, tcp_from_sensor
from spadscan.protocol.errors import ConfigError

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

# SIM's socket lies beside the config: a test whose config gets as far as the socket's checks writes it into its
# short sock_dir, as tmp_path, under a long TMPDIR, makes the socket's path longer than the 107 bytes it may have.
SIM = """
captures = "caps"
socket = "ctl.sock"
[arm]
backend = "sim"
motion_time_s = 0.0
[sensor]
backend = "sim"
mesh = "builtin:sphere"
[scan]
views = 8
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def error_of(tmp_path: Path, text: str) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text))
    msg = str(info.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("name", ["rig-sim.toml", "rig-ur.toml", "rig-serial.toml"])
def test_examples_load(name):
    cfg = load_config(EXAMPLES / name)
    assert cfg.arm.hand_eye.shape == (4, 4)
    assert cfg.scan.views >= 1


@pytest.mark.parametrize("name", ["rig-sim.toml", "rig-ur.toml", "rig-serial.toml", "rig-i2c.toml"])
def test_examples_listen_where_ctl_looks(name, tmp_path, sock_dir, monkeypatch):
    """`spadscan ctl scan` with no --socket must reach a daemon started from any example."""
    from spadscan.daemon.client import default_socket_path

    monkeypatch.delenv("SPADSCAN_SOCKET", raising=False)
    image = tmp_path / "app.hex"
    image.write_text(":00000001FF\n")
    text = (EXAMPLES / name).read_text().replace("/home/lab/tmf8820/tmf8820_app.hex", str(image))
    assert load_config(write(tmp_path, text)).socket == Path(default_socket_path())
    monkeypatch.setenv("SPADSCAN_SOCKET", str(sock_dir / "env.sock"))
    assert load_config(write(tmp_path, text)).socket == sock_dir / "env.sock" == Path(default_socket_path())


def test_i2c_example_needs_the_users_firmware(tmp_path):
    text = (EXAMPLES / "rig-i2c.toml").read_text()
    msg = error_of(tmp_path, text)
    assert "firmware" in msg and "no such file" in msg and "rig.toml" in msg
    image = tmp_path / "app.hex"
    image.write_text(":00000001FF\n")
    cfg = load_config(write(tmp_path, text.replace("/home/lab/tmf8820/tmf8820_app.hex", str(image))))
    assert cfg.sensor.device.firmware == image and cfg.sensor.device.address == 0x41 and cfg.sensor.device.bus == 1


def test_defaults_and_relative_paths(sock_dir):
    cfg = load_config(write(sock_dir, SIM))
    assert cfg.captures == sock_dir / "caps"
    assert cfg.socket == sock_dir / "ctl.sock"
    assert cfg.auto_resume is False
    assert cfg.scan.frames_per_pose == 1 and cfg.scan.schedule == "fibonacci"
    np.testing.assert_array_equal(cfg.arm.hand_eye, np.eye(4))


@pytest.mark.parametrize("text, words", [
    (SIM + "colour = 'red'\n", ["unknown key 'colour'"]),
    (SIM.replace("views = 8", "views = 8\nview = 3"), ["[scan]", "unknown key 'view'"]),
    (SIM.replace('backend = "sim"\nmotion', 'backend = "sim"\nspeed = -1\nmotion'), ["[arm] speed", "-1"]),
    (SIM.replace("views = 8", "views = 0"), ["[scan] views", "outside"]),
    (SIM.replace("views = 8", "views = 8\nseed = -1"), ["[scan] seed = -1 is outside [0, 9223372036854775807]"]),
    (SIM.replace("views = 8", "views = 8\nchunk_size = 0"), ["[scan] chunk_size = 0 is outside [1, 1000000]"]),
    (SIM.replace("views = 8", "views = 8\nmin_elevation_deg = 45\nmax_elevation_deg = 45"),
     ["min_elevation_deg 45 must be below max_elevation_deg 45", "equal only for one ring"]),
    (SIM.replace("views = 8", "views = 'many'"), ["[scan] views", "integer"]),
    (SIM.replace("views = 8", "views = 8\nradius_m = true"), ["radius_m", "number"]),
    (SIM.replace("views = 8", "views = 8\ntarget = [0, 0]"), ["target", "[x, y, z]"]),
    (SIM.replace("views = 8", "views = 8\nmin_elevation_deg = 50\nmax_elevation_deg = 40"), ["min_elevation_deg"]),
    (SIM.replace("views = 8", "views = 10\nschedule = 'rings'\nrings = 4"), ["multiple of rings"]),
    (SIM.replace("views = 8", "views = 8\nframes_per_pose = 8\nchunk_size = 4"), ["chunk_size", "whole"]),
    (SIM.replace("views = 8", "views = 8\nschedule = 'spiral'"), ["schedule", "'fibonacci'"]),
    (SIM.replace('backend = "sim"\nmotion', 'backend = "sim"\nhost = "10.0.0.1"\nmotion'), ["host", "'ur'"]),
    (SIM.replace('backend = "sim"\nmotion', 'backend = "ur"\nmotion'), ["motion_time_s", "'sim'"]),
    (SIM.replace('backend = "sim"\nmotion_time_s = 0.0', 'backend = "ur"'), ["host is required"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "nowhere.obj"'), ["mesh", "no such file"]),
    (SIM.replace('backend = "sim"\nmesh = "builtin:sphere"', 'backend = "serial"'), ["port is required"]),
    (SIM.replace('backend = "sim"\nmesh = "builtin:sphere"', 'backend = "serial"\nport = "/dev/x"\n'
                 'preset = "lcspc-sim"'), ["preset", "TMF8820"]),
    (SIM.replace('motion_time_s = 0.0', 'hand_eye = [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]'),
     ["hand_eye", "rigid"]),
    (SIM.replace('motion_time_s = 0.0', 'hand_eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 45], [0, 0, 0, 1]]'),
     ["hand_eye", "metres"]),
    (SIM.replace('motion_time_s = 0.0', 'workspace_min = [0, 0, 0]'), ["workspace_max", "together"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = [-3]\nsilence_s = 1'),
     ["[sensor] silence_on_frames", "outside"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = 7\nsilence_s = 1'),
     ["[sensor] silence_on_frames", "list of integers"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = [1.5]\nsilence_s = 1'),
     ["[sensor] silence_on_frames", "list of integers"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = [7]\nsilence_s = -1'),
     ["[sensor] silence_s", "outside"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = [7]\nsilence_s = "2"'),
     ["[sensor] silence_s", "number"]),
    (SIM.replace('mesh = "builtin:sphere"', 'mesh = "builtin:sphere"\nsilence_on_frames = [7]'),
     ["silence_on_frames", "needs silence_s > 0"]),
    (SIM.replace('backend = "sim"\nmesh = "builtin:sphere"', 'backend = "serial"\nport = "/dev/x"\n'
                 'silence_on_frames = [1]'), ["silence_on_frames", "'sim'"]),
    (SIM + "[arm\n", ["not valid TOML"]),
    (SIM.replace('socket = "ctl.sock"', 'socket = "' + "s" * 120 + '"'), ["107 bytes"]),
])
def test_bad_configs_are_one_line_errors_naming_file_and_key(tmp_path, text, words):
    msg = error_of(tmp_path, text)
    assert "rig.toml" in msg
    for w in words:
        assert w in msg, msg


UR = SIM.replace('backend = "sim"\nmotion_time_s = 0.0', 'backend = "ur"\nhost = "10.0.0.9"\n'
                 'workspace_min = [-1, -1, 0]\nworkspace_max = [1, 1, 1]')


def test_auto_resume_of_a_real_arm_needs_a_second_confirming_key(sock_dir):
    """auto_resume = true moves the arm after a restart with nobody watching: a simulated arm may, a real 'ur' arm
    only with [arm] allow_auto_resume = true as well."""
    assert load_config(write(sock_dir, "auto_resume = true\n" + SIM)).auto_resume
    assert not load_config(write(sock_dir, UR)).auto_resume
    msg = error_of(sock_dir, "auto_resume = true\n" + UR)
    assert "auto_resume = true would let the daemon move the real 'ur' arm by itself" in msg
    assert "[arm] allow_auto_resume = true" in msg and "rig.toml" in msg
    cfg = load_config(write(sock_dir, "auto_resume = true\n" + UR.replace("[sensor]", "allow_auto_resume = true\n"
                                                                           "[sensor]")))
    assert cfg.auto_resume and cfg.arm.device.allow_auto_resume
    assert "allow_auto_resume applies only to backend 'ur'" in error_of(
        sock_dir, SIM.replace("motion_time_s = 0.0", "allow_auto_resume = true"))


def test_the_ur_watchdog_frequency_reaches_the_arm(sock_dir):
    from spadscan.daemon.rig import build_arm

    cfg = load_config(write(sock_dir, UR.replace("[sensor]", "watchdog_hz = 10\n[sensor]")))
    assert build_arm(cfg).watchdog_hz == 10.0
    assert build_arm(load_config(write(sock_dir, UR))).watchdog_hz == 2.0
    assert "watchdog_hz = 0.1 (Hz) is outside [0.5, 100]" in error_of(
        sock_dir, UR.replace("[sensor]", "watchdog_hz = 0.1\n[sensor]"))


def test_one_ring_may_sit_at_one_elevation():
    """A single ring of views at 45 degrees: min_elevation_deg = max_elevation_deg places it."""
    from spadscan.daemon.config import ArmConfig
    from spadscan.daemon.scan_plan import build_plan

    scan = scan_with(ScanConfig(), {"schedule": "rings", "rings": 1, "views": 8, "min_elevation_deg": 45.0,
                                    "max_elevation_deg": 45.0, "radius_m": 0.5})
    pos = build_plan(scan, ArmConfig()).sensor_poses[:, :3, 3]
    assert len(pos) == 8 and np.allclose(pos[:, 2], 0.5 * np.sin(np.radians(45)))
    with pytest.raises(ConfigError, match="equal only for one ring"):
        scan_with(scan, {"rings": 2})


RINGS = SIM.replace("views = 8", "views = 8\nschedule = 'rings'")  # 4 rings of 2 views


@pytest.mark.parametrize("keys, line", [
    ("max_elevation_deg = 90", "max_elevation_deg 90: a ring of 2 views there stands at one viewpoint (straight "
                               "above the target); schedule 'rings' needs its rings strictly between -90 and 90 "
                               "(degrees)"),
    ("min_elevation_deg = -90", "min_elevation_deg -90: a ring of 2 views there stands at one viewpoint (straight "
                                "below the target)"),
    ("rings = 1\nmin_elevation_deg = 90\nmax_elevation_deg = 90",
     "min_elevation_deg and max_elevation_deg 90: a ring of 8 views there stands at one viewpoint"),
], ids=["top", "bottom", "one-ring"])
def test_a_ring_at_a_pole_is_refused_naming_the_file_and_key(tmp_path, capsys, keys, line):
    """`daemon --check` refuses it in the form of every other config error, with the key's own name."""
    path = write(tmp_path, RINGS.replace("[scan]", "[scan]\n" + keys))
    assert main(["daemon", "--config", str(path), "--check"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"spadscan: error: {path}: [scan] {line}") and err.count("\n") == 1, err
    with pytest.raises(ConfigError, match=r"^scan request max_elevation_deg 90: a ring of 4 views"):
        scan_request(ScanConfig(), {"schedule": "rings", "views": 16, "max_elevation_deg": 90.0})


@pytest.mark.parametrize("rings, views, lo, hi", [
    (4, 8, 10.0, 90.0), (4, 8, -90.0, 30.0), (4, 8, -90.0, 90.0), (1, 8, 90.0, 90.0), (1, 8, -90.0, 90.0),
    (4, 8, 10.0, 89.9), (8, 8, 10.0, 90.0), (2, 8, 90.0 - 1e-12, 90.0), (3, 9, 0.0, 60.0),
    (3, 9, 30.0, 30.0), (2, 8, 45.0, 45.0), (1, 8, 45.0, 45.0),
])
def test_the_config_refuses_a_ring_at_a_pole_exactly_when_the_schedule_does(rings, views, lo, hi):
    """One rule: a request `daemon --check` passes never fails later when the plan is built, and the reverse."""
    from spadscan.protocol import schedules
    from spadscan.protocol.errors import SimulationError

    def refused(call) -> bool:
        try:
            call()
        except (ConfigError, SimulationError):
            return True
        return False

    by_config = refused(lambda: scan_request(ScanConfig(), {"schedule": "rings", "rings": rings, "views": views,
                                                            "min_elevation_deg": lo, "max_elevation_deg": hi}))
    by_schedule = refused(lambda: schedules.elevation_rings(rings, views // rings, 0.5, (0, 0, 0), lo, hi))
    assert by_config == by_schedule


@pytest.mark.parametrize("keys, line", [
    ("min_elevation_deg = 90\nmax_elevation_deg = 90", "min_elevation_deg 90 must be below max_elevation_deg 90"),
    ("schedule = 'rings'\nrings = 2\nmin_elevation_deg = 30\nmax_elevation_deg = 30",
     "min_elevation_deg 30 must be below max_elevation_deg 30 (degrees; equal only for one ring"),
], ids=["spiral-at-the-top", "rings-in-no-band"])
def test_a_schedule_that_repeats_one_pose_is_refused_by_the_check(tmp_path, capsys, keys, line):
    """A spiral band of zero width at the zenith (one pose, views times) and several rings at one elevation: the
    schedule functions refuse them, and `daemon --check` refuses them first, in one line naming the keys."""
    path = write(tmp_path, SIM.replace("[scan]", "[scan]\n" + keys))
    assert main(["daemon", "--config", str(path), "--check"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"spadscan: error: {path}: [scan] {line}") and err.count("\n") == 1, err
    assert "Traceback" not in err


def test_a_ring_of_one_view_may_stand_at_the_zenith(sock_dir):
    """One view per ring: the top ring is a single viewpoint, not several views at one point."""
    from spadscan.daemon.scan_plan import build_plan

    cfg = load_config(write(sock_dir, RINGS.replace("[scan]", "[scan]\nrings = 8\nmax_elevation_deg = 90")))
    pos = build_plan(cfg.scan, cfg.arm).sensor_poses[:, :3, 3]
    assert len(pos) == 8 and np.isclose(pos[:, 2].max(), cfg.scan.radius_m)


@pytest.mark.parametrize("lag", [0, 1])
@pytest.mark.parametrize("schedule", ["adaptive", "fibonacci"])
def test_a_ranking_lag_below_2_is_refused_saying_why(sock_dir, lag, schedule):
    """The daemon chooses each pose while the one before it is captured: a ranking is at least 1 pose behind, so
    a lag below 2 would make every ranking stale and the adaptive scan its fallback plan without a word."""
    text = SIM.replace("views = 8", f"views = 8\nschedule = '{schedule}'\ninitial_views = 4\n"
                                    f"next_views_max_lag = {lag}")
    assert error_of(sock_dir, text) == (
        f"{sock_dir / 'rig.toml'}: [scan] next_views_max_lag {lag} must be at least 2 (poses): the daemon chooses "
        f"each pose while the one before it is still being captured, so the freshest ranking is already 1 pose "
        f"behind and a smaller value makes every ranking stale")
    assert load_config(write(sock_dir, text.replace(f"next_views_max_lag = {lag}", "next_views_max_lag = 2"))
                       ).scan.next_views_max_lag == 2


def test_a_scan_request_that_sets_rings_needs_the_rings_schedule():
    """`ctl scan --rings 3` with the Fibonacci schedule is refused rather than ignored; a [scan] table may keep
    rings for the scans that choose schedule 'rings'."""
    base = ScanConfig(rings=3)
    with pytest.raises(ConfigError, match="rings applies only to schedule 'rings', not 'fibonacci'"):
        scan_request(base, {"rings": 3})
    assert scan_request(base, {"rings": 2, "schedule": "rings", "views": 8}).rings == 2
    assert scan_request(base, {"views": 9}).rings == 3


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="absent.toml: no such config file"):
        load_config(tmp_path / "absent.toml")


def test_scan_overrides_are_validated_like_the_file():
    base = ScanConfig()
    s = scan_with(base, {"views": 12, "target": [0.1, 0, 0], "jitter_deg": 5})
    assert s.views == 12 and s.jitter_deg == 5 and s.target.tolist() == [0.1, 0, 0]
    assert base.views == 128  # the defaults are untouched (and the default is the paper rigs' 120-128)
    for bad, word in (({"view": 3}, "unknown key"), ({"views": -1}, "outside"), ({"radius_m": "far"}, "number")):
        with pytest.raises(ConfigError, match=word):
            scan_with(base, bad)


def test_cli_error_is_one_line_exit_1_and_nothing_moves(tmp_path, monkeypatch, capsys):
    """Bad key, bad value, missing file, unreachable default scan: exit 1 before any device is built."""
    import spadscan.daemon.app as app

    built = []
    monkeypatch.setattr(app, "build_devices", lambda cfg: built.append(cfg))
    cases = [SIM + "bogus = 1\n", SIM.replace("views = 8", "views = -2"),
             SIM.replace('mesh = "builtin:sphere"', 'mesh = "missing.stl"'),
             SIM.replace("motion_time_s = 0.0", "motion_time_s = 0.0\nworkspace_min = [-1, -1, 0.3]\n"
                                                 "workspace_max = [1, 1, 1]")]
    for text in cases:
        path = write(tmp_path, text)
        assert main(["daemon", "--config", str(path)]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("spadscan: error: ") and "\n" not in err, err
    assert main(["daemon", "--config", str(tmp_path / "nope.toml")]) == 1
    assert "no such config file" in capsys.readouterr().err
    assert built == [] and not (tmp_path / "ctl.sock").exists()


def test_check_flag_validates_without_devices(sock_dir, capsys):
    path = write(sock_dir, SIM)
    assert main(["daemon", "--config", str(path), "--check"]) == 0
    out = capsys.readouterr().out
    assert "ok" in out and "8 poses" in out
    assert not (sock_dir / "caps").exists()


def test_example_readme_documents_every_key():
    """Every key of every section and every backend (the registry's), so a new backend's keys are documented too."""
    from spadscan.daemon.backends import ARM_BACKENDS, SENSOR_BACKENDS
    from spadscan.daemon.config import ArmConfig, DaemonConfig, SensorConfig
    from spadscan.daemon.config_keys import key_names

    readme = (EXAMPLES / "README.md").read_text()
    for cls in (DaemonConfig, ArmConfig, SensorConfig, ScanConfig, *ARM_BACKENDS.values(), *SENSOR_BACKENDS.values()):
        for name in key_names(cls):
            assert f"`{name}`" in readme, f"examples/README.md lacks {cls.__name__}.{name}"


def test_examples_copy_runs_check(tmp_path):
    """The sim example passes `--check` from another folder; `~` is expanded."""
    shutil.copy(EXAMPLES / "rig-sim.toml", tmp_path / "rig-sim.toml")
    assert main(["daemon", "--config", str(tmp_path / "rig-sim.toml"), "--check"]) == 0
    cfg = load_config(tmp_path / "rig-sim.toml")
    assert cfg.captures == Path.home() / "spadscan-captures"


def test_config_from_dict_rejects_non_table_section(tmp_path):
    with pytest.raises(ConfigError, match=r"\[arm\] must be a table"):
        config_from_dict({"arm": 3}, tmp_path / "rig.toml")


def test_a_hand_eye_typed_to_four_decimals_plans_targets_the_arm_accepts(sock_dir):
    """A 30-degree turn typed from a drawing (cos 30 = 0.8660) is rigid to 1e-4, which the config accepts; the arm's
    pose conversion wants rotations orthonormal to 1e-6, so the reader projects it onto the nearest rotation."""
    typed = "[[0.8660, -0.5, 0, 0], [0.5, 0.8660, 0, 0], [0, 0, 1, 0.045], [0, 0, 0, 1]]"
    cfg = load_config(write(sock_dir, SIM.replace("[arm]\n", f"[arm]\nhand_eye = {typed}\n")))
    x = cfg.arm.hand_eye
    assert np.abs(x[:3, :3].T @ x[:3, :3] - np.eye(3)).max() < 1e-12
    assert np.abs(x - np.array(json.loads(typed))).max() < 1e-4  # the nearest rotation: the typed one, to its digits
    for pose in tcp_from_sensor(generate_sensor_poses(cfg.scan), x):
        pose_to_vector(pose)  # raises DeviceError for a rotation off by more than 1e-6
