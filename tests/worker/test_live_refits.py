"""When a live job refits: only once the views have grown by a useful amount, and never so often that refits take
most of its time (on a loaded machine a refit takes tens of seconds: refitting at every new chunk left no time to
train)."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

from spadscan.worker.live.job import LiveRun, LiveSettings, refit_due

S = LiveSettings()  # a quarter more views or 16, refits at most a quarter of the time


def test_a_chunk_or_two_more_is_no_reason_to_refit():
    assert not refit_due(64, 66, trained_s=1e6, last_refit_s=0.1, settings=S)
    assert not refit_due(8, 9, trained_s=1e6, last_refit_s=0.1, settings=S)


def test_a_quarter_more_views_or_sixteen_is():
    assert refit_due(8, 10, trained_s=1e6, last_refit_s=0.1, settings=S)  # 8 -> 10: a quarter more
    assert not refit_due(96, 111, trained_s=1e6, last_refit_s=0.1, settings=S)
    assert refit_due(96, 112, trained_s=1e6, last_refit_s=0.1, settings=S)  # 16 more, though not a quarter


def test_a_slow_refit_waits_for_its_share_of_training():
    # A refit that took 30 s (a loaded machine): the next one waits for 90 s of training, however many views land.
    assert not refit_due(32, 64, trained_s=25.0, last_refit_s=30.0, settings=S)
    assert not refit_due(32, 64, trained_s=89.0, last_refit_s=30.0, settings=S)
    assert refit_due(32, 64, trained_s=90.0, last_refit_s=30.0, settings=S)


def test_a_live_run_with_a_few_new_views_keeps_training_long_after_its_last_refit():
    """The rule as the follow loop asks it: two new views 25 s after the last refit are no refit (the former rule
    refitted on any new view 20 s after the last refit, which on a loaded machine is every poll)."""
    run = LiveRun(job=None, scan=Path("scan"), folder=Path("live"), follower=None, settings=S, log=print)
    run.fit = SimpleNamespace(views_used=64, model=object())
    now = time.monotonic()
    run.last_rebuild, run.last_rebuild_cost = now - 25.0, 3.0
    assert not run._refit_due(SimpleNamespace(views_published=66), now)
    assert run._refit_due(SimpleNamespace(views_published=80), now)
