"""The dashboard's Reconstruction panel and scans table in a real headless browser, for what an operator misread:
the "did not converge" warning is a finished result's only (a live fit is not converged until it ends); the live
Chamfer says it is the live fit's, against the ground truth, on the views it had; while the final run runs, the
heading says so, with its progress and whether it started from the live fit or the carved hull, and a finished
result says which; the scan in hand with no result yet shows its own state, never another scan's result; a job
whose worker is gone says so in the heading and the queue's counts, as `spadscan worker --status` does."""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
import sys
from pathlib import Path

from dashboard_helpers import add_final_recon, complete_scan, serving
from page_helpers import add_pose, browser_page, start_scan
from spadscan.dashboard.server import address
from spadscan.worker.end_of_run import UNCONVERGED
from spadscan.worker.holder import Holder
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
BAR = "reconstruct (fast):  60%|######    | 6/10 s [00:06<00:04, loss=27.3, step=72]\r"


def live_status(scan_path: Path, **fields) -> None:
    live = scan_path / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    (live / "status.json").write_text(json.dumps(fields))


def running_job(root: Path, job_id: str, log_text: str, holder: Holder | None = None, live: bool = True) -> None:
    """`job_id` (a job of scan `job_id`'s first part) claimed by `holder` (this process), its log holding
    `log_text`."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=job_id, scan=job_id.split("-")[0], live=live))
    claim = queue.claim(holder or Holder.current())
    assert claim is not None and claim.job.id == job_id
    log = claim_log(queue.path, queue.job_paths()[job_id][1])
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(log_text)


def gone_holder() -> Holder:
    """A holder whose process has exited (and been reaped)."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    return Holder(**{**Holder.current().to_dict(), "pid": gone.pid, "pid_start": ""})


def wait_text(page, selector: str, text: str) -> str:
    """The text of `selector` once it holds `text`."""
    page.wait_for_function("([s, t]) => (document.querySelector(s) || {}).textContent?.includes(t)",
                           arg=[selector, text], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def pick(page, scan: str) -> None:
    page.locator(f'#scans tr[data-scan="{scan}"] a.pick').first.click()
    wait_text(page, "#viewer-name", scan + " / ")


def test_only_a_finished_result_warns_that_its_run_did_not_converge(tmp_path):
    for name, state in (("waiting", "waiting"), ("following", "live"), ("aborted", "aborted")):
        complete_scan(tmp_path / name, 1)
        live_status(tmp_path / name, views_used=0 if state == "waiting" else 16, views_published=18,
                    steps=0 if state == "waiting" else 1, converged=False, state=state)
    complete_scan(tmp_path / "done", 1)
    add_final_recon(tmp_path / "done", "done-fast")
    # As a run's report.json says it (end_of_run.UNCONVERGED): once, counted as the scans table counts it.
    (tmp_path / "done" / "recon" / "done-fast" / "report.json").write_text(
        json.dumps({"preset": "fast", "chamfer_mm": 1.0, "converged": False, "warnings": [UNCONVERGED]}))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        pick(page, "done")
        assert wait_text(page, "#viewer-notes", "the run did not converge")
        assert page.locator("#viewer-notes .warning").all_text_contents() == [UNCONVERGED]
        assert wait_text(page, "#viewer-notes .warnings-head", "warning").startswith("1 warning")
        row = page.locator('#scans tr[data-scan="done"]')
        assert row.locator("a[data-warnings]").get_attribute("data-warnings") == "1"
        assert row.locator("span.warning").all_text_contents() == [" not converged"]
        for name in ("waiting", "following", "aborted"):
            pick(page, name)
            assert "converge" not in page.locator("#viewer-notes").text_content(), name
            assert page.locator(f'#scans tr[data-scan="{name}"] .warning').count() == 0, name
    assert not seen.errors, seen.errors


def test_the_live_chamfer_says_it_is_the_live_fits_against_the_ground_truth_on_its_views(tmp_path):
    complete_scan(tmp_path / "bowl", 1)
    live_status(tmp_path / "bowl", views_used=57, views_published=60, steps=89, chamfer_mm=48.8, state="live")
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        heading = wait_text(page, "#viewer-name", "bowl")
        # 57 of the 60 views the scan has published: the fit is behind the scan, and says so
        assert heading == ("bowl / live, following the scan (fit of 57 of 60 views, 89 steps), the live fit's Chamfer "
                           "against the ground truth on its 57 views: 48.80 mm"), heading
    assert not seen.errors, seen.errors


def test_while_the_final_run_runs_the_heading_says_so_and_where_it_started(tmp_path):
    for name, start in (("bowl", "hull"), ("mug", "live")):
        complete_scan(tmp_path / name, 1)
        live_status(tmp_path / name, views_used=57, views_published=64, steps=89, chamfer_mm=48.8, state="final",
                    job=f"{name}-fast", final_start=start)
        running_job(tmp_path, f"{name}-fast", "live: refit on 57 views\n" + BAR)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        pick(page, "bowl")
        heading = wait_text(page, "#viewer-name", "step 72")
        assert heading.startswith("bowl / live, finishing: the final run on 64 views, from the carved hull (not the "
                                  "live fit), is running: reconstruct (fast): 6/10 s, step 72, loss 27.3 (lower is "
                                  "better) ["), heading
        assert "48.80" not in heading, "the live fit's figures read as the final run's"
        assert "the live fit's Chamfer against the ground truth on its 57 views: 48.80 mm" in \
            page.locator("#viewer-notes").text_content()
        pick(page, "mug")
        assert wait_text(page, "#viewer-name", "step 72").startswith(
            "mug / live, finishing: the final run on 64 views, continuing the live fit, is running: ")
        # done: the live entry gives way to its result, which says where its final run started
        for name, start in (("bowl", "hull"), ("mug", "live")):
            add_final_recon(tmp_path / name, f"{name}-fast")
            (tmp_path / name / "recon" / f"{name}-fast" / "report.json").write_text(json.dumps(
                {"preset": "fast", "chamfer_mm": 83.85, "live": {"views_used": 57, "final_start": start}}))
            live_status(tmp_path / name, views_used=64, views_published=64, steps=145, chamfer_mm=83.85,
                        state="done", job=f"{name}-fast", result=str(tmp_path / name / "recon" / f"{name}-fast"))
        assert wait_text(page, "#viewer-name", "result") == (
            "mug / fast, Chamfer to the ground truth 83.85 mm (the live reconstruction's result: its final run "
            "continued from the live fit)")
        assert page.locator('#scans tr[data-scan="bowl"] a.pick').text_content() == (
            "fast, Chamfer to the ground truth 83.85 mm (the live reconstruction's result: its final run started "
            "from the carved hull, not from the live fit)")
    assert not seen.errors, seen.errors


def test_a_final_run_whose_job_ended_says_the_queues_word_and_how_old_its_status_is(tmp_path):
    # A worker that could not write 'done' or 'failed' (a full disk) leaves the live status at 'final': its job, done
    # or failed in the queue, runs no final run, which must never read as starting, for good.
    queue = Queue.for_root(tmp_path)
    ten_min_ago = (_dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(minutes=10)).strftime("%Y-%m-%dT%H:%M:%SZ")
    for name in ("bowl", "mug"):
        complete_scan(tmp_path / name, 1)
        live_status(tmp_path / name, views_used=57, views_published=64, steps=89, state="final", job=f"{name}-fast",
                    final_start="live", updated_utc=ten_min_ago)
        queue.enqueue(Job(id=f"{name}-fast", scan=name, live=True))
    queue.finish(queue.claim(), result=str(tmp_path / "bowl" / "recon" / "bowl-fast"))
    queue.fail(queue.claim(), "out of room", retry=False)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        pick(page, "bowl")
        heading = wait_text(page, "#viewer-name", "its job")
        assert heading.startswith("bowl / live, finishing: the final run on 64 views, continuing the live fit; its job "
                                  "is done, updated 10 min ago"), heading
        pick(page, "mug")
        heading = wait_text(page, "#viewer-name", "its job")
        assert heading.startswith("mug / live, finishing: the final run on 64 views, continuing the live fit; its job "
                                  "failed, updated 10 min ago"), heading
        assert "starting" not in page.locator("#scans").text_content()
    assert not seen.errors, seen.errors


def test_the_scan_in_hand_without_a_result_shows_its_own_state_not_another_scans_result(tmp_path):
    complete_scan(tmp_path / "vase", 1)
    add_final_recon(tmp_path / "vase", "vase-fast")
    writer, poses = start_scan(tmp_path / "jug", 3)
    add_pose(writer, poses, 0)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        wait_text(page, "#current-name", "jug")
        assert wait_text(page, "#viewer-name", "jug") == "jug / no result yet: the scan is being recorded"
        assert page.locator("#viewer-preview").is_hidden() and page.locator("#viewer-links a").count() == 0
        for i in (1, 2):
            add_pose(writer, poses, i)
        writer.finish()
        assert wait_text(page, "#viewer-name", "reconstruction job") == (
            "jug / no result yet: no reconstruction job for it (a running `spadscan worker` queues it)")
        running_job(tmp_path, "jug-fast", BAR, live=False)
        assert wait_text(page, "#viewer-name", "step 72").startswith(
            "jug / no result yet: reconstructing: reconstruct (fast): 6/10 s, step 72")
        assert "vase" not in page.locator("#viewer").text_content()
        pick(page, "vase")  # another scan's result only when asked for
        assert page.locator("#viewer-name").text_content() == "vase / fast, Chamfer to the ground truth 1.00 mm"
    assert not seen.errors, seen.errors


def test_a_job_whose_worker_is_gone_says_so_in_the_heading_and_the_queue_counts(tmp_path):
    writer, poses = start_scan(tmp_path / "vase", 40)
    add_pose(writer, poses, 0)
    live_status(tmp_path / "vase", views_used=0, views_published=17, steps=0, state="waiting", job="vase-fast",
                note="making the first fit of 17 views (loading them, carving their hull)")
    running_job(tmp_path, "vase-fast", "", holder=gone_holder())
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        heading = wait_text(page, "#viewer-name", "worker")
        # it follows the scan no more, and the command that brings a worker back is this root's own
        assert heading == ("vase / live reconstruction stopped before its first fit (its worker is gone: start one "
                           f"with `spadscan worker --root {tmp_path.resolve()}`)"), heading
        assert wait_text(page, "#queue-counts", "stale") == (
            "(0 queued, 1 running (1 stale: their worker is gone), 0 done, 0 failed)")
    assert not seen.errors, seen.errors
