"""`spadscan demo`, the whole loop (daemon -> capture -> worker -> mesh) as real processes: it finishes with a summary
and leaves no process behind; Ctrl-C during the scan stops every process it started."""

from __future__ import annotations

import json
import math
import re
import signal
from pathlib import Path

import pytest

from e2e_helpers import processes_mentioning, spadscan, spadscan_argv, wait_for
from spadscan.protocol.capture_reader import CaptureReader


@pytest.mark.slow
@pytest.mark.parametrize("arm, sensor", [("sim", "lcspc-sim"), ("ur-sim", "tmf8820")])
def test_demo_finishes_with_a_summary_and_no_process_left(tmp_path, arm, sensor):
    """The README's demo as it is, and the demo with both other devices at once (a demo costs half a minute):
    ur-sim, the real ur_rtde client (in its own process) against the simulated UR controller; tmf8820, the simulated
    3x3-zone sensor, whose captures the worker must still treat as simulated (no table, no estimated background),
    though the model carries reference histograms like the hardware."""
    out = tmp_path / "demo"
    r = spadscan("demo", "--out", out, "--views", 8, "--budget-s", 10, "--arm", arm, "--sensor", sensor,
                 timeout=480)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert isinstance(summary["chamfer_mm"], float) and math.isfinite(summary["chamfer_mm"])
    assert summary["chamfer_mm"] > 0
    for key in ("mesh", "report"):
        assert Path(summary[key]).is_file(), f"summary {key}: {summary[key]} does not exist"
    assert Path(summary["mesh"]).parent == Path(summary["report"]).parent
    report = json.loads(Path(summary["report"]).read_text())
    assert report["scene"]["sensor"] == sensor and report["scene"]["real"] is False
    assert report["scene"]["table"] is None and report["scene"]["background"] == "sensor model"
    stages = summary["seconds"]
    assert {"start_s", "scan_s", "reconstruct_s", "total_s"} <= set(stages)
    assert all(isinstance(v, (int, float)) and v >= 0 for v in stages.values())
    assert stages["total_s"] >= stages["scan_s"] + stages["reconstruct_s"]
    assert summary["mesh"] in r.stdout and "chamfer" in r.stdout
    # Live by default; 8 views scan in about a second, often before the worker's first look: the job may then run
    # as an ordinary one (tests/e2e/test_live_demo.py covers what the demo shows of a live job).
    assert "live" in summary and "live reconstruction, final run budget 10 s" in r.stderr
    capture = CaptureReader(summary["capture"])
    assert capture.state == "complete" and len(capture.load().hists) == 8
    assert not processes_mentioning(str(out)), "the demo left a process running"
    assert not (out / "daemon.sock").exists()


def _ctrl_c_during_the_scan(procs, out: Path, views: int = 400) -> Path:
    """Run the demo into `out` and stop it with Ctrl-C once its scan has published a few poses; returns the scan's
    capture folder, left 'running' (resumable)."""
    demo = procs.start(spadscan_argv("demo", "--out", out, "--views", views, "--budget-s", 10), "demo")
    wait_for(lambda: list(out.glob("captures/*/chunk-000002")) or demo.poll() is not None,
             "the scan to publish a few poses", 120, poll_s=0.05)
    assert demo.poll() is None, procs.log(demo)
    started = {pid: cmd for pid, cmd in processes_mentioning(str(out)).items() if pid != demo.pid}
    assert any(" daemon " in cmd for cmd in started.values()), started
    demo.send_signal(signal.SIGINT)
    assert demo.wait(timeout=90) == 130, procs.log(demo)
    wait_for(lambda: not processes_mentioning(str(out)), "every process of the demo to stop", 30, poll_s=0.1)
    assert "Traceback" not in procs.log(demo)
    (capture,) = out.glob("captures/*/scan.json")
    return capture.parent


@pytest.mark.slow
def test_ctrl_c_during_the_scan_stops_every_process(tmp_path, procs):
    out = tmp_path / "demo"
    reader = CaptureReader(_ctrl_c_during_the_scan(procs, out))
    assert reader.state == "running", "stopped during the scan: the capture stays resumable"
    assert len(reader.load().hists) < 400
    assert not (out / "daemon.sock").exists()


@pytest.mark.slow
@pytest.mark.parametrize("torn", [False, True], ids=["taken-over", "torn-chunk"])
def test_a_rerun_after_ctrl_c_keeps_the_earlier_scan_aborted_and_scans_anew(tmp_path, procs, torn):
    """A demo stopped during its scan leaves it 'running'. Its rerun's daemon takes it over, paused, and would refuse
    the new scan, with no daemon left afterwards to resume or abort it: the rerun aborts it through its daemon,
    every pose kept, says so, and scans anew. A torn chunk (a power cut) keeps the daemon from taking the scan over:
    the rerun aborts it all the same, as it stands on disk. That rerun is offline: its `worker --once` also runs the
    earlier live job, which ends failed with the aborted scan, and the demo's own job counts."""
    out = tmp_path / "demo"
    earlier = _ctrl_c_during_the_scan(procs, out)
    chunks = sorted(p.name for p in earlier.glob("chunk-*"))
    published = len(CaptureReader(earlier).load().hists)
    if torn:
        (earlier / chunks[0] / "hists.npy").write_bytes(b"")
    r = spadscan("demo", "--out", out, "--views", 4, "--budget-s", 5, *(["--offline"] if torn else []), timeout=480)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    said = (f"its scan {earlier.name}, which the daemon could not take over (daemon.log says why), is kept aborted"
            if torn else f"its scan {earlier.name} ({published} of 400 poses) is kept aborted")
    assert f"an earlier demo run was interrupted: {said}; starting a new one\n" in r.stderr, r.stderr[-3000:]
    reader = CaptureReader(earlier)
    assert reader.state == "aborted" and "an earlier demo run was interrupted" in reader.manifest["reason"]
    assert sorted(p.name for p in earlier.glob("chunk-*")) == chunks, "every chunk of the earlier scan stays"
    if not torn:
        assert len(reader.load().hists) == published
    summary = json.loads((out / "summary.json").read_text())
    assert Path(summary["capture"]) != earlier and CaptureReader(summary["capture"]).state == "complete"
    assert not processes_mentioning(str(out)), "the demo left a process running"


@pytest.mark.slow
@pytest.mark.parametrize("offline", [True, False], ids=["offline", "live"])
def test_a_rerun_reconstructs_a_scan_left_unreconstructed_first_and_apart(tmp_path, offline):
    """A demo stopped during its reconstruction leaves its scan complete and its job queued. The rerun's worker took
    that job first, silently, inside the new scan's reconstruction: one bar ran through both jobs, and the summary's
    time covered both and named only the new scan. The rerun reconstructs it first, on its own line and bar, and its
    own worker runs only its own scan's job."""
    from spadscan.demo import record_started
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    out = tmp_path / "demo"
    earlier = out / "captures" / "demo-20261205-060000"
    assert spadscan("simulate", "builtin:demo", "--out", earlier, "--views", 4, "--no-progress").returncode == 0
    record_started(out, earlier.name)
    Queue.for_root(out / "captures").enqueue(Job(id=f"{earlier.name}-fast", scan=earlier.name, budget_s=5.0))
    r = spadscan("demo", "--out", out, "--views", 4, "--budget-s", 5, *(["--offline"] if offline else []),
                 timeout=480)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (f"scan {earlier.name} left complete but not reconstructed: reconstructing it first, on a bar of its own "
            f"and outside this run's times (Ctrl-C leaves it for `spadscan worker --root {out / 'captures'} "
            f"--once`)\n") in r.stderr, r.stderr[-3000:]
    assert f"earlier scan {earlier.name} reconstructed: " in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert Path(summary["capture"]) != earlier and earlier.name not in summary["report"]
    assert [e["scan"] for e in summary["earlier"]] == [earlier.name] and summary["earlier"][0]["state"] == "done"
    assert Path(summary["earlier"][0]["report"]).is_file()
    assert summary["seconds"]["earlier_s"] > 0 and f"earlier:  {earlier.name}" in r.stdout
    # Two workers, one job each: the earlier scan's, then this run's (one worker ran both: "2 done, 0 failed").
    log = (out / "logs" / "worker.log").read_text()
    ends = re.findall(r"^spadscan worker: (?:stopped; )?(\d+) done, (\d+) failed", log, re.M)
    assert ends == [("1", "0"), ("1", "0")], log[-3000:]
    assert not processes_mentioning(str(out)), "the demo left a process running"


def test_the_rig_config_finds_the_captures_from_a_relative_output_folder(tmp_path, sock_dir, monkeypatch):
    # The README's `spadscan demo` writes to ./spadscan-demo: the daemon reads the rig config's paths relative to
    # the config's own folder, so a path relative to the working folder would point one level too deep.
    from spadscan.daemon.config import load_config
    from spadscan.demo import DemoOptions, write_rig_config

    monkeypatch.chdir(tmp_path)
    out = Path("spadscan-demo")
    out.mkdir()
    # The socket in the short sock_dir: under a long TMPDIR, one in tmp_path is refused as too long.
    config = load_config(write_rig_config(DemoOptions(out=out), out / "captures", sock_dir / "d.sock", None))
    assert Path(config.captures).resolve() == (tmp_path / "spadscan-demo" / "captures").resolve()
