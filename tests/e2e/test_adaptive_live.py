"""An adaptive scan steered by a real live reconstruction: a daemon (sim arm and sensor) scans with schedule
'adaptive' while `spadscan worker --live` fits the views and writes next_views.json; the poses after the ranking
arrives are the ranked views, and each says so in its meta. The scan is paused after its initial views until the
ranking is there (an event, not a wait on the clock), so that the live fit has time on a busy machine."""

from __future__ import annotations

import pytest

from e2e_helpers import assert_every_pose_once, spadscan_argv, wait_for
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.next_views import read_next_views

VIEWS, INITIAL = 14, 6
SLOW_S = 300.0  # a live fit on a busy machine may take minutes; every wait ends as soon as its event happens
RIG = {"arm": {"motion_time_s": 0.2}, "sensor": {"rays_per_zone": 64},
       "scan": {"views": VIEWS, "schedule": "adaptive", "initial_views": INITIAL}}


def ranking(capture):
    try:
        return read_next_views(capture)
    except CaptureError:
        return None


@pytest.mark.slow
def test_a_live_worker_steers_an_adaptive_scan(make_daemon, procs):
    daemon = make_daemon(**RIG).start()
    procs.start(spadscan_argv("worker", "--root", daemon.captures, "--live", "--steps", 2, "--device", "cpu",
                              "--poll-s", 0.2), "worker")
    daemon.call("scan", name="nbv", options={})
    daemon.wait_pose("nbv", INITIAL)
    daemon.call("pause")
    paused = daemon.wait_state("paused")
    capture = daemon.captures / "nbv"
    nv = wait_for(lambda: ranking(capture), "next_views.json from the live job", SLOW_S, poll_s=0.2)
    assert nv.measure == "coverage" and INITIAL <= nv.pose_count <= paused["pose"]
    daemon.call("resume")
    wait_for(lambda: (daemon.status().get("last_scan") or {}).get("state") == "complete", "the scan complete", 120.0)

    data = assert_every_pose_once(capture, VIEWS, 1)
    why = {m["pose_index"]: m["view_choice"] for m in data.meta}
    assert [why[i]["why"] for i in range(INITIAL)] == ["initial"] * INITIAL
    taken = [why[i] for i in range(paused["pose"], VIEWS) if why[i]["why"] == "adaptive"]
    assert taken and taken[0]["measure"] == "coverage" and taken[0]["ranked_at_poses"] >= INITIAL
    assert CaptureReader(capture).manifest["view_choices"]["adaptive"] == sum(
        1 for c in why.values() if c["why"] == "adaptive")
