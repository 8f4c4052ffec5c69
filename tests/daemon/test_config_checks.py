"""Rig config checks across keys and tables: simulated timings that can never beat their timeouts, and a mistyped
table name, are refused by `daemon --check` in one line that names what to change."""

from __future__ import annotations

from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.daemon.config import load_config

# RIG's socket lies beside the config: a test whose config gets as far as the socket's checks writes it into its
# short sock_dir, as tmp_path, under a long TMPDIR, makes the socket's path longer than the 107 bytes it may have.
RIG = """
captures = "caps"
socket = "ctl.sock"
[arm]
backend = "sim"
{arm}
[sensor]
backend = "sim"
mesh = "builtin:sphere"
{sensor}
[scan]
views = 8
"""


def rig(tmp_path: Path, arm: str = "", sensor: str = "", top: str = "", tail: str = "") -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(top + RIG.format(arm=arm, sensor=sensor) + tail)
    return p


def check_error(path: Path, capsys) -> str:
    """`daemon --check`'s error: one line, exit 1, in the shape of every config error."""
    assert main(["daemon", "--config", str(path), "--check"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"spadscan: error: {path}: "), err
    return err.strip()


# ---- timings that can never finish ---------------------------------------------------------------------------------
@pytest.mark.parametrize("sensor, words", [
    ("frame_time_s = 1.5\nframe_timeout_s = 1.0",
     "[sensor] frame_time_s 1.5 s is not under half of frame_timeout_s 1 s: the first frame begun after the arm "
     "settles can end two frame times (3 s) after it"),
    ("frame_time_s = 1.0\nframe_timeout_s = 1.0", "[sensor] frame_time_s 1 s is not under half of frame_timeout_s 1 s"),
    # Frames of 0.9 s (and 0.6 s) in a wait of 1 s: a sim rig run so paused 17 times in 40 s at 2 of 6 poses.
    ("frame_time_s = 0.9\nframe_timeout_s = 1.0", "[sensor] frame_time_s 0.9 s is not under half of frame_timeout_s"),
    ("frame_time_s = 0.6\nframe_timeout_s = 1.0", "[sensor] frame_time_s 0.6 s is not under half of frame_timeout_s"),
    # Exactly half: the last frame ends just as the wait does.
    ("frame_time_s = 0.5\nframe_timeout_s = 1.0", "[sensor] frame_time_s 0.5 s is not under half of frame_timeout_s"),
    # 3 s frames in the default 5 s wait: a daemon so configured paused at each of 4 poses.
    ("frame_time_s = 3", "[sensor] frame_time_s 3 s is not under half of frame_timeout_s 5 s"),
])
def test_a_sim_frame_longer_than_its_timeout_is_refused(tmp_path, capsys, sensor, words):
    err = check_error(rig(tmp_path, sensor=sensor), capsys)
    assert words in err and "shorten frame_time_s or lengthen frame_timeout_s" in err, err


@pytest.mark.parametrize("arm, words", [
    ("motion_time_s = 3.0\nmove_timeout_s = 1.0", "[arm] motion_time_s 3 s is not shorter than move_timeout_s 1 s"),
    ("motion_time_s = 1.0\nmove_timeout_s = 1.0", "[arm] motion_time_s 1 s is not shorter than move_timeout_s 1 s"),
    ("motion_time_s = 10.0\ntime_scale = 0.5\nmove_timeout_s = 4.0",
     "[arm] motion_time_s 10 s x time_scale 0.5 = 5 s is not shorter than move_timeout_s 4 s"),
    ("motion_time_s = 61", "[arm] motion_time_s 61 s is not shorter than move_timeout_s 60 s"),  # the default 60 s
])
def test_a_fixed_sim_move_longer_than_its_timeout_is_refused(tmp_path, capsys, arm, words):
    err = check_error(rig(tmp_path, arm=arm), capsys)
    assert words in err and "every move would time out" in err, err


@pytest.mark.parametrize("arm, sensor", [
    ("", ""),
    ("motion_time_s = 0.9\nmove_timeout_s = 1.0", "frame_time_s = 0.45\nframe_timeout_s = 1.0"),
    # A long fixed time scaled down to fit; frames whose two fit the wait.
    ("motion_time_s = 10.0\ntime_scale = 0.05\nmove_timeout_s = 1.0", "frame_time_s = 0.3\nframe_timeout_s = 1.0"),
    # Trapezoid timing: a move's time depends on its distance, so a short one fits whatever the scale.
    ("time_scale = 1000\nmove_timeout_s = 0.5", ""),
    ("motion_time_s = 0\nmove_timeout_s = 0.001", "frame_time_s = 0"),
])
def test_sim_timings_that_can_finish_are_kept(sock_dir, arm, sensor):
    cfg = load_config(rig(sock_dir, arm=arm, sensor=sensor))
    assert 2 * cfg.sensor.device.frame_time_s < cfg.sensor.frame_timeout_s


def test_a_real_arms_move_timeout_is_not_compared_with_sim_timing(sock_dir):
    """The rule is about the simulated arm's fixed timing: a real arm's move_timeout_s stands alone."""
    path = rig(sock_dir, arm="move_timeout_s = 0.001")
    text = path.read_text().replace('backend = "sim"\nmove', 'backend = "ur"\nhost = "10.0.0.9"\n'
                                    'workspace_min = [-1, -1, 0]\nworkspace_max = [1, 1, 1]\nmove')
    path.write_text(text)
    cfg = load_config(path)
    assert cfg.arm.backend == "ur" and cfg.arm.move_timeout_s == 0.001


# ---- names at the top level ----------------------------------------------------------------------------------------
TABLES = "[arm], [sensor], [scan]"
"""Every table a rig config has (daemon/config.py TABLES)."""


@pytest.mark.parametrize("tail, words", [
    ("[scna]\nviews = 3\n", "unknown table [scna], did you mean [scan]?"),
    ("[Scan]\nviews = 3\n", "unknown table [Scan], did you mean [scan]?"),
    ("[sensors]\nseed = 3\n", "unknown table [sensors], did you mean [sensor]?"),
    ("[[scna]]\nviews = 3\n", "unknown table [[scna]], did you mean [scan]?"),
    ("[gripper]\nforce = 3\n", "unknown table [gripper] (known tables:"),
])
def test_a_mistyped_table_is_called_a_table_and_the_tables_are_listed(tmp_path, capsys, tail, words):
    err = check_error(rig(tmp_path, tail=tail), capsys)
    assert words in err and f"known tables: {TABLES}" in err, err
    assert "unknown key" not in err and "captures, socket" not in err, err


@pytest.mark.parametrize("top, words", [
    ("arm_x = 1\n", "unknown key 'arm_x' (known keys: captures, socket, auto_resume;"),
    ("captres = 'x'\n", "unknown key 'captres', did you mean 'captures'? (known keys: captures, socket, auto_resume;"),
])
def test_an_unknown_top_level_key_lists_the_keys_and_the_tables(tmp_path, capsys, top, words):
    err = check_error(rig(tmp_path, top=top), capsys)
    assert words in err and f"known tables: {TABLES})" in err, err
