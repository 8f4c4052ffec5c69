"""The durable job queue: queued once, claimed once, leases that expire, retries, failures with reasons."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
from dataclasses import replace

import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.worker.holder import Holder, holder_gone
from spadscan.worker.jobs import Job, job_id_for, old_job_id_for
from spadscan.worker.queue import Queue

from process_helpers import reaped


def _job(name: str, preset: str = "fast") -> Job:
    return Job(id=job_id_for(name, preset), scan=name, preset=preset)


def _elsewhere() -> Holder:
    """A holder on another machine: only its lease's expiry can free its jobs."""
    return Holder(host="another-host", pid=12345, boot_id="other-boot", pid_ns="pid:[1]", pid_start="1")


def test_job_ids_are_deterministic_and_safe():
    assert job_id_for("bunny", "fast") == "bunny-fast" == job_id_for("bunny", "fast")
    assert re.fullmatch(r"a_b_\.\._c-[0-9a-f]{8}-paper", job_id_for("a b/../c", "paper"))
    assert job_id_for("bunny", "fast") != job_id_for("bunny", "paper")


SAFE_NAMES = ["bunny", "mug_1", "x_y", "scan.2024-05-01", "-", "a" * 195]
ODD_NAMES = ["x+y", "mug 1", "tasse-\u00fc", "tasse-\u00f6", "caf\udce9 #1", ".hidden", "\u00fc", "a" * 196, "a" * 300]


def test_job_ids_of_safe_names_are_as_they_always_were():
    """Existing queues and result folders (`<scan>/recon/<scan>-<preset>/`) keep their jobs."""
    for name in SAFE_NAMES:
        assert job_id_for(name, "fast") == f"{name}-fast" == old_job_id_for(name, "fast")


def test_scans_whose_names_differ_only_in_odd_characters_get_ids_of_their_own(tmp_path):
    names = SAFE_NAMES + ODD_NAMES + ["x y", "x++y", "mug_1" + "b" * 300, "mug_1" + "c" * 300]
    ids = [job_id_for(name, preset) for name in names for preset in ("fast", "paper")]
    assert len(set(ids)) == len(ids), "one id per scan and preset"
    hashed = [job_id_for(name, "fast", hashed=True) for name in SAFE_NAMES]
    assert len(set(hashed + ids)) == len(hashed + ids), "a hashed id is no other scan's id either"
    for job_id in ids + hashed:
        assert re.fullmatch(r"[A-Za-z0-9._-]{1,200}", job_id) and not job_id.startswith("."), job_id
        assert job_id.endswith(("-fast", "-paper")), job_id
    q = Queue(tmp_path / "q")
    assert all(q.enqueue(Job(id=job_id_for(name, "fast"), scan=name)) for name in names), "each one is queued"


def test_the_queue_says_which_scan_an_id_is_registered_to(tmp_path):
    q = Queue(tmp_path / "q")
    assert q.registered_scan("x_y-fast") is None
    q.enqueue(Job(id="x_y-fast", scan="x+y"))
    assert q.registered_scan("x_y-fast") == "x+y"
    (q.path / "ids" / "torn-fast.json").write_text("{")
    assert q.registered_scan("torn-fast") == "", "a damaged registry file names no scan"


def test_a_scan_is_queued_once(tmp_path):
    q = Queue(tmp_path / "q")
    assert q.enqueue(_job("bunny"))
    assert not q.enqueue(_job("bunny"))
    claim = q.claim()
    assert claim.job.scan == "bunny" and claim.attempt == 1
    assert not q.enqueue(_job("bunny")), "a running job must not be queued again"
    q.finish(claim)
    assert not q.enqueue(_job("bunny")), "a finished job must not be queued again"
    assert q.counts() == {"queued": 0, "running": 0, "done": 1, "failed": 0}


def test_bad_job_ids_are_refused(tmp_path):
    q = Queue(tmp_path / "q")
    with pytest.raises(ConfigError, match="job id"):
        q.enqueue(Job(id="../escape", scan="x"))


CLAIM_ALL = """
import json, sys
from spadscan.worker.queue import Queue
q = Queue(sys.argv[1])
got = []
while (c := q.claim()) is not None:
    got.append(c.job.id)
    q.finish(c)
print(json.dumps(got))
"""


def test_concurrent_claims_take_each_job_once(tmp_path):
    q = Queue(tmp_path / "q")
    ids = [job_id_for(f"scan{i:03d}", "fast") for i in range(60)]
    for i in range(60):
        q.enqueue(_job(f"scan{i:03d}"))
    with reaped(*(subprocess.Popen([sys.executable, "-c", CLAIM_ALL, str(q.path)], stdout=subprocess.PIPE, text=True)
                  for _ in range(4))) as procs:
        outs = [p.communicate(timeout=60)[0] for p in procs]
    got = [j for out in outs for j in json.loads(out)]
    assert sorted(got) == sorted(ids), "every job claimed exactly once"
    assert q.counts()["done"] == 60


def test_claims_racing_in_threads_take_each_job_once(tmp_path):
    q = Queue(tmp_path / "q")
    for i in range(200):
        q.enqueue(_job(f"s{i:03d}"))
    start = threading.Barrier(8)
    got: list[list[str]] = [[] for _ in range(8)]

    def claimer(k: int) -> None:
        start.wait()
        while (c := q.claim()) is not None:
            got[k].append(c.job.id)

    threads = [threading.Thread(target=claimer, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    flat = [j for g in got for j in g]
    assert len(flat) == 200 and len(set(flat)) == 200
    assert q.counts() == {"queued": 0, "running": 200, "done": 0, "failed": 0}


def test_heartbeat_keeps_the_lease_and_finish_records_the_result(tmp_path):
    q = Queue(tmp_path / "q", lease_s=5)
    q.enqueue(_job("s"))
    claim = q.claim()
    assert q.heartbeat(claim)
    assert q.reclaim_expired(now=time.time() + 1) == [], "a fresh lease holds"
    assert q.finish(claim)
    q.record_result(claim, "/x/recon/s-fast")
    (row,) = q.statuses()
    assert (row.state, row.attempts, row.result, row.error) == ("done", 1, "/x/recon/s-fast", None)


def test_status_rows_say_when_a_running_claim_began_and_how_long_a_queued_job_waited(tmp_path):
    q = Queue(tmp_path / "q", lease_s=60)
    q.enqueue(_job("a"))
    q.enqueue(_job("b"))
    before = time.time()
    claim = q.claim()
    rows = {r.id: r for r in q.statuses()}
    running, queued = rows[claim.job.id], rows["b-fast" if claim.job.id == "a-fast" else "a-fast"]
    assert running.state == "running" and before <= running.claimed_unix <= time.time()
    assert running.waiting_s is None
    assert queued.state == "queued" and queued.claimed_unix is None and 0.0 <= queued.waiting_s < 60.0
    damaged = 0
    for path in (tmp_path / "q").rglob("*.json"):  # a damaged start in the claim's attempt record says nothing
        data = json.loads(path.read_text())
        if isinstance(data, dict) and data.get("token") == claim.token and "started_unix" in data:
            path.write_text(json.dumps({**data, "started_unix": "soon"}))
            damaged += 1
    assert damaged == 1
    assert {r.id: r for r in q.statuses()}[claim.job.id].claimed_unix is None


def test_expired_lease_is_taken_over_and_retried_then_failed(tmp_path):
    q = Queue(tmp_path / "q", lease_s=10, max_attempts=2)
    q.enqueue(_job("s"))
    first = q.claim(_elsewhere())
    assert q.reclaim_expired(now=time.time() + 5) == []
    assert q.reclaim_expired(now=time.time() + 11) == [("s-fast", "queued")]
    assert not q.heartbeat(first), "the old holder learns that it lost the lease"
    assert not q.finish(first), "and cannot finish the job any more"
    second = q.claim(_elsewhere())
    assert second.attempt == 2
    assert q.reclaim_expired(now=time.time() + 11) == [("s-fast", "failed")]
    (row,) = q.statuses()
    assert row.state == "failed" and row.attempts == 2
    assert "stopped renewing its lease" in row.error and "giving up" in row.error


def test_a_job_taken_over_is_handed_to_before_requeue_while_still_held_and_only_when_retried(tmp_path):
    q = Queue(tmp_path / "q", lease_s=10, max_attempts=2)
    q.enqueue(_job("s"))
    q.claim(_elsewhere())
    seen = []

    def note(job, why):
        seen.append((job.id, why, q.job_paths()[job.id][0]))

    assert q.reclaim_expired(now=time.time() + 11, before_requeue=note) == [("s-fast", "queued")]
    assert len(seen) == 1 and seen[0][0] == "s-fast" and seen[0][2] == "running", seen
    assert seen[0][1].startswith("worker another-host pid 12345 stopped renewing its lease"), seen
    q.claim(_elsewhere())
    assert q.reclaim_expired(now=time.time() + 11, before_requeue=note) == [("s-fast", "failed")]
    assert len(seen) == 1, "a job given up on is not queued again"


def test_concurrent_reclaims_take_an_expired_job_once(tmp_path):
    q = Queue(tmp_path / "q", lease_s=1, max_attempts=5)
    q.enqueue(_job("s"))
    q.claim(_elsewhere())
    later = time.time() + 2
    results = [q.reclaim_expired(now=later) for _ in range(3)]
    assert sum(len(r) for r in results) == 1
    assert q.counts()["queued"] == 1


def test_a_job_being_taken_over_is_not_taken_over_again(tmp_path, monkeypatch):
    """Worker B's reclaim pass runs while worker A is between renaming an expired job to its own name and settling it:
    B must not see A's file as expired (it would record a claim that never ran and use up an attempt)."""
    qa, qb = Queue(tmp_path / "q", lease_s=5, max_attempts=3), Queue(tmp_path / "q", lease_s=5, max_attempts=3)
    qa.enqueue(_job("s"))
    claim = qa.claim(_elsewhere())
    old = time.time() - 100
    os.utime(claim.path, (old, old))  # its holder stopped renewing the lease
    seen_by_b = []
    attempts = qa.attempts

    def b_reclaims_meanwhile(job_id):
        seen_by_b.extend(qb.reclaim_expired())
        return attempts(job_id)

    monkeypatch.setattr(qa, "attempts", b_reclaims_meanwhile)
    assert qa.reclaim_expired() == [("s-fast", "queued")]
    assert seen_by_b == []
    assert [r.get("outcome") for r in qb.records("s-fast")] == ["lost"]
    assert qb.attempts("s-fast") == 1
    assert qb.claim(_elsewhere()).attempt == 2


def test_the_oldest_queued_job_is_claimed_first(tmp_path):
    q = Queue(tmp_path / "q")
    for k, name in enumerate(["zebra", "apple", "mango"]):
        q.enqueue(_job(name))
        path = q.path / "queued" / f"{name}-fast.json"
        os.utime(path, (1_000_000 + k, 1_000_000 + k))  # queued in this order
    zebra = q.claim()
    assert zebra.job.scan == "zebra"
    q.release(zebra)  # given back: it goes behind the jobs queued before
    assert [q.claim().job.scan for _ in range(3)] == ["apple", "mango", "zebra"]


def test_a_live_job_is_claimed_before_a_backlog_of_finished_scans(tmp_path):
    """A live job follows a scan being recorded: behind the backlog, its fit would start after the scan's end."""
    q = Queue(tmp_path / "q")
    for k, (name, live) in enumerate([("old1", False), ("old2", False), ("now", True), ("later", False)]):
        q.enqueue(replace(_job(name), live=live))
        path = q.path / "queued" / f"{name}-fast.json"
        os.utime(path, (1_000_000 + k, 1_000_000 + k))  # queued in this order
    (q.path / "queued" / "damaged-fast.json").write_text("{not json")  # counts as not live; its claim fails it
    os.utime(q.path / "queued" / "damaged-fast.json", (999_999, 999_999))
    claimed = [q.claim() for _ in range(4)]
    assert [c.job.scan for c in claimed] == ["now", "old1", "old2", "later"]


def test_a_dead_holder_on_this_machine_frees_its_job_at_once(tmp_path):
    q = Queue(tmp_path / "q", lease_s=3600)
    q.enqueue(_job("s"))
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    dead = replace(Holder.current(), pid=proc.pid, pid_start="")
    assert holder_gone(dead.to_dict())
    assert not holder_gone(Holder.current().to_dict())
    assert not holder_gone(_elsewhere().to_dict()), "liveness of other machines' processes is unknown"
    q.claim(dead)
    assert q.reclaim_expired() == [("s-fast", "queued")]
    (row,) = q.statuses()
    assert "died mid-job" in row.error


def test_a_live_holder_keeps_its_job(tmp_path):
    q = Queue(tmp_path / "q", lease_s=3600)
    q.enqueue(_job("s"))
    q.claim()
    assert q.reclaim_expired() == []
    (row,) = q.statuses()
    assert row.state == "running" and row.holder.endswith(f":{os.getpid()}")


def test_input_errors_fail_at_once_crashes_retry(tmp_path):
    q = Queue(tmp_path / "q", max_attempts=3)
    q.enqueue(_job("bad"))
    q.enqueue(_job("flaky"))
    bad = q.claim()
    assert q.fail(bad, "capture: chunk-000000/hists.npy: corrupt\nsecond line", retry=False) == "failed"
    states = []
    while (c := q.claim()) is not None:
        states.append(q.crash(c, "job process killed by SIGKILL"))
    assert states == ["queued", "queued", "failed"]
    rows = {r.id: r for r in q.statuses()}
    assert rows["bad-fast"].error == "capture: chunk-000000/hists.npy: corrupt second line"
    assert rows["bad-fast"].attempts == 1
    assert rows["flaky-fast"].attempts == 3 and "giving up" in rows["flaky-fast"].error


def test_release_gives_a_job_back_without_using_an_attempt(tmp_path):
    q = Queue(tmp_path / "q", max_attempts=1)
    q.enqueue(_job("s"))
    assert q.release(q.claim())
    claim = q.claim()
    assert claim.attempt == 1
    assert q.crash(claim, "boom") == "failed"


def test_retry_failed_starts_the_count_again(tmp_path):
    q = Queue(tmp_path / "q", max_attempts=1)
    q.enqueue(_job("s"))
    q.fail(q.claim(), "bad", retry=False)
    assert q.retry_failed() == ["s-fast"]
    claim = q.claim()
    assert claim.attempt == 1
    q.finish(claim)
    (row,) = q.statuses()
    assert row.state == "done" and row.error is None


def _failed(q: Queue, job: Job) -> None:
    q.enqueue(job)
    q.fail(q.claim(), "device 'cuda' asked for, but torch sees no CUDA device", retry=False)


def test_retry_failed_with_changes_queues_the_job_with_them(tmp_path):
    q = Queue(tmp_path / "q", max_attempts=1)
    _failed(q, Job(id="s-fast", scan="s", device="cuda", seed=7, steps=5, budget_s=30.0))
    assert q.retry_failed(changes={"device": "cpu"}) == ["s-fast"]
    assert q.counts() == {"queued": 1, "running": 0, "done": 0, "failed": 0}
    claim = q.claim()
    assert (claim.job.device, claim.job.seed, claim.job.steps, claim.job.budget_s) == ("cpu", 7, 5, 30.0)
    assert claim.attempt == 1
    q.fail(claim, "bad", retry=False)
    assert q.retry_failed(changes={"seed": 3}) == ["s-fast"], "a job changed once can be changed again"
    assert (q.claim().job.device, q.attempts("s-fast")) == ("cpu", 1)
    assert q.repair(min_age_s=0) == [] and not list((q.path / "tmp").iterdir()), "no second copy of the job"


def test_retry_failed_without_changes_keeps_the_jobs_options(tmp_path):
    q = Queue(tmp_path / "q")
    _failed(q, Job(id="s-fast", scan="s", device="cuda", seed=7))
    assert q.retry_failed(changes={}) == ["s-fast"]
    assert (q.claim().job.device, q.known("s-fast")) == ("cuda", True)


def test_retry_failed_picks_a_preset_and_never_changes_one(tmp_path):
    q = Queue(tmp_path / "q")
    _failed(q, _job("s", "fast"))
    _failed(q, _job("s", "paper"))
    assert q.retry_failed(preset="paper", changes={"device": "cpu"}) == ["s-paper"]
    assert q.counts()["failed"] == 1
    with pytest.raises(ConfigError, match="cannot change preset"):
        q.retry_failed(changes={"preset": "paper"})
    assert q.counts()["failed"] == 1, "nothing moved"


def test_a_retry_cut_short_leaves_the_job_to_repair(tmp_path, monkeypatch):
    """A crash while the changed job file is written: `repair` queues the job as it was, once (also a job that was
    changed before: its changed file is the registered one)."""
    import spadscan.worker.queue as queue_module

    q = Queue(tmp_path / "q")
    _failed(q, Job(id="s-fast", scan="s", device="auto"))
    q.retry_failed(changes={"device": "cuda"})
    q.fail(q.claim(), "no CUDA device", retry=False)
    hour_ago = time.time() - 3600
    os.utime(q.path / "failed" / "s-fast.json", (hour_ago, hour_ago))  # failed long ago

    def disk_full(path, data):
        raise OSError("No space left on device")

    monkeypatch.setattr(queue_module, "_write_new", disk_full)
    with pytest.raises(OSError):
        q.retry_failed(changes={"device": "cpu"})
    monkeypatch.undo()
    assert q.counts() == {"queued": 0, "running": 0, "done": 0, "failed": 0}
    assert q.repair(min_age_s=60) == [], "a retry in progress is left alone"
    assert q.repair(min_age_s=0) == ["s-fast"]
    assert q.claim().job.device == "cuda" and q.claim() is None


def test_repair_queues_a_job_whose_enqueue_was_cut_short(tmp_path):
    q = Queue(tmp_path / "q")
    job = _job("s")
    tmp = q.path / "tmp" / f"{job.id}~abc.json"
    tmp.write_text(json.dumps(job.to_dict()))
    os.link(tmp, q.path / "ids" / f"{job.id}.json")  # registered, then the process died before queuing it
    assert q.repair(min_age_s=3600) == [], "a recent enqueue may still be in progress"
    assert q.repair(min_age_s=0) == ["s-fast"]
    assert q.claim().job == job


def test_an_unreadable_job_file_fails_that_job_only(tmp_path):
    q = Queue(tmp_path / "q")
    (q.path / "queued" / "junk.json").write_text("{not json")
    q.enqueue(_job("s"))
    claim = q.claim()
    assert claim is not None and claim.job.id == "s-fast"
    rows = {r.id: r for r in q.statuses()}
    assert rows["junk"].state == "failed" and "unreadable job file" in rows["junk"].error


def test_a_folder_in_place_of_a_job_file_fails_that_job_only(tmp_path):
    """Read once taken, it raised IsADirectoryError out of the claim: no job was claimed, poll after poll, and the
    taken one waited in running/ without a record until its lease ran out."""
    q = Queue(tmp_path / "q")
    (q.path / "queued" / "junk.json").mkdir()
    q.enqueue(_job("s"))
    claim = q.claim()
    assert claim is not None and claim.job.id == "s-fast"
    rows = {r.id: r for r in q.statuses()}
    assert rows["junk"].state == "failed" and "unreadable job file" in rows["junk"].error, rows["junk"]


def test_a_job_file_this_process_may_not_take_is_passed_over_and_named(tmp_path, monkeypatch):
    """Another user's job file on a shared queue (its utime refused: EACCES) stopped every claim of the worker, which
    said only "Permission denied"; the others are claimed now, and the one passed over is named with its file."""
    q = Queue(tmp_path / "q")
    theirs, mine = _job("theirs"), _job("mine")
    q.enqueue(theirs)
    q.enqueue(mine)
    old = time.time() - 60  # the oldest: claimed first
    os.utime(q.path / "queued" / f"{theirs.id}.json", (old, old))
    real = os.utime

    def utime(path, *args, **kwargs):
        if str(path).endswith(f"queued/{theirs.id}.json"):
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "utime", utime)
    skipped = []
    claim = q.claim(skipped=skipped)
    assert claim is not None and claim.job.id == mine.id
    assert [(job_id, str(exc)) for job_id, exc in skipped] == [
        (theirs.id, f"[Errno 13] Permission denied: '{q.path / 'queued' / f'{theirs.id}.json'}'")]
    assert {r.id: r.state for r in q.statuses()}[theirs.id] == "queued"


@pytest.mark.parametrize("record, why", [
    ({"id": "bad", "scan": None}, "scan = null is not a string"),
    ({"id": "bad", "scan": ["s"]}, 'scan = ["s"] is not a string'),
    ({"id": "bad", "scan": "s", "steps": "many"}, 'steps = "many" is not an integer or null'),
    ({"id": "bad", "scan": "s", "live": 1}, "live = 1 is not true or false"),
])
def test_a_job_file_of_the_wrong_types_fails_that_job_only(tmp_path, record, why):
    """A job file another tool wrote, valid JSON but with a field of the wrong type, fails with the reason: the
    worker that claims it must not die on it (each restart would claim it again)."""
    q = Queue(tmp_path / "q")
    (q.path / "queued" / "bad.json").write_text(json.dumps(record))
    q.enqueue(_job("s"))
    claim = q.claim()
    assert claim is not None and claim.job.id == "s-fast"
    rows = {r.id: r for r in q.statuses()}
    assert rows["bad"].state == "failed" and why in rows["bad"].error, rows["bad"].error


def test_damaged_attempt_records_never_stop_the_queue(tmp_path):
    """A record that is not a JSON object is set aside, and a record's damaged numbers read as unknown: claims,
    expiry and retries go on."""
    q = Queue(tmp_path / "q", lease_s=5)
    q.enqueue(_job("s"))
    first = q.claim(_elsewhere())
    (q.path / "attempts" / "s-fast" / f"{first.token}.json").write_text('{"lease_s": "y", "started_unix": "x"}')
    (q.path / "attempts" / "s-fast" / "0000000000000000.json").write_text("[]")
    assert q.reclaim_expired(now=time.time() + 60) == [("s-fast", "queued")]
    claim = q.claim()
    assert claim is not None and claim.attempt == 2, "the damaged record is not an attempt"
    records, bad = q.read_records("s-fast")
    assert [p.name for p in bad] == ["0000000000000000.json"] and len(records) == 2


def test_a_claim_is_dead_only_when_it_can_never_publish(tmp_path):
    q = Queue(tmp_path / "q", lease_s=5)
    for name in ("live", "gone", "far", "done"):
        q.enqueue(_job(name))
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    live = q.claim()  # this process: alive
    gone = q.claim(replace(Holder.current(), pid=proc.pid, pid_start=""))
    far = q.claim(_elsewhere())
    done = q.claim()
    q.finish(done)
    assert not q.claim_is_dead(live.job.id, live.token)
    assert q.claim_is_dead(gone.job.id, gone.token), "its holder died on this machine"
    assert not q.claim_is_dead(far.job.id, far.token), "another machine's holder may be alive while its lease holds"
    assert not q.claim_is_dead(done.job.id, done.token), "a finished claim's holder may be publishing its result"
    assert not q.claim_is_dead("far-fast", "0" * 16), "an unknown claim is left alone"
    q.reclaim_expired(now=time.time() + 60)  # the far holder's lease expires: its claim is lost
    assert q.claim_is_dead(far.job.id, far.token)


def test_a_claim_put_back_never_ages_another_workers_claim_made_meanwhile(tmp_path, monkeypatch):
    """Worker A's claim cannot write its record (the queue's disk full) and puts the job back with its old times;
    worker B claims it at that moment (its utime, A's restore of the old times, its rename). Before: A restored
    the times on the file in queued/, so B's fresh claim got the hour-old mtime, its lease looked expired, and the
    job could be taken over while B ran it."""
    q, other = Queue(tmp_path / "q"), Queue(tmp_path / "q")
    q.enqueue(Job(id="s-fast", scan="s"))
    old = time.time() - 3600
    os.utime(q.path / "queued" / "s-fast.json", (old, old))
    real_utime, real_rename = os.utime, os.rename
    restore: dict = {}
    b_claims: list = []

    def utime(path, times=None, *, ns=None, **kwargs):
        if ns is not None and not restore and not b_claims:  # A restores the old times: B claims right now
            restore["args"] = (path, ns)
            b_claims.append(other.claim())
        return real_utime(path, times, ns=ns, **kwargs) if ns is not None else real_utime(path, times, **kwargs)

    def rename(src, dst, **kwargs):
        if restore and "running" in str(dst) and "done" not in restore:  # B's rename: A's restore comes first
            restore["done"] = True
            try:
                real_utime(restore["args"][0], ns=restore["args"][1])
            except FileNotFoundError:
                pass
        return real_rename(src, dst, **kwargs)

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "utime", utime)
    monkeypatch.setattr(os, "rename", rename)
    monkeypatch.setattr(q, "_write_record", full)
    with pytest.raises(OSError):
        q.claim()
    monkeypatch.undo()
    claim = (b_claims and b_claims[0]) or other.claim()
    assert claim is not None and claim.job.id == "s-fast"
    assert time.time() - claim.path.stat().st_mtime < 60, "B's lease starts at its claim"
    assert other.reclaim_expired() == [], "B's live lease is not taken over"
