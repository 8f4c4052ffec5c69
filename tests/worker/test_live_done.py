"""The live status once a live job's final result is published: 'done', with that result's figures."""

from __future__ import annotations

import dataclasses
import json

from spadscan.protocol.live_status import LiveStatus, check_status
from spadscan.worker.live.done import done_status

AT_SCAN_END = LiveStatus(views_used=92, views_published=128, steps=9, converged=False, state="final",
                         updated_utc="2026-11-27T17:04:05.715+00:00", chamfer_mm=155.96, views_planned=128,
                         job="demo-fast")


def result_with(tmp_path, report) -> object:
    folder = tmp_path / "demo-fast"
    folder.mkdir()
    (folder / "report.json").write_text(report if isinstance(report, str) else json.dumps(report))
    return folder


def test_done_carries_the_final_results_figures_not_the_live_fits(tmp_path):
    result = result_with(tmp_path, {"steps": 1805, "converged": True, "chamfer_mm": 1.2449, "scene": {"views": 128}})
    done = done_status(AT_SCAN_END, result)
    assert (done.state, done.result, done.updated_utc) == ("done", str(result), "")
    assert (done.views_used, done.views_published, done.steps) == (128, 128, 9 + 1805)
    assert done.converged is True and done.chamfer_mm == 1.2449
    assert "Chamfer 1.24 mm" in done.summary() and "155.96" not in done.summary()


def test_a_final_run_from_the_hull_counts_its_own_steps_only(tmp_path):
    # The live fit's steps shaped nothing of a result whose final run started from the carved hull.
    report = {"steps": 560, "converged": False, "chamfer_mm": 1.48, "scene": {"views": 128},
              "live": {"steps": 9, "final_start": "hull"}}
    assert done_status(AT_SCAN_END, result_with(tmp_path, report)).steps == 560
    (tmp_path / "demo-fast" / "report.json").write_text(json.dumps({**report, "live": {"final_start": "live"}}))
    assert done_status(AT_SCAN_END, tmp_path / "demo-fast").steps == 9 + 560


def test_the_results_chamfer_names_no_live_mesh_of_fewer_views(tmp_path):
    # The live status named the mesh of 94 views its last Chamfer was measured on; the result's Chamfer is its own
    # mesh's, on all 128 views: the stale count would name the wrong mesh (in `ctl status` and the written status.json).
    from spadscan.protocol.live_status import read_status, write_status

    at_end = dataclasses.replace(AT_SCAN_END, views_used=96, chamfer_views=94, final_start="hull")
    report = {"steps": 560, "converged": False, "chamfer_mm": 0.93, "scene": {"views": 128},
              "live": {"final_start": "hull"}}
    done = done_status(at_end, result_with(tmp_path, report))
    assert done.chamfer_views is None and done.views_used == 128
    assert "Chamfer 0.93 mm" in done.summary() and "its mesh of" not in done.summary(), done.summary()
    (tmp_path / "live").mkdir()
    written = write_status(tmp_path / "live", done)
    assert "chamfer_views" not in json.loads(written.read_text())
    assert read_status(written).chamfer_views is None
    # A report that cannot be read leaves the live figures, the live mesh's count with its Chamfer.
    (tmp_path / "demo-fast" / "report.json").write_text("{not json")
    assert done_status(at_end, tmp_path / "demo-fast").chamfer_views == 94


def test_a_done_status_of_an_earlier_version_says_no_live_meshs_count():
    stale = dataclasses.replace(AT_SCAN_END, state="done", views_used=128, chamfer_mm=0.93, chamfer_views=94)
    assert "Chamfer 0.93 mm" in stale.summary() and "its mesh of" not in stale.summary(), stale.summary()
    live = dataclasses.replace(AT_SCAN_END, state="live", views_used=96, chamfer_views=94)
    assert "(its mesh of 94 views)" in live.summary(), "a live fit's status still names its mesh"


def test_a_result_without_a_chamfer_shows_none_rather_than_the_live_fits(tmp_path):
    done = done_status(AT_SCAN_END, result_with(tmp_path, {"steps": 40, "converged": False, "scene": {"views": 128}}))
    assert done.chamfer_mm is None and done.steps == 49 and done.converged is False
    assert "Chamfer" not in done.summary()


def test_an_unreadable_report_leaves_the_live_figures_and_still_says_done(tmp_path):
    bad_values = [json.dumps({"steps": True, "chamfer_mm": float("nan")}),
                  json.dumps({"steps": -3, "chamfer_mm": -1.0})]
    for report in ("{not json", json.dumps([1, 2]), *bad_values):
        folder = result_with(tmp_path, report)
        done = done_status(AT_SCAN_END, folder)
        assert done.state == "done" and done.result == str(folder)
        if report.startswith("{\""):  # a report with bad values: those values are not taken
            assert done.steps == 9 and done.chamfer_mm is None and done.views_used == 128
            check_status(done, "the done status")  # what the format allows: it is written, not refused
        else:
            assert (done.steps, done.chamfer_mm, done.views_used) == (9, 155.96, 92)
        (folder / "report.json").unlink()
        folder.rmdir()
    missing = done_status(AT_SCAN_END, tmp_path / "nowhere")
    assert missing.state == "done" and missing.chamfer_mm == 155.96


def settle_failed_live_job(tmp_path, status: LiveStatus, outcome: dict, returncode: int) -> LiveStatus:
    """A worker settles its live job's process that ended with `outcome` and `returncode` (the queue's last attempt)
    over a live status `status`; returns the live status then."""
    from types import SimpleNamespace

    from spadscan.protocol.live_status import read_status, status_path, write_status
    from spadscan.worker.jobs import Job
    from spadscan.worker.pool import Worker
    from spadscan.worker.worker_config import WorkerConfig

    root = tmp_path / "captures"
    live = root / "demo" / "recon" / "live"
    live.mkdir(parents=True)
    write_status(live, status)
    worker = Worker(WorkerConfig(root=root, max_attempts=1), log=lambda line: None)
    worker.queue.enqueue(Job(id="demo-fast", scan="demo", live=True, device="cpu"))
    claim = worker.queue.claim()
    (outcome_file := tmp_path / "outcome.json").write_text(json.dumps(outcome))
    worker._settle(SimpleNamespace(claim=claim, proc=SimpleNamespace(returncode=returncode),
                                   scratch=tmp_path / "scratch", outcome=outcome_file, log=tmp_path / "job.log",
                                   stopped_why=None))
    assert worker.settled == {"demo-fast": "failed"}
    return read_status(status_path(root / "demo"))


def test_a_live_job_whose_final_run_fails_says_stopped_with_the_error_not_finishing(tmp_path):
    error = "capture demo: no histogram holds a return above the noise: nothing to reconstruct"
    status = settle_failed_live_job(tmp_path, AT_SCAN_END, {"ok": False, "kind": "input", "error": error}, 1)
    assert (status.state, status.note, status.views_used) == ("stopped", error, AT_SCAN_END.views_used)


def test_a_live_job_that_crashes_for_good_says_stopped_but_an_aborted_scan_stays_aborted(tmp_path):
    status = settle_failed_live_job(tmp_path / "a", AT_SCAN_END, {}, -9)
    assert status.state == "stopped" and status.note.startswith("job process killed by SIGKILL"), status.note
    aborted = dataclasses.replace(AT_SCAN_END, state="aborted", note="scan aborted: operator")
    status = settle_failed_live_job(tmp_path / "b", aborted, {"ok": False, "kind": "input", "error": "aborted"}, 1)
    assert (status.state, status.note) == ("aborted", "scan aborted: operator")
