"""A live job follows a scan published pose by pose (a stand-in writer publishes each pose as a chunk, as the daemon
does): it waits for enough views, fits them, refits warm as more land, publishes recon/live/ as it goes, and
finishes the complete scan from the live fit; an aborted scan ends it with the scan's reason."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import LiveStatus, read_status, status_path
from spadscan.worker.end_of_run import UNCONVERGED
from spadscan.worker.jobs import Job
from spadscan.worker.live.follower import ScanProgress
from spadscan.worker.live.job import LiveRun, LiveSettings, ScanAborted, execute_live_job, final_job, final_start

from live_helpers import ReplayScan
from worker_helpers import FAST_SMALL

DEADLINE_S = 300.0  # generous: the machine may be busy with other work


def small_settings(**changes) -> LiveSettings:
    return LiveSettings(**{"min_views": 6, "poll_s": 0.05, "publish_every_s": 0.2, "rebuild_share": 0.5,
                           "rebuild_views": 1, "preview": False, "overrides": tuple(FAST_SMALL.items()), **changes})


class LiveJobThread:
    """`execute_live_job` on a thread, with every status it published seen on the way."""

    def __init__(self, root: Path, scan: str, settings: LiveSettings, budget_s: float | None = 1.0, recon=None):
        self.root, self.capture = root, root / scan
        self.job = Job(id=f"{scan}-fast", scan=scan, live=True, budget_s=budget_s, device="cpu")
        self.out = root / scan / "recon" / ".tmp-test"
        self.result: dict = {}
        self.seen: list[LiveStatus] = []
        self.lines: list[str] = []
        """What the job logged."""
        self.recon = recon
        self.thread = threading.Thread(target=self._run, args=(settings,), daemon=True)
        self.thread.start()

    def _run(self, settings) -> None:
        try:
            self.result["report"] = execute_live_job(self.job, self.root, self.out, self.recon, settings=settings,
                                                     log=self.lines.append)
        except BaseException as exc:  # re-raised on the test's thread
            self.result["error"] = exc

    def wait_status(self, pred, what: str) -> LiveStatus:
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline:
            try:
                status = read_status(status_path(self.capture))
            except CaptureError:
                status = None
            if status is not None and (not self.seen or status != self.seen[-1]):
                self.seen.append(status)
            if status is not None and pred(status):
                return status
            if not self.thread.is_alive():
                raise AssertionError(f"the live job ended before {what}: {self.result}")
            time.sleep(0.02)
        raise AssertionError(f"no live status with {what} within {DEADLINE_S:.0f} s; last {self.seen[-1:]}")

    def join(self) -> dict:
        self.thread.join(DEADLINE_S)
        assert not self.thread.is_alive(), "the live job did not end"
        if "error" in self.result:
            raise self.result["error"]
        return self.result["report"]


def test_a_live_job_follows_a_scan_pose_by_pose_and_finishes_from_the_live_fit(cylinder_capture, tmp_path,
                                                                               one_thread):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(3)
    live = LiveJobThread(root, "cyl", small_settings())
    waiting = live.wait_status(lambda s: s.views_published == 3, "three views published")
    assert (waiting.state, waiting.views_used, waiting.steps) == ("waiting", 0, 0)

    scan.publish(5)  # 8 published: enough to fit
    first = live.wait_status(lambda s: s.state == "live" and s.views_used == 8 and s.steps > 0, "a fit of 8 views")
    assert first.views_published == 8 and first.views_planned == 24
    assert (root / "cyl" / "recon" / "live" / "mesh.ply").stat().st_size > 0

    scan.publish(16)  # all 24: a refit, warm
    grown = live.wait_status(lambda s: s.views_used == 24 and s.steps > first.steps + 5, "a fit of all 24 views")
    assert grown.views_published == 24 and grown.state == "live"
    scan.finish()
    report = live.join()

    steps = [s.steps for s in live.seen]
    assert steps == sorted(steps), f"the live fit restarted: steps went {steps}"
    assert [s.views_used for s in live.seen] == sorted(s.views_used for s in live.seen)
    assert report["live"]["views_used"] == 24 and report["live"]["rebuilds"] >= 2
    assert report["live"]["steps"] >= grown.steps and report["live"]["final_budget_s"] == 1.0
    assert report["live"]["final_steps"] is None and report["live"]["final_start"] == "live"
    assert report["scene"]["views"] == 24 and report["capture_state"] == "complete"
    # The better-fitting of the live and the final field is published; a mesh that the job's 1 s budget made coarser
    # than the preset's says so.
    published = report["published"]
    better = "live" if published["deviance_live"] < published["deviance_final"] else "final"
    assert published["mesh"] == better
    if report["mesh_resolution"] < 256:
        assert any("cells a side" in note for note in report["budget"]["notes"]), report["budget"]
    saved = json.loads((live.out / "report.json").read_text())
    assert saved["live"]["views_used"] == 24 and saved["published"] == published
    assert (live.out / "mesh.ply").stat().st_size > 0
    final = read_status(status_path(root / "cyl"))
    assert final.state == "final" and final.views_used == 24 and final.views_published == 24
    assert final.final_start == report["live"]["final_start"], "the status says where the final run starts"
    leftovers = [p.name for p in (root / "cyl" / "recon" / "live").iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_with_no_budget_the_final_run_polishes_for_steps_and_says_nothing_of_a_short_budget(cylinder_capture, tmp_path,
                                                                                          one_thread):
    """A live job whose job names neither a budget nor steps (the worker's default): the final run takes the live
    fit's recent step rate times `final_polish_s` in steps, and the stages after it run in full: no line about a
    coarse mesh or few metric points, nor about a rough early state (it went on from the live fit). Its trace has
    its start and its end only (`final_checkpoints`): with a ground truth each checkpoint meshes and scores."""
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(10)
    live = LiveJobThread(root, "cyl", small_settings(final_polish_s=0.5, final_min_steps=7), budget_s=None)
    live.wait_status(lambda s: s.state == "live" and s.steps > 20, "a fit")
    scan.publish(14)
    live.wait_status(lambda s: s.views_used == 24, "a fit of all 24 views")  # else the final run starts from the hull
    scan.finish()
    report = live.join()
    assert report["live"]["final_budget_s"] is None and report["live"]["final_steps"] >= 7
    assert report["steps"] == report["live"]["final_steps"] and report["stopped_by"] in ("steps", "converged")
    assert [c["step"] for c in report["trace"]] == [0, report["steps"]], report["trace"]
    assert report["budget"]["notes"] == [] and report["budget"]["budget_s"] is None
    assert not [w for w in report["warnings"] if "rough early state" in w or "time budget" in w], report["warnings"]
    # A polish the live job chose itself: too short for the plateau test, no "did not converge" line either.
    assert not [w for w in report["warnings"] if w.startswith(UNCONVERGED)], report["warnings"]


def test_the_final_run_is_bounded_by_the_jobs_own_budget_or_steps_else_by_the_live_rate():
    rates = SimpleNamespace(recent_steps_per_s=lambda: 20.0, steps_per_s=lambda: 50.0)
    job = Job(id="s-fast", scan="s", live=True)
    final, bounds = final_job(job, rates, LiveSettings(final_polish_s=6.0), "live")
    assert (final.steps, final.budget_s, final.live) == (120, None, False)
    assert bounds == {"final_budget_s": None, "final_steps": 120}
    no_recent = SimpleNamespace(recent_steps_per_s=lambda: None, steps_per_s=lambda: 5.0)
    assert final_job(job, no_recent, LiveSettings(final_polish_s=6.0), "live")[0].steps == 30, "no recent rate yet"
    slow = SimpleNamespace(recent_steps_per_s=lambda: 0.5, steps_per_s=lambda: 0.5)
    assert final_job(job, slow, LiveSettings(final_min_steps=10), "live")[0].steps == 10
    timed, bounds = final_job(dataclasses.replace(job, budget_s=30.0), rates, LiveSettings(), "live")
    assert (timed.budget_s, timed.steps) == (30.0, None) and bounds == {"final_budget_s": 30.0, "final_steps": None}
    counted, _ = final_job(dataclasses.replace(job, steps=500), rates, LiveSettings(), "live")
    assert (counted.budget_s, counted.steps) == (None, 500)
    # From the hull: the preset's own budget, not a polish.
    young, bounds = final_job(job, rates, LiveSettings(final_polish_s=6.0), "hull")
    assert (young.steps, young.budget_s, young.live) == (None, None, False)
    assert bounds == {"final_budget_s": None, "final_steps": None}
    assert final_job(dataclasses.replace(job, budget_s=30.0), rates, LiveSettings(), "hull")[0].budget_s == 30.0, \
        "the job's own budget still bounds it"


def test_only_the_steps_the_live_job_chose_make_its_final_run_a_polish(tmp_path):
    """A polish (too short for the plateau test: no "did not converge" line) is the step count the live job chose
    itself; the steps the user asked for (`worker --live --steps 3000`) or a budget make a run judged as any."""
    from spadscan.worker.live.job import chose_polish
    from spadscan.worker.reconstruct import reconstruct_capture

    rates = SimpleNamespace(recent_steps_per_s=lambda: 20.0, steps_per_s=lambda: 50.0)
    job = Job(id="s-fast", scan="s", live=True)
    for asked, start, polish in ((job, "live", True), (dataclasses.replace(job, steps=3000), "live", False),
                                 (dataclasses.replace(job, budget_s=30.0), "live", False), (job, "hull", False)):
        final, _ = final_job(asked, rates, LiveSettings(final_polish_s=6.0), start)
        assert chose_polish(asked, final) is polish, (asked, start)
    # The final run's reconstruction is told, for its report's checks (end_of_run.RunFacts.polish).
    run = LiveRun(job, tmp_path, tmp_path / "recon" / "live", follower=None, settings=small_settings(), log=print)
    run.fit = SimpleNamespace(live_state=lambda: None, warm_factory=lambda from_live: None)
    for polish in (True, False):
        recon = run.final_recon(None, True, polish)
        assert recon.func is reconstruct_capture and recon.keywords["polish"] is polish


@pytest.mark.parametrize("continuable, used, views, start", [
    (True, 48, 48, "live"),
    (True, 46, 48, "live"),
    (True, 107, 128, "live"),  # a steady scan's end: 21 left out, under a quarter of 107 (27)
    (True, 103, 128, "live"),  # 25 left out, one under a quarter of 103 (26)
    (True, 102, 128, "hull"),  # 26 left out: a quarter of 102, rounded up
    (True, 26, 48, "hull"),  # a pause and a fast resume: 22 views left out
    (False, 48, 48, "hull"),  # too young on its level
])
def test_the_final_run_continues_only_from_a_live_fit_of_all_but_a_few_of_the_scans_views(continuable, used, views,
                                                                                          start):
    fit = SimpleNamespace(continuable=continuable, views_used=used)
    where, why = final_start(fit, views, LiveSettings())
    assert where == start
    if start == "live":
        assert why is None
    elif continuable:
        assert why == f"the live fit holds {used} of the scan's {views} views (the scan ended before its next refit)"
    else:
        assert "too young" in why


def test_a_scan_that_ends_before_the_live_fit_takes_its_last_views_is_finished_from_the_hull(cylinder_capture,
                                                                                            tmp_path, one_thread):
    """The live fit of 10 views never refits (its refits may take a millionth of the time): the scan's other 14
    views land, the scan ends, and the final run starts from the carved hull, not from the fit of 10 views."""
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(10)
    live = LiveJobThread(root, "cyl", small_settings(rebuild_share=1e-6))
    live.wait_status(lambda s: s.state == "live" and s.views_used == 10 and s.steps > 20, "a fit of 10 views")
    scan.publish(14)
    scan.finish()
    report = live.join()
    assert report["live"]["views_used"] == 10 and report["live"]["final_start"] == "hull"
    assert report["scene"]["views"] == 24
    said = [line for line in live.lines if "the final reconstruction" in line]
    assert said and said[0].endswith("starts from the carved hull: the live fit holds 10 of the scan's 24 views "
                                     "(the scan ended before its next refit), for 1 s"), said


def test_an_aborted_scan_ends_its_live_job_with_the_reason(cylinder_capture, tmp_path, one_thread):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(8)
    live = LiveJobThread(root, "cyl", small_settings())
    fitted = live.wait_status(lambda s: s.state == "live" and s.steps > 0, "a fit")
    scan.finish("aborted", "the operator stopped the arm")
    with pytest.raises(ScanAborted, match="the operator stopped the arm") as err:
        live.join()
    assert "\n" not in str(err.value) and "recon/live" in str(err.value)
    status = read_status(status_path(root / "cyl"))
    assert status.state == "aborted" and "the operator stopped the arm" in status.note
    assert status.steps >= fitted.steps
    assert (root / "cyl" / "recon" / "live" / "mesh.ply").exists()  # the last live result stays
    assert not (live.out / "report.json").exists()


def stand_in(scan_dir, out, **options):
    """The ordinary reconstruction's stand-in: records what it was asked for."""
    Path(out, "report.json").write_text(json.dumps(options))
    return {"asked": options}


def test_a_scan_that_completes_before_enough_views_is_reconstructed_from_scratch(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(2)
    live = LiveJobThread(root, "cyl", small_settings(min_views=100), budget_s=7.0, recon=stand_in)
    live.wait_status(lambda s: s.state == "waiting", "the job waiting")
    scan.publish(22)
    scan.finish()
    report = live.join()
    assert report["asked"]["budget_s"] == 7.0 and "live" not in report  # the job's budget, from the job's start
    assert report["asked"]["started"] <= time.perf_counter()
    status = read_status(status_path(root / "cyl"))
    assert status.state == "final" and "from scratch" in status.note and status.views_published == 24


def test_a_live_job_of_a_complete_scan_is_an_ordinary_job_and_says_so(cylinder_capture, tmp_path):
    # A scan quicker than the worker's poll: whoever follows the live status (the demo, `ctl wait`) still sees the
    # final run, and the worker then marks it done with its result.
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(24)
    scan.finish()
    report = LiveJobThread(root, "cyl", small_settings(), budget_s=7.0, recon=stand_in).join()
    assert report["asked"]["budget_s"] == 7.0 and "live" not in report  # the job's budget, from the job's start
    assert report["asked"]["started"] <= time.perf_counter()
    status = read_status(status_path(root / "cyl"))
    assert (status.state, status.views_used, status.steps, status.views_published) == ("final", 0, 0, 24)
    assert "already complete" in status.note and status.job == "cyl-fast"


def test_a_chunk_that_cannot_be_read_stops_the_live_job_saying_why(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(2)
    live = LiveJobThread(root, "cyl", small_settings(min_views=100), recon=stand_in)
    live.wait_status(lambda s: s.state == "waiting", "the job waiting")
    bad = root / "cyl" / "chunk-000777"
    bad.mkdir()
    (bad / "hists.npy").write_bytes(b"not an array")
    with pytest.raises(CaptureError, match="chunk-000777") as err:
        live.join()
    status = read_status(status_path(root / "cyl"))
    assert status.state == "stopped" and status.note == str(err.value)


def test_the_status_never_says_more_views_used_than_published(tmp_path):
    # A refit reads the capture on its own and can hold views that the follower's last poll had not seen yet.
    class Fit:
        model, views_used, steps, converged = object(), 101, 40, False

    job = Job(id="s-fast", scan="s", live=True, device="cpu")
    (tmp_path / "recon" / "live").mkdir(parents=True)
    run = LiveRun(job, tmp_path, tmp_path / "recon" / "live", follower=None, settings=small_settings(),
                  log=lambda line: None)
    run.fit = Fit()
    polled = ScanProgress(state="running", reason=None, views_published=98, views_planned=128, new_chunks=0)
    run.write_status(polled, "live")
    status = read_status(status_path(tmp_path))
    assert (status.views_used, status.views_published, status.views_planned) == (101, 101, 128)
    run.write_status(dataclasses.replace(polled, views_published=104), "live")
    assert read_status(status_path(tmp_path)).views_published == 104


def test_a_full_disk_skips_a_publication_and_a_ranking_without_ending_the_live_job(tmp_path, monkeypatch):
    import errno

    import spadscan.worker.live.job as live_job

    class Fit:
        model, views_used, steps, converged = object(), 12, 40, False

        def mesh(self, resolution):
            return "a mesh"

        def remember(self):
            self.remembered = True

        def snapshot(self):
            return "a snapshot"

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    for name in ("publish_mesh", "publish_status", "update_next_views"):
        monkeypatch.setattr(live_job, name, full_disk)
    monkeypatch.setattr(live_job, "is_adaptive", lambda manifest: True)
    lines: list[str] = []
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, tmp_path / "recon" / "live",
                  follower=None, settings=small_settings(), log=lines.append)
    run.fit = Fit()
    polled = ScanProgress(state="running", reason=None, views_published=12, views_planned=128, new_chunks=0)
    run.publish(polled, force=True)
    run._rank(polled)
    assert run.fit.remembered and run.next_publish > time.monotonic() - 1, "the fit went on, and publishes later"
    assert lines == ["live: the live mesh not published this time: [Errno 28] No space left on device",
                     "live: the live status not published this time: [Errno 28] No space left on device",
                     "live: no next views this time: [Errno 28] No space left on device"], lines


def test_a_scan_that_publishes_nothing_for_long_is_said_to_be_quiet_until_it_publishes_again(tmp_path):
    import shutil

    from test_watcher import make_scan

    class Fit:
        model, views_used, steps, converged, not_yet = None, 0, 0, False, None

    make_scan(tmp_path, "s", "running")
    lines: list[str] = []
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path / "s",
                  live_folder := tmp_path / "s" / "recon" / "live", follower=None,
                  settings=small_settings(quiet_note_s=600.0), log=lines.append)
    live_folder.mkdir(parents=True)
    run.fit = Fit()
    manifest = {"updated_utc": "2026-12-03T06:00:00Z"}
    polled = ScanProgress(state="running", reason=None, views_published=3, views_planned=128, new_chunks=1,
                          manifest=manifest)
    run._note_quiet(polled, 1000.0)
    run.last = nothing_new = dataclasses.replace(polled, new_chunks=0)
    run._note_quiet(nothing_new, 1599.0)
    assert lines == [] and run.quiet_note is None, "ten minutes are not up"
    run._note_quiet(nothing_new, 1601.0)
    assert len(lines) == 1 and lines[0].startswith("live: the scan has published nothing for 10 min"), lines
    assert read_status(status_path(tmp_path / "s")).note == run.quiet_note
    run.publish(nothing_new, force=True)
    assert read_status(status_path(tmp_path / "s")).note == run.quiet_note, "every publication keeps saying so"
    run._note_quiet(dataclasses.replace(nothing_new, manifest={"updated_utc": "2026-12-03T06:20:00Z"}), 1700.0)
    assert lines[1:] == ["live: the scan publishes again"] and run.quiet_note is None
    run.publish(nothing_new, force=True)
    assert read_status(status_path(tmp_path / "s")).note is None
    shutil.move(tmp_path / "s", tmp_path / "moved")
    run.stopped("stopped", "scan.json: missing")  # the folder moved away: said in the log, no error on top
    assert lines[-1] == "live: scan.json: missing"


def test_a_ranking_counts_every_published_view_as_taken_not_only_the_fitted_ones(tmp_path):
    # The model refits only every few views; the daemon calls a ranking stale by the poses taken since its
    # pose_count, so a count of the fitted views made every ranking between two refits stale.
    from spadscan.daemon.config import ScanConfig, scan_to_dict, scan_with
    from spadscan.protocol.next_views import read_next_views
    from spadscan.protocol.schedules import fibonacci_hemisphere

    from test_view_ranking import grid, snapshot

    published = fibonacci_hemisphere(64, 0.5, (0, 0, 0), 10, 80)
    fitted = published[published[:, 0, 3] > 0.1]  # the model fits the +x views; the -x ones are published since

    class Fit:
        model = object()

        def snapshot(self):
            return snapshot([grid()], fitted)

    scan = scan_with(ScanConfig(), {"schedule": "adaptive", "views": 128, "initial_views": 8})
    manifest = {"schedule": {**scan_to_dict(scan), "candidates": 128}}
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, tmp_path / "recon" / "live",
                  follower=None, settings=small_settings(), log=lambda line: None)
    run.fit = Fit()
    run._rank(ScanProgress(state="running", reason=None, views_published=len(published), views_planned=128,
                           new_chunks=1, manifest=manifest, poses=published))
    nv = read_next_views(tmp_path)
    assert len(fitted) < nv.pose_count == len(published)
    x = nv.poses[:, 0, 3]  # the -x side, unseen by the fitted views, is seen by the published ones: no favourite
    assert nv.scores[x < -0.1].mean() < 2 * nv.scores[x > 0.1].mean(), "the published -x views count as taken"


def test_a_poll_hands_on_the_poses_of_the_views_published(cylinder_capture, tmp_path):
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.worker.live.follower import ScanFollower

    scan = ReplayScan(cylinder_capture, tmp_path / "cyl")
    follower = ScanFollower(tmp_path / "cyl")
    assert follower.poll().poses.shape == (0, 4, 4)
    scan.publish(3)
    progress = follower.poll()
    data = CaptureReader(cylinder_capture).load()
    first = data.poses[data.by_pose().first]  # each view's pose, as the reconstruction takes it
    assert progress.views_published == 3 and (progress.poses == first[:3]).all()


def test_a_quick_scan_is_ranked_every_half_its_max_lag_of_poses_not_only_every_rank_every_s(tmp_path, monkeypatch):
    import spadscan.worker.live.job as live_job

    class Fit:
        model = object()

        def snapshot(self):
            return "a snapshot"

    ranked_at: list[int] = []
    monkeypatch.setattr(live_job, "update_next_views", lambda capture, manifest, snap, poses: ranked_at.append(
        len(poses)))
    # A clock that moves a second a reading: each ranking "takes" a second, and the next call comes after the pause
    # it earns (on the real clock a ranking slowed by a busy machine made the next calls come before it ended).
    ticks = itertools.count()
    monkeypatch.setattr(live_job, "time", SimpleNamespace(monotonic=lambda: float(next(ticks))))
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, tmp_path, follower=None,
                  settings=small_settings(rank_every_s=1e6), log=lambda line: None)
    run.fit = Fit()
    manifest = {"schedule": {"schedule": "adaptive", "next_views_max_lag": 8}}
    for views in range(10, 20):
        run._rank(ScanProgress(state="running", reason=None, views_published=views, views_planned=64, new_chunks=1,
                               manifest=manifest, poses=np.zeros((views, 4, 4))))
    assert ranked_at == [10, 14, 18], "a ranking never gets a max lag behind the scan"
    run.rank_free_at = math.inf  # the last ranking took that long: the fit trains as long
    run._rank(ScanProgress(state="running", reason=None, views_published=30, views_planned=64, new_chunks=1,
                           manifest=manifest, poses=np.zeros((30, 4, 4))))
    assert ranked_at == [10, 14, 18]


def test_a_live_status_waiting_on_the_first_fit_of_enough_views_says_it_is_being_made(tmp_path):
    # After a worker restart a scan of 124 views is loaded and carved before the first fit: "waiting for views:
    # 0/124" alone read as if no view had come.
    class Fit:
        model, views_used, steps, converged, not_yet = None, 0, 0, False, None

    (folder := tmp_path / "recon" / "live").mkdir(parents=True)
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, folder, follower=None,
                  settings=small_settings(), log=lambda line: None)
    run.fit = Fit()
    polled = ScanProgress(state="running", reason=None, views_published=124, views_planned=124, new_chunks=0)
    run.publish(polled, force=True)
    status = read_status(status_path(tmp_path))
    assert (status.state, status.views_used, status.views_published) == ("waiting", 0, 124)
    assert status.note == "making the first fit of 124 views (loading them, carving their hull)"
    run.publish(dataclasses.replace(polled, views_published=3), force=True)
    assert read_status(status_path(tmp_path)).note is None, "too few views: waiting is all there is to say"
    run.fit.not_yet = "no live fit yet: no hull"
    run.publish(polled, force=True)
    assert read_status(status_path(tmp_path)).note == "no live fit yet: no hull", "a failed first fit says why"


def test_the_log_never_says_more_views_fitted_than_published(tmp_path):
    # A refit reads the capture on its own and can hold views that the follower's last poll had not seen yet.
    class Fit:
        model, views_used, steps, converged, not_yet, rebuilds = None, 0, 0, False, None, 0

        def rebuild(self, views_planned):
            self.model, self.views_used, self.rebuilds = SimpleNamespace(level=0), 22, self.rebuilds + 1
            self.scene = SimpleNamespace(counts=torch.zeros(22, 9, 128), valid=torch.ones(22, 9, 128, dtype=torch.bool))
            return True

        def mesh(self, resolution):
            raise CaptureError("no surface yet")

        def remember(self):
            pass

        def train(self, until):
            return 0

    polled = ScanProgress(state="running", reason=None, views_published=21, views_planned=24, new_chunks=1)
    ended = dataclasses.replace(polled, state="complete", views_published=24)
    (folder := tmp_path / "recon" / "live").mkdir(parents=True)
    lines: list[str] = []
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, folder,
                  follower=SimpleNamespace(poll=lambda: ended), settings=small_settings(), log=lines.append)
    run.fit = Fit()
    assert run.follow(polled) is ended
    assert [line for line in lines if "fitting" in line] == [
        "live: fitting 22 of 22 published views (refit 1, 0 steps so far, coarse level)"], lines
