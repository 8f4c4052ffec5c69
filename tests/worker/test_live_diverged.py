"""A live fit whose step diverges (a non-finite loss) starts again from the carved hull instead of failing the live
job; diverged twice on the same views it drops its model until more views arrive, and the scan still gets its
final reconstruction."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import torch

from spadscan.worker.live.job import no_live_model
from spadscan.worker.live.live_fit import LiveFit
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.errors import ReconstructionError
from spadscan.worker.recon.fast.model import FastModel
from spadscan.worker.recon.presets import preset_config

from live_helpers import ReplayScan
from test_live_job import LiveJobThread, small_settings
from worker_helpers import FAST_SMALL


def diverging(monkeypatch, at: set[int]):
    """FastModel.step raising as a diverged step does on the calls numbered in `at` (from 1); returns the count and
    an event set once 20 steps ran after the last of them."""
    real = FastModel.step
    calls = {"n": 0}
    after = threading.Event()

    def step(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] in at:
            raise ReconstructionError(f"the loss became nan at step {calls['n']} (diverged)")
        if calls["n"] >= max(at) + 20:
            after.set()
        return real(self, *args, **kwargs)

    monkeypatch.setattr(FastModel, "step", step)
    return calls, after


def test_a_diverged_step_restarts_the_fit_and_twice_drops_it(cylinder_capture, tmp_path, one_thread, monkeypatch):
    scan = ReplayScan(cylinder_capture, tmp_path / "scan")
    scan.publish(10)
    lines: list[str] = []
    fit = LiveFit(tmp_path / "scan", with_overrides(preset_config("fast"), FAST_SMALL), torch.device("cpu"), 0,
                  log=lines.append)
    assert fit.rebuild()
    diverging(monkeypatch, {3, 4})
    assert fit.train_steps(2) == 2
    first = fit.model
    assert fit.train_steps(5) == 0  # the third step diverges: a new model, cold, on the same 10 views
    assert fit.model is not None and fit.model is not first and fit.model.steps == 0 and fit.views_used == 10
    assert any("diverged" in line and "starting it again from the carved hull" in line for line in lines), lines
    assert fit.train_steps(5) == 0  # its first step diverges too: no live model till more views arrive
    assert fit.model is None and "diverged twice on 10 views" in fit.not_yet
    scan.publish(4)
    assert fit.rebuild() and fit.model is not None and fit.not_yet is None
    assert fit.train_steps(3) == 3


def test_a_live_job_whose_fit_diverges_still_ends_with_its_result(cylinder_capture, tmp_path, one_thread,
                                                                   monkeypatch):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(8)
    _, after = diverging(monkeypatch, {15})
    live = LiveJobThread(root, "cyl", small_settings())
    assert after.wait(300), live.lines
    scan.run()
    scan.finish()
    live.thread.join(300)
    assert not live.thread.is_alive()
    assert "error" not in live.result, live.result
    report = live.result["report"]
    assert report["steps"] > 0 and report["live"]["final_start"] in ("live", "hull")
    assert any("starting it again from the carved hull" in line for line in live.lines), live.lines


def test_a_live_job_whose_fit_diverged_twice_says_so_when_it_reconstructs_from_scratch(
        cylinder_capture, tmp_path, one_thread, monkeypatch):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.run()  # every view published: no new one to fit the live model again on
    diverging(monkeypatch, {3, 4})
    live = LiveJobThread(root, "cyl", small_settings())
    live.wait_status(lambda s: s.note is not None and "diverged twice" in s.note, "the live fit dropped")
    scan.finish()
    report = live.join()
    assert report["steps"] > 0 and "live" not in report  # an ordinary run's report
    final = [line for line in live.lines if "reconstructing it from scratch" in line]
    assert final and "no live fit: it diverged twice on" in final[0], live.lines


def test_an_early_tries_failure_is_not_given_as_the_reason_the_scan_has_no_live_model():
    early = SimpleNamespace(model=None, not_yet="no live fit yet: too few views", diverged_views=-1, views_used=0)
    assert no_live_model(early, 6) == "the scan completed with 6 views before the live fit started"
    dropped = SimpleNamespace(model=None, not_yet="no live fit: it diverged twice on 10 views (nan)",
                              diverged_views=10, views_used=10)
    assert no_live_model(dropped, 12) == dropped.not_yet
