"""The client's side of a sweep on a scheduler that other sweeps share."""

from __future__ import annotations

import json

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import emit_event, run_sweep
from spadscan.sweep.spec import load_spec

from sweep_helpers import write_tiny


def point_beside_another_sweep(task, out, device, keep):
    """A point that reports its start while a point of another sweep on the same scheduler reports its own."""
    emit_event(str(out) + "-other", task.id, "start")
    emit_event(out, task.id, "start")
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None}


def test_a_sweep_logs_only_its_own_events_on_a_shared_scheduler(tmp_path):
    from distributed import LocalCluster

    plan = make_plan(load_spec(write_tiny(tmp_path)))
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    try:
        summary = run_sweep(plan, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False,
                            point=point_beside_another_sweep)
    finally:
        cluster.close()
    assert summary.done == len(plan.points)
    events = [json.loads(line) for line in (tmp_path / "out" / "log.jsonl").read_text().splitlines()]
    # The events of a task reach the client before its result (one stream, in order): all of this sweep's are here.
    assert sorted(e["point"] for e in events) == sorted(plan.points) and all(e["event"] == "start" for e in events)
