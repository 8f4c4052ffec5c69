"""Adaptive scans with the simulated arm and sensor: the ranked views a fresh next_views.json offers, the fallback
plan when the file is missing, stale, malformed or names poses the arm may not reach, why each pose was taken in
its measurements' meta, and the scan that ends once the live reconstruction has converged."""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from spadscan.daemon.adaptive import ViewChooser, live_converged
from spadscan.daemon.app import DeviceSession
from spadscan.daemon.config import scan_to_dict, scan_with
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_plan import build_plan
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import ConfigError
from spadscan.protocol.live_status import LiveStatus, write_status
from spadscan.protocol.schedules import look_at
from spadscan.protocol.next_views import (FILE, candidate_poses, ranked, read_next_views, view_angles_deg,
                                          write_next_views)

from test_runner import check_capture, daemon_runner, make_cfg, make_rig, until

VIEWS, INITIAL = 7, 3
ADAPTIVE = {"schedule": "adaptive", "views": VIEWS, "initial_views": INITIAL, "frames_per_pose": 1,
            "min_elevation_deg": 10.0, "max_elevation_deg": 80.0}
BOX = {"workspace_min": [-1.0, -1.0, -0.2], "workspace_max": [1.0, 1.0, 1.2]}


@pytest.fixture(scope="module")
def sphere():
    from spadscan.protocol.scenes import builtin_scene

    return builtin_scene("sphere")


def by_elevation(cfg, target) -> np.ndarray:
    """Candidates ranked highest first (a stand-in for a live reconstruction's ranking)."""
    cand = candidate_poses(scan_to_dict(cfg.scan))
    return cand, cand[:, 2, 3] - target[2]


def elevation_ranking(cfg, pose_count=0, created=None):
    cand, score = by_elevation(cfg, np.asarray(cfg.scan.target))
    return ranked(cand, score, pose_count, "elevation", created)


def run_scan(arun, cfg, sphere, name="a", before=None):
    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.start(name)
            if before is not None:  # no await since the start: the scan has not moved yet
                before(cfg.captures / name)
            done = await runner.wait(name)
            return done, runner.status()

    return arun(scenario())


def choices(data) -> list[dict]:
    return [m["view_choice"] for m in sorted(data.meta, key=lambda m: m["pose_index"])]


def test_without_a_ranking_the_scan_is_its_fibonacci_plan(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, **ADAPTIVE)
    done, status = run_scan(arun, cfg, sphere)
    assert done["state"] == "complete"
    data = check_capture(cfg.captures / "a", VIEWS, 1)
    why = choices(data)
    assert [c["why"] for c in why] == ["initial"] * INITIAL + ["fallback"] * (VIEWS - INITIAL)
    assert all(c["detail"] == f"no {FILE} yet" for c in why[INITIAL:])
    # Every pose of the Fibonacci plan of `views` poses, each once (in another order: the initial ones first).
    fib = build_plan(scan_with(cfg.scan, {"schedule": "fibonacci"}), cfg.arm).sensor_poses
    angles = view_angles_deg(data.poses, fib, cfg.scan.target)
    assert sorted(angles.argmin(axis=1).tolist()) == list(range(VIEWS)) and angles.min(axis=1).max() < 1e-6
    manifest = CaptureReader(cfg.captures / "a").manifest
    assert manifest["view_choices"] == {"fallback": VIEWS - INITIAL, "initial": INITIAL}
    assert manifest["schedule"]["schedule"] == "adaptive" and manifest["planned_poses"] == VIEWS
    assert status["last_scan"] == {"name": "a", "state": "complete"}


def test_a_fresh_ranking_is_followed_best_first_and_spaced(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, **ADAPTIVE, next_views_max_lag=100, min_view_spacing_deg=12.0)
    nv = elevation_ranking(cfg)
    done, _ = run_scan(arun, cfg, sphere, before=lambda folder: write_next_views(folder, nv))
    data = check_capture(cfg.captures / "a", VIEWS, 1)  # every pose once, each at the row schedule.npy names
    why = choices(data)
    assert [c["why"] for c in why] == ["initial"] * INITIAL + ["adaptive"] * (VIEWS - INITIAL)
    # The best-ranked views that keep 12 degrees from every pose taken before them, in rank order.
    taken = list(data.poses[:INITIAL])
    for c, pose in zip(why[INITIAL:], data.poses[INITIAL:]):
        expect = next(k for k, p in enumerate(nv.poses)
                      if view_angles_deg(p[None], np.array(taken), cfg.scan.target).min() >= 12.0)
        assert c["rank"] == expect and c["score"] == pytest.approx(nv.scores[expect])
        assert c["ranked_at_poses"] == 0 and c["measure"] == "elevation"
        np.testing.assert_allclose(pose, nv.poses[expect], atol=1e-9)
        taken.append(pose)
    assert CaptureReader(cfg.captures / "a").manifest["view_choices"] == {"adaptive": VIEWS - INITIAL,
                                                                          "initial": INITIAL}


def _stale_count(cfg, folder):
    write_next_views(folder, elevation_ranking(cfg, pose_count=0))  # lag 3 >= next_views_max_lag 3 at pose 3


def _old(cfg, folder):
    old = (dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=600)).isoformat(timespec="milliseconds")
    write_next_views(folder, elevation_ranking(cfg, created=old))


def _truncated(cfg, folder):
    write_next_views(folder, elevation_ranking(cfg))
    text = (folder / FILE).read_text()
    (folder / FILE).write_text(text[: len(text) // 2])


def _not_rigid(cfg, folder):
    write_next_views(folder, elevation_ranking(cfg))
    data = json.loads((folder / FILE).read_text())
    data["candidates"][0]["pose"][0][0] = 2.0
    (folder / FILE).write_text(json.dumps(data))


def _unreachable(cfg, folder):
    cand, score = by_elevation(cfg, np.asarray(cfg.scan.target))
    far = cand.copy()
    far[:, 0, 3] += 3.0  # beyond the workspace box
    write_next_views(folder, ranked(far, score, 0, "elevation"))


def _zeros(cfg, folder):
    cand, _ = by_elevation(cfg, np.asarray(cfg.scan.target))
    write_next_views(folder, ranked(cand, np.zeros(len(cand)), 0, "coverage"))  # a field with no surface yet


@pytest.mark.parametrize("make, detail", [
    (_stale_count, "next_views.json stale: ranked at 0 poses, 3 before this one (next_views_max_lag 3)"),
    # 600 s old when written: some more by the time the scan reaches the pose, on a slow or busy machine.
    (_old, re.compile(r"next_views\.json stale: ranked 6\d\d s ago \(next_views_max_age_s 60\)")),
    (_truncated, "next_views.json unreadable ("),
    (_not_rigid, "candidate 0: pose is not a rigid transform"),
    (_unreachable, "none of the 512 ranked views passes (512 outside the workspace)"),
    (_zeros, "no ranked view scores above 0 (all 512 score 0 or less: nothing to gain)"),
], ids=["stale-pose-count", "stale-time", "truncated", "not-rigid", "unreachable", "all-zero"])
def test_the_fallback_plan_when_the_ranking_cannot_be_used(arun, tmp_path, sphere, make, detail):
    cfg = make_cfg(tmp_path, **ADAPTIVE, next_views_max_lag=3 if make is _stale_count else 100, arm=BOX)
    done, _ = run_scan(arun, cfg, sphere, before=lambda folder: make(cfg, folder))
    assert done["state"] == "complete"
    why = choices(check_capture(cfg.captures / "a", VIEWS, 1))
    assert [c["why"] for c in why] == ["initial"] * INITIAL + ["fallback"] * (VIEWS - INITIAL)
    if make is _stale_count:  # fresh at pose 3 only if the lag were below 3: every later pose is staler
        assert all(c["detail"].startswith("next_views.json stale: ranked at 0 poses") for c in why[INITIAL:])
    found = detail.search(why[INITIAL]["detail"]) if isinstance(detail, re.Pattern) else detail in why[INITIAL]["detail"]
    assert found, why[INITIAL]["detail"]


def live_status(folder: Path, **fields) -> None:
    live = folder / "recon" / "live"
    live.mkdir(parents=True)
    write_status(live, LiveStatus(views_published=fields["views_used"], steps=100, **fields))


def test_the_scan_ends_when_the_live_reconstruction_has_converged(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, **ADAPTIVE, stop_when_converged=True)

    def converged(folder: Path):
        live_status(folder, views_used=INITIAL, converged=True)

    done, status = run_scan(arun, cfg, sphere, before=converged)
    assert done["state"] == "complete"
    reader = CaptureReader(cfg.captures / "a")
    assert reader.manifest["planned_poses"] == INITIAL and len(reader.planned_poses()) == INITIAL
    assert "the live reconstruction converged with 3 views" in reader.manifest["reason"]
    data = check_capture(cfg.captures / "a", INITIAL, 1)  # complete as it stands: every planned pose published
    assert [c["why"] for c in choices(data)] == ["initial"] * INITIAL


def test_a_chunk_lost_before_an_early_end_is_taken_again_first(arun, tmp_path, sphere):
    """"complete" promises every pose of the capture as it stands: a chunk deleted while an adaptive scan runs is
    found before the scan ends early, and its pose is taken again."""
    cfg = make_cfg(tmp_path, **ADAPTIVE, stop_when_converged=True, chunk_size=1)
    folder = cfg.captures / "a"

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            take_frame, deleted = runner.sensor.next_frame, []

            async def next_frame(timeout_s):
                if not deleted and (folder / "chunk-000000").exists():  # once pose 0 is published
                    await runner._io(shutil.rmtree, folder / "chunk-000000")
                    deleted.append(runner.job.next_pose)
                return await take_frame(timeout_s)

            runner.sensor.next_frame = next_frame
            await runner.start("a")
            live_status(folder, views_used=INITIAL, converged=True)  # the scan ends after its initial views
            return await runner.wait("a"), deleted

    done, deleted = arun(scenario())
    assert done["state"] == "complete" and deleted and deleted[0] < INITIAL, deleted
    reader = CaptureReader(folder)
    assert "converged" in reader.manifest["reason"]
    check_capture(folder, reader.manifest["planned_poses"], 1)


def test_a_status_without_convergence_never_ends_the_scan(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, **ADAPTIVE, stop_when_converged=True)

    def not_yet(folder: Path):
        live_status(folder, views_used=INITIAL - 1, converged=True)  # fewer views than the initial ones

    run_scan(arun, cfg, sphere, before=not_yet)
    check_capture(cfg.captures / "a", VIEWS, 1)


# ---- the chooser alone -------------------------------------------------------------------------------------------
def chooser_for(tmp_path, **scan):
    cfg = make_cfg(tmp_path, **{**ADAPTIVE, **scan}, arm=BOX)
    plan = build_plan(cfg.scan, cfg.arm).sensor_poses
    folder = tmp_path / "cap"
    folder.mkdir()
    return cfg, ViewChooser(cfg.scan, cfg.arm, cfg.arm.hand_eye, folder), plan, folder


def test_the_best_reachable_view_replaces_the_queued_pose_nearest_it(tmp_path):
    cfg, chooser, plan, folder = chooser_for(tmp_path, next_views_max_lag=100)
    cand, score = by_elevation(cfg, np.asarray(cfg.scan.target))
    poses = cand.copy()
    poses[np.argsort(-score)[:5], 0, 3] += 3.0  # the five best are out of reach
    write_next_views(folder, ranked(poses, score, 0, "elevation"))
    choice, rows = chooser.choose(plan, INITIAL)
    assert choice.why == "adaptive" and choice.record["rank"] == 5
    np.testing.assert_array_equal(rows[:INITIAL], plan[:INITIAL])
    np.testing.assert_array_equal(rows[INITIAL], read_next_views(folder).poses[5])
    queue = plan[INITIAL:]
    dropped = view_angles_deg(rows[INITIAL][None], queue, cfg.scan.target).argmin()
    np.testing.assert_array_equal(rows[INITIAL + 1:], np.delete(queue, dropped, axis=0))
    assert len(rows) == VIEWS


def test_views_scoring_zero_or_less_are_passed_over_for_the_planned_pose(tmp_path):
    """A view that sees nothing scores 0: the order among such views is the candidates' spiral (top down), not a
    ranking. With the positive views out of reach, the planned pose is taken, not the first zero of the spiral."""
    cfg, chooser, plan, folder = chooser_for(tmp_path, next_views_max_lag=100)
    cand = candidate_poses(scan_to_dict(cfg.scan))
    score = np.zeros(len(cand))
    score[:5], score[5:9] = [5.0, 4.0, 3.0, 2.0, 1.0], -1.0
    poses = cand.copy()
    poses[:5, 0, 3] += 3.0  # the five views scoring above 0 are out of reach
    write_next_views(folder, ranked(poses, score, 0, "coverage"))
    choice, rows = chooser.choose(plan, INITIAL)
    assert choice.why == "fallback", choice.record
    assert choice.record["detail"] == ("none of the 512 ranked views passes (507 scoring 0 or less, 5 outside the "
                                       "workspace)")
    np.testing.assert_array_equal(choice.pose, plan[INITIAL])
    np.testing.assert_array_equal(rows, plan)
    score[5] = 0.5  # one reachable view scoring above 0: it is taken
    write_next_views(folder, ranked(poses, score, 0, "coverage"))
    choice, _ = chooser.choose(plan, INITIAL)
    assert choice.why == "adaptive" and choice.record["rank"] == 5 and choice.record["score"] == 0.5
    np.testing.assert_allclose(choice.pose, cand[5], atol=1e-9)


def test_the_smallest_lag_takes_a_ranking_one_pose_behind(tmp_path):
    """next_views_max_lag 2: a ranking made while the pose before was captured is fresh, one 2 poses behind not."""
    cfg, chooser, plan, folder = chooser_for(tmp_path, next_views_max_lag=2)
    write_next_views(folder, elevation_ranking(cfg, pose_count=INITIAL - 1))
    assert chooser.choose(plan, INITIAL)[0].why == "adaptive"
    write_next_views(folder, elevation_ranking(cfg, pose_count=INITIAL - 2))
    choice, _ = chooser.choose(plan, INITIAL)
    assert choice.why == "fallback"
    assert choice.record["detail"] == ("next_views.json stale: ranked at 1 poses, 2 before this one "
                                       "(next_views_max_lag 2)")


def test_a_refused_view_is_never_offered_again(tmp_path):
    cfg, chooser, plan, folder = chooser_for(tmp_path, next_views_max_lag=100)
    write_next_views(folder, elevation_ranking(cfg))
    first, _ = chooser.choose(plan, INITIAL)
    chooser.refuse(first.candidate)
    second, _ = chooser.choose(plan, INITIAL)
    assert second.why == "adaptive" and second.record["rank"] > first.record["rank"]


def test_a_ranked_view_already_taken_is_never_taken_again_even_with_no_spacing(tmp_path):
    cfg, chooser, plan, folder = chooser_for(tmp_path, next_views_max_lag=100, min_view_spacing_deg=0.0)
    write_next_views(folder, elevation_ranking(cfg))
    first, rows = chooser.choose(plan, INITIAL)
    second, _ = chooser.choose(rows, INITIAL + 1)  # the same ranking: its best view is now a pose taken
    assert (first.why, second.why) == ("adaptive", "adaptive")
    assert second.record["rank"] == first.record["rank"] + 1


def test_the_fallback_passes_over_queued_poses_close_to_taken_ones(tmp_path):
    cfg, chooser, plan, _ = chooser_for(tmp_path, min_view_spacing_deg=1.0)
    rows = plan.copy()
    rows[INITIAL - 1] = plan[INITIAL]  # the first queued pose was taken (as a ranked view) just before
    choice, out = chooser.choose(rows, INITIAL)
    assert choice.why == "fallback" and np.array_equal(choice.pose, plan[INITIAL + 1])
    np.testing.assert_array_equal(out[INITIAL + 1], plan[INITIAL])  # kept in the queue, for the end


def test_a_scan_no_live_worker_follows_says_so_once(tmp_path, caplog):
    _, chooser, plan, folder = chooser_for(tmp_path)
    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        for i in range(INITIAL, INITIAL + 3):
            choice, plan = chooser.choose(plan, i)
            assert choice.why == "fallback"
    said = [r.getMessage() for r in caplog.records]
    assert said == [f"scan {folder.name}: no live reconstruction follows it (no next_views.json, no live status): "
                    f"taking the fallback plan until one ranks its views (is a worker running with --live?)"]


def test_a_scan_whose_live_job_has_not_ranked_yet_is_the_usual_start_and_not_said(tmp_path, caplog):
    _, chooser, plan, folder = chooser_for(tmp_path)
    (folder / "recon" / "live").mkdir(parents=True)
    write_status(folder / "recon" / "live", LiveStatus(views_used=8, views_published=16, steps=40))
    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        choice, _ = chooser.choose(plan, INITIAL)
    assert choice.why == "fallback" and caplog.records == []


def test_no_reachable_pose_left_is_one_line(tmp_path):
    cfg, chooser, plan, _ = chooser_for(tmp_path)
    rows = plan.copy()
    rows[INITIAL - 1, 0, 3] += 5.0  # pose 2 stands far outside the box: no straight move from it stays inside
    with pytest.raises(ConfigError, match="no pose left in the plan can be reached"):
        chooser.choose(rows, INITIAL)


def test_adaptive_keys_need_the_adaptive_schedule(tmp_path):
    from spadscan.daemon.config import scan_request

    cfg = make_cfg(tmp_path)
    with pytest.raises(ConfigError, match="initial_views applies only to schedule 'adaptive'"):
        scan_request(cfg.scan, {"initial_views": 4})
    with pytest.raises(ConfigError, match="initial_views 20 exceeds views 8"):
        scan_request(cfg.scan, {"schedule": "adaptive", "views": 8, "initial_views": 20})


def test_ctl_scan_asks_for_an_adaptive_scan(monkeypatch, capsys):
    from spadscan.cli import main
    from spadscan.daemon import client

    sent = []
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **req: sent.append((op, req)) or
                        {"ok": True, "scan": "s", "state": "scanning"})
    assert main(["ctl", "scan", "--name", "s", "--schedule", "adaptive", "--initial-views", "12",
                 "--stop-when-converged", "--socket", "/tmp/x.sock"]) == 0
    assert sent == [("scan", {"name": "s", "options": {"schedule": "adaptive", "initial_views": 12,
                                                         "stop_when_converged": True}})]


def test_a_scan_stopped_on_a_ranked_view_is_taken_over(arun, tmp_path, sphere):
    """A daemon stopped after it wrote a ranked view into schedule.npy, before that pose was published: the rest of
    the plan does not follow on from that view as a path, and the restarted daemon still takes the scan over (each
    move is checked as its pose is chosen) and completes it, every pose once."""
    arm = {"keepout_radius_m": 0.08}
    cfg = make_cfg(tmp_path, **{**ADAPTIVE, "views": 9, "max_elevation_deg": 50.0}, arm=arm)
    home = np.eye(4)
    home[:3, 3] = [0.45, 0.0, 0.3]  # beside the scan, clear of the base's column

    async def first():
        arm_, sensor = make_rig(cfg, sphere, motion_time_s=0.01, home=home)
        async with DeviceSession([arm_, sensor]):
            runner = ScanRunner(arm_, sensor, cfg)
            await runner.start("k")
            await until(lambda: runner.job.next_pose >= INITIAL + 1, "a pose after the initial ones")
            await runner.pause()
            await until(lambda: runner.state == "paused", "paused")
            await runner.shutdown()

    arun(first())
    folder = cfg.captures / "k"
    done = CaptureReader(folder).load().pose_indices.max() + 1
    rows = np.load(folder / "schedule.npy")
    # as if a ranked view straight across the target from the next planned pose had been chosen for the next pose
    eye = rows[done + 1][:3, 3].copy()
    eye[:2] = 2 * np.asarray(cfg.scan.target)[:2] - eye[:2]
    rows[done] = look_at(eye, cfg.scan.target)
    np.save(folder / "schedule.npy", rows)
    from spadscan.daemon.scan_plan import tcp_from_sensor
    from spadscan.daemon.workspace import check_workspace

    with pytest.raises(ConfigError, match="keepout"):  # the rows left, as a path, break the keep-out
        check_workspace(tcp_from_sensor(rows[done:], cfg.arm.hand_eye), cfg.arm, "left")

    async def second():
        arm_, sensor = make_rig(cfg, sphere, motion_time_s=0.01, home=home)
        async with DeviceSession([arm_, sensor]):
            runner = ScanRunner(arm_, sensor, cfg)
            try:
                await runner.recover()
                assert runner.state == "paused" and runner.last_error is None, runner.last_error
                await runner.resume()
                return await runner.wait("k")
            finally:
                await runner.shutdown()

    assert arun(second())["state"] == "complete"
    check_capture(folder, 9, 1)


@pytest.mark.parametrize("state", ["queued", "stopped", "aborted", "waiting", "final", "done"])
def test_only_a_fit_following_the_scan_ends_it_as_converged(tmp_path, state):
    """A live status that says its job was given back, stopped or ended keeps the stopped fit's figures, its
    converged flag too: that is no reason to end the scan; the same figures in a 'live' status are."""
    live_status(tmp_path / "a", views_used=20, converged=True, state=state)
    assert live_converged(tmp_path / "a", 8) is None
    live_status(tmp_path / "b", views_used=20, converged=True, state="live")
    assert live_converged(tmp_path / "b", 8) == "the live reconstruction converged with 20 views"
