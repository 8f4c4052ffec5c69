"""benchmarks/live_recoarse.py's replay of a live job: the refits read from its log, a recorded capture published in
its own order, and the command line's one-line refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmark_helpers import load_benchmark
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset

PROGRESS = "reconstruct (fast):   2%|▏         | 1/41 step [00:02<01:22, step=1, loss=3.96]\r"


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("live_recoarse")


def job_log(folder: Path, refits, end: str) -> Path:
    """A live job's log as the live job writes it: a line per refit, the scan's end, the final run's progress bar."""
    lines = [f"live: fitting {v} of {v + 1} published views (refit {k + 1}, {s} steps so far, level 1)"
             for k, (v, s) in enumerate(refits)]
    log = folder / "job.log"
    log.write_text("\n".join(lines + [end, PROGRESS * 3, "live: publishing the final field"]) + "\n")
    return log


def test_the_refits_of_a_live_jobs_log_are_read_with_the_final_runs_steps(bench, tmp_path):
    log = job_log(tmp_path, [(8, 0), (11, 26), (59, 1255)],
                  "live: scan complete (122 views fitted, 2566 steps); the final reconstruction continues from the "
                  "live fit, for 41 steps")
    refits = bench.read_refits(log)
    assert refits.at == ((8, 0), (11, 26), (59, 1255))
    assert (refits.end_steps, refits.final_steps) == (2566, 41)


@pytest.mark.parametrize("refits, end, says", [
    ([(8, 0), (11, 26)], "live: scan complete (11 views fitted, 40 steps); the final reconstruction starts from the "
                         "carved hull: the live fit is too young (on its coarse level, or only just past it), for the "
                         "preset's budget",
     "no live refits"),
    ([], "live: scan complete (11 views fitted, 40 steps); the final reconstruction continues from the live fit, "
         "for 10 steps", "no live refits"),
    ([(8, 0), (11, 26), (14, 12)], "live: scan complete (14 views fitted, 40 steps); the final reconstruction "
                                   "continues from the live fit, for 10 steps", "go backwards"),
])
def test_a_log_without_a_replayable_live_job_is_refused_in_one_line(bench, tmp_path, refits, end, says):
    with pytest.raises(SystemExit) as exc:
        bench.read_refits(job_log(tmp_path, refits, end))
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_a_missing_log_is_refused_in_one_line(bench, tmp_path):
    with pytest.raises(SystemExit) as exc:
        bench.read_refits(tmp_path / "nowhere.log")
    assert "cannot read it" in str(exc.value)


def recorded_capture(folder: Path) -> tuple[Path, np.ndarray]:
    """A capture as the daemon records it: three poses in visiting order, the middle one with two frames."""
    sensor = sensor_preset("tmf8820")
    poses = np.stack([np.eye(4) for _ in range(3)])
    poses[:, 0, 3] = [0.1, 0.2, 0.3]
    writer = CaptureWriter.create(folder, sensor, planned_poses=poses, chunk_size=64, frames_per_pose=2)
    hist = np.zeros((len(sensor.zones), sensor.n_bins))
    for index, frames in enumerate((1, 2, 1)):  # two frames planned a pose, one of the first and last dropped
        for frame in range(frames):
            writer.append(Measurement(hist + index, poses[index], index, frame))
    writer.finish("complete")
    return folder, poses


def test_a_recorded_capture_is_published_pose_by_pose_in_its_own_order(bench, tmp_path):
    source, poses = recorded_capture(tmp_path / "recorded")
    scan = bench.DaemonOrderScan(source, tmp_path / "published", recorded=True)
    assert scan.planned == 3
    scan.publish()
    scan.publish()  # the second pose: both its frames at once
    data = CaptureReader(tmp_path / "published").load()
    assert [m["pose_index"] for m in data.meta] == [0, 1, 1]
    np.testing.assert_allclose(data.poses[:, 0, 3], [0.1, 0.2, 0.2])
    np.testing.assert_allclose(data.hists[:, 0, 0], [0, 1, 1])


def test_a_recorded_capture_is_not_taken_for_a_simulated_default_plan(bench, tmp_path):
    source, _ = recorded_capture(tmp_path / "recorded")
    with pytest.raises(SystemExit, match="not the daemon's default plan"):
        bench.DaemonOrderScan(source, tmp_path / "published")


def call(bench, argv) -> int:
    try:
        return bench.main([str(a) for a in argv])
    except SystemExit as exc:
        return exc.code


def test_the_command_line_refuses_refits_without_their_capture_and_a_folder_without_one(bench, tmp_path, capsys):
    log = job_log(tmp_path, [(8, 0)], "live: scan complete (8 views fitted, 40 steps); the final reconstruction "
                                      "continues from the live fit, for 10 steps")
    assert call(bench, ["--refits", log]) == 2
    assert "give that capture with --capture" in capsys.readouterr().err
    assert call(bench, ["--capture", tmp_path, "--refits", log]) == 2
    assert "no capture there" in capsys.readouterr().err
    source, _ = recorded_capture(tmp_path / "recorded")  # its scene names nothing to score against
    assert call(bench, ["--capture", source, "--refits", log]) == 2
    assert "no ground truth" in capsys.readouterr().err
    simulated = tmp_path / "simulated"  # a capture with a ground truth, of three poses
    recorded_capture(simulated)
    manifest = json.loads((simulated / "scan.json").read_text())
    manifest["scene"] = {"builtin": "mug"}
    (simulated / "scan.json").write_text(json.dumps(manifest))
    many = job_log(tmp_path, [(2, 0), (5, 10)], "live: scan complete (5 views fitted, 40 steps); the final "
                                                "reconstruction continues from the live fit, for 10 steps")
    assert call(bench, ["--capture", simulated, "--refits", many]) == 2
    assert "a refit of 5 views, but --capture" in capsys.readouterr().err, "refused before any fit runs"
    (source / "scan.json").write_text("{not json")
    assert call(bench, ["--capture", source]) == 2
    err = capsys.readouterr().err
    assert f"--capture {source}:" in err and "Traceback" not in err
