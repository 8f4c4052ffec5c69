"""A sweep whose Dask scheduler dies mid-run: Dask cancels every point the client was waiting for. Those points did
not fail (a worker may still finish and store one), so nothing is recorded for them, and a stored result (a stale
one, run again) stays as it was; the run ends with one line that says so."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from sweep_helpers import DaskCluster

from spadscan.protocol.errors import SpadscanError
from spadscan.sweep.fingerprint import Expected
from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import run_sweep
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

pytestmark = pytest.mark.slow


def test_a_lost_scheduler_records_nothing_for_the_points_it_held_and_says_so(tiny_sweep, tmp_path):
    plan = make_plan(load_spec(tiny_sweep))
    out, started = tmp_path / "out", tmp_path / "started"
    stale_id, task = next(iter(plan.points.items()))
    store = SweepDir(out)
    store.open(plan)
    store.write_point({"id": stale_id, "status": "done", "methods": {"fast": {"status": "done", "chamfer_mm": 5.0}},
                       "fingerprints": {"fast": "an older spadscan"}})
    store.close()
    assert Expected(task, "cpu").state(store.read_point(stale_id)) == "stale"
    stored = (out / "points" / f"{stale_id}.json").read_bytes()

    def point(task, out, device, keep):  # pickled by value: the worker runs it, and it outlasts the scheduler
        Path(started).touch()
        time.sleep(300)

    cluster = DaskCluster(tmp_path / "dask")
    cluster.folder.mkdir()
    ended: list[BaseException | None] = []

    def sweep():
        try:
            run_sweep(plan, out, scheduler=cluster.address, point=point, progress=False)
            ended.append(None)
        except BaseException as exc:  # noqa: BLE001 - what the run ended with is the test's subject
            ended.append(exc)

    try:
        cluster.start(workers=1)
        runner = threading.Thread(target=sweep, daemon=True)
        runner.start()
        deadline = time.monotonic() + 120
        while not started.exists():
            assert runner.is_alive() and time.monotonic() < deadline, f"no point started: {ended}"
            time.sleep(0.05)
        cluster.kill("scheduler")
        runner.join(timeout=120)
        assert not runner.is_alive(), "the sweep did not end after its scheduler died"
    finally:
        cluster.stop()
    assert isinstance(ended[0], SpadscanError), ended
    message = str(ended[0])
    assert "\n" not in message and message.startswith("lost the Dask scheduler with 3 point(s)"), message
    assert "nothing is recorded for them" in message and "the same command runs the rest" in message
    assert (out / "points" / f"{stale_id}.json").read_bytes() == stored
    assert sorted(p.name for p in (out / "points").iterdir()) == [f"{stale_id}.json"]
