"""The live status says the fit as it stands: after every refit, and between two publications of the mesh and preview
(which on a busy machine come 12-15 s apart, a refit delaying them further) the views the scan has published since,
while the mesh and preview keep their own cadence."""

from __future__ import annotations

import itertools
from pathlib import Path
from types import SimpleNamespace

import torch

from spadscan.protocol.live_status import read_status, status_path
from spadscan.worker.jobs import Job
from spadscan.worker.live.follower import ScanProgress
from spadscan.worker.live.job import LiveRun, LiveSettings

NEVER_S = 1e6
"""A publication cadence no follow loop of the test reaches: the mesh is published only when forced (the first fit)."""


class Fit:
    """A live fit that refits on every view published at the moment (as `LiveFit.rebuild` reads the capture) and
    steps at once."""

    def __init__(self, scan: SimpleNamespace):
        self.scan = scan
        self.model, self.views_used, self.steps, self.converged, self.not_yet, self.rebuilds = None, 0, 0, False, \
            None, 0

    def rebuild(self, views_planned):
        self.model, self.views_used, self.rebuilds = SimpleNamespace(level=1), self.scan.published, self.rebuilds + 1
        shape = (self.views_used, 9, 128)  # nothing detected: no pile-up to say
        self.scene = SimpleNamespace(counts=torch.zeros(shape), valid=torch.ones(shape, dtype=torch.bool))
        return True

    def mesh(self, resolution):
        return "the live mesh"

    def remember(self):
        pass

    def train(self, until):
        self.steps += 5
        return 5


class Follower:
    """Hands out the polls of a scan one at a time, and keeps the live status as it stood at each poll."""

    def __init__(self, scan: SimpleNamespace, capture: Path, counts: list[int]):
        self.scan, self.capture = scan, capture
        self.polls = iter([*(polled(n) for n in counts), polled(counts[-1], state="complete")])
        self.seen = []

    def poll(self) -> ScanProgress:
        self.seen.append(read_status(status_path(self.capture)))
        progress = next(self.polls)
        self.scan.published = progress.views_published
        return progress


def polled(views: int, state: str = "running") -> ScanProgress:
    return ScanProgress(state=state, reason=None, views_published=views, views_planned=40, new_chunks=1,
                        manifest={"updated_utc": f"poll {views}"})


def following_run(tmp_path, monkeypatch, meshes: list, lines: list) -> tuple[LiveRun, Follower]:
    """A live run of a scan of 8 views published, then 10, then 13 (8: the first fit; 10: too few more for a refit,
    a quarter more, at most 4; 13: a refit), whose meshes go to `meshes` and whose log lines to `lines`."""
    import spadscan.worker.live.job as live_job

    monkeypatch.setattr(live_job, "publish_mesh", lambda folder, mesh, gt, preview: meshes.append(mesh))
    # A clock that moves a second a reading: every status cadence of a second or two is due at each poll, and no
    # publication cadence of NEVER_S ever is.
    ticks = itertools.count()
    monkeypatch.setattr(live_job, "time", SimpleNamespace(monotonic=lambda: float(next(ticks)),
                                                          perf_counter=lambda: 0.0, sleep=lambda s: None))
    (folder := tmp_path / "recon" / "live").mkdir(parents=True)
    scan = SimpleNamespace(published=8)
    follower = Follower(scan, tmp_path, [10, 13])
    settings = LiveSettings(min_views=8, publish_every_s=NEVER_S, rebuild_growth=0.5, rebuild_views=4,
                            rebuild_share=1.0, preview=False)
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), tmp_path, folder, follower, settings,
                  lines.append)
    run.fit = Fit(scan)
    return run, follower


def test_the_status_follows_every_refit_and_the_views_published_while_the_mesh_keeps_its_cadence(tmp_path,
                                                                                                  monkeypatch):
    meshes: list[str] = []
    lines: list[str] = []
    run, follower = following_run(tmp_path, monkeypatch, meshes, lines)
    assert run.follow(polled(8)).state == "complete"

    first, between, refitted = [(s.views_used, s.views_published, s.steps) for s in follower.seen]
    assert first[:2] == (8, 8), lines
    assert between[:2] == (8, 10), "the views published since the fit are said before the next refit"
    assert between[2] > first[2], "and the steps taken since"
    assert refitted[:2] == (13, 13), f"the refit is said at once, not at the next publication: {follower.seen}"
    assert refitted[2] > between[2]
    assert all(s.state == "live" and s.views_planned == 40 for s in follower.seen)
    assert meshes == ["the live mesh"], "the mesh and preview keep their own cadence: only the first fit's, forced"
    assert any("refit 2" in line for line in lines), lines


def test_a_chamfer_measured_on_an_older_mesh_says_the_views_of_that_mesh(tmp_path, monkeypatch):
    # The status is rewritten between two meshes: after the refit to 13 views the Chamfer is still the 8-view
    # mesh's, and the status (and the lines made from it) must not pair it with the 13 views.
    run, follower = following_run(tmp_path, monkeypatch, [], [])
    run.config = SimpleNamespace(trace_points=1000)
    run.truth = SimpleNamespace(mesh=None, metrics=lambda mesh, n_points: SimpleNamespace(chamfer_mm=5.0))
    run.follow(polled(8))

    first, _, refitted = follower.seen
    assert (first.views_used, first.chamfer_mm, first.chamfer_views) == (8, 5.0, 8)
    assert (refitted.views_used, refitted.chamfer_mm, refitted.chamfer_views) == (13, 5.0, 8)
    assert "Chamfer 5.00 mm (its mesh of 8 views)" in refitted.summary()
    assert "Chamfer 5.00 mm," in first.summary(), "the mesh of the fit as it stands: nothing more to say"
