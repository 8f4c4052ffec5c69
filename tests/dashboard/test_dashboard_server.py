"""The dashboard's server: what /api/status says of a root, that nothing outside the root is served and that every
link it gives is served, that a malformed capture is an error row, and that a root of 500 scans costs a stat per scan
per poll once read."""

from __future__ import annotations

import datetime as _dt

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from contextlib import contextmanager

import numpy as np
import pytest

from dashboard_helpers import (add_final_recon, complete_scan, get, queue_with_a_kept_result_and_a_damaged_record,
                               scan_with_non_finite_results, serving, status)
from page_helpers import add_pose, start_scan
from spadscan.commands.dashboard import daemon_running
from spadscan.daemon.root_lock import RootLock
from spadscan.protocol.capture_writer import mark_paused
from spadscan.protocol.errors import SpadscanError
from spadscan.worker.job_progress import parse_progress


@contextmanager
def lock_holder(root):
    """A process that holds the captures root's lock as a daemon does (the daemon's own RootLock), until killed."""
    code = ("import sys; from spadscan.daemon.root_lock import RootLock; RootLock(sys.argv[1]).acquire(); "
            "print('held', flush=True); sys.stdin.read()")
    proc = subprocess.Popen([sys.executable, "-c", code, str(root)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline() == "held\n"
        yield proc
    finally:
        proc.kill()
        proc.wait(30)


@contextmanager
def dashboard_command(root):
    """`spadscan dashboard --root ROOT --port 0` in its own process; yields the address it says it serves."""
    proc = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "dashboard", "--root", str(root), "--port", "0"],
                            stderr=subprocess.PIPE, text=True)
    try:
        said = proc.stderr.readline()
        found = re.search(r" at (http://\S+/) ", said)
        assert found, said
        yield found.group(1)
    finally:
        proc.terminate()
        proc.wait(30)


def strict_json(body: bytes):
    """JSON as a browser's JSON.parse reads it: NaN and Infinity are no JSON."""
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON: a browser refuses the whole answer")
    return json.loads(body, parse_constant=refuse)


def fetch_status(url: str) -> dict:
    with urllib.request.urlopen(url + "api/status", timeout=30) as answer:
        return strict_json(answer.read())


def test_status_lists_scans_with_progress_and_the_scan_in_hand(tmp_path):
    complete_scan(tmp_path / "done", 3)
    writer, poses = start_scan(tmp_path / "going", 8)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    with serving(tmp_path) as server:
        st = status(server)
        rows = {s["name"]: s for s in st["scans"]}
        assert rows["done"]["state"] == "complete" and rows["done"]["poses"] == 3 and rows["done"]["progress"] == 1
        assert rows["going"]["state"] == "running" and (rows["going"]["poses"], rows["going"]["planned"]) == (3, 8)
        assert st["scans"][0]["name"] == "going"  # running scans first
        current = st["current"]
        assert current["name"] == "going"
        assert current["frames_per_s"] == pytest.approx(2.0)  # t_end 10.25, 10.75, 11.25
        hist = current["histograms"]
        assert hist["zones"] == 9 and len(hist["counts"]) == 9 and max(hist["counts"][8]) == 280
        add_pose(writer, poses, 3)
        assert {s["name"]: s for s in status(server)["scans"]}["going"]["poses"] == 4


def test_nothing_outside_the_root_is_served(tmp_path):
    root = tmp_path / "captures"
    complete_scan(root / "scan", 1)
    (root / "scan" / "note.txt").write_text("inside")
    (tmp_path / "secret.txt").write_text("outside")
    (root / "scan" / "link.txt").symlink_to(tmp_path / "secret.txt")
    (root / ".queue").mkdir()
    (root / ".queue" / "job.json").write_text("{}")
    with serving(root) as server:
        assert get(server, "/files/scan/note.txt") == (200, b"inside")
        for path in ("/files/../secret.txt", "/files/scan/../../secret.txt", "/files/%2e%2e/secret.txt",
                     "/files/scan/%2e%2e/%2e%2e/secret.txt", "/files/scan%2f..%2f..%2fsecret.txt",
                     "/files//" + str(tmp_path / "secret.txt"), "/files/scan/link.txt", "/files/.queue/job.json",
                     "/files/scan", "/files/", "/../secret.txt", "/live3d/..", "/live3d/scan", "/nowhere",
                     "/files/scan/" + "a" * 300):  # a name the system refuses (over 255 bytes) is no file either
            code, body = get(server, path)
            assert code == 404 and b"outside" not in body, path


def test_a_malformed_capture_is_an_error_row(tmp_path):
    complete_scan(tmp_path / "good", 2)
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "scan.json").write_text("{ not json")
    (tmp_path / "stranger").mkdir()
    (tmp_path / "stranger" / "scan.json").write_text(json.dumps({"format": "something-else"}))
    with serving(tmp_path) as server:
        rows = {s["name"]: s for s in status(server)["scans"]}
    assert rows["good"]["state"] == "complete" and rows["good"]["error"] is None
    for name in ("broken", "stranger"):
        assert rows[name]["state"] == "error" and name in rows[name]["error"], rows[name]
        assert "\n" not in rows[name]["error"]


def test_a_field_of_the_wrong_type_is_that_scans_error_row_and_the_others_are_listed(tmp_path):
    complete_scan(tmp_path / "good", 2)
    wrong = {"schedule": {"schedule": [1, 2, 3]}, "views": {"schedule": {"views": "12"}},
             "planned_poses": {"planned_poses": "12"}, "updated_utc": {"updated_utc": 5},
             "reason": {"reason": ["cable"]}}
    for name, fields in wrong.items():
        complete_scan(tmp_path / name, 2)
        manifest = json.loads((tmp_path / name / "scan.json").read_text())
        manifest.update({"planned_poses": None, **fields})  # none planned: the schedule's views are read
        (tmp_path / name / "scan.json").write_text(json.dumps(manifest))
    recon = tmp_path / "good" / "recon" / "good-fast"
    recon.mkdir(parents=True)
    (recon / "report.json").write_text(json.dumps({"preset": "fast", "warnings": 5}))  # the page iterates them
    with serving(tmp_path) as server:
        st = status(server)
    rows = {s["name"]: s for s in st["scans"]}
    assert rows["good"]["state"] == "complete" and rows["good"]["error"] is None and st["current"]["name"] == "good"
    for name in wrong:
        assert rows[name]["state"] == "error" and f"{name} " in rows[name]["error"], rows[name]
        assert "scan.json" in rows[name]["error"] and "\n" not in rows[name]["error"]
    (recon_row,) = rows["good"]["recons"]
    assert recon_row["error"] == "report.json: warnings 5 is not a list" and "warnings" not in recon_row["summary"]


def test_the_histogram_axis_labels_the_centre_of_the_bin_that_holds_a_return():
    from spadscan.dashboard.scans import plot_histograms
    from spadscan.protocol.sensor_presets import tmf8820

    sensor = tmf8820()
    for bins in (sensor.n_bins, 1024):  # plotted as they are, and max-pooled by 4
        for range_m in 0.5 + sensor.bin_width_m * np.array([0.02, 0.5, 0.98, 2.7, 3.95]):
            hist = np.zeros((1, bins))
            hist[0, int(np.floor(sensor.bin_of_range(range_m)))] = 100  # the simulator counts t in bin floor(t)
            h = plot_histograms(hist, sensor)
            shown = h["first_m"] + int(np.argmax(h["counts"][0])) * h["bin_m"]
            assert abs(shown - range_m) <= h["bin_m"] / 2 + 1e-9, (bins, range_m, shown)


def test_the_queue_and_each_running_jobs_progress(tmp_path):
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    complete_scan(tmp_path / "scan", 2)
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="scan-fast", scan="scan"))
    claim = queue.claim()
    (queue.path / "logs").mkdir(exist_ok=True)
    (queue.path / "logs" / f"{claim.path.stem}.log").write_text(
        "reconstruct (fast):  10%|#  | 12/120 s [00:12<01:48, loss=9.1]\r"
        "reconstruct (fast):  58%|#####     | 70/120 s [01:10<00:50, loss=2.25, chamfer=1.86mm]\r")
    with serving(tmp_path) as server:
        (job,) = status(server)["queue"]["jobs"]
    assert job["id"] == "scan-fast" and job["state"] == "running"
    assert job["progress"]["fraction"] == pytest.approx(70 / 120) and job["progress"]["chamfer_mm"] == 1.86
    assert job["progress"]["line"].startswith("reconstruct (fast): 70/120 s, loss 2.25, Chamfer 1.86 mm")


def test_the_queue_says_of_kept_results_and_damaged_files_what_worker_status_says(tmp_path, capsys):
    from spadscan.cli import main

    said = queue_with_a_kept_result_and_a_damaged_record(tmp_path)
    assert main(["worker", "--root", str(tmp_path), "--status"]) == 0
    printed = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    with serving(tmp_path) as server:
        jobs = {j["id"]: j for j in status(server)["queue"]["jobs"]}
    for job_id, detail in said.items():
        assert jobs[job_id]["detail"] == detail and printed[job_id].endswith("  " + detail), (jobs[job_id], printed)


def test_a_progress_bar_is_read_with_every_field_it_carries():
    p = parse_progress("junk\rreconstruct (fast):  5%|   | 3/60 s [00:03<00:57, step=40, loss=3.2e+03]\r")
    assert (p.done, p.total, p.unit, p.fields) == (3.0, 60.0, "s", {"step": "40", "loss": "3.2e+03"})
    assert "step 40" in p.line() and p.chamfer_mm is None
    assert parse_progress("no bar here") is None


def test_finished_and_live_reconstructions_with_their_pages(tmp_path):
    complete_scan(tmp_path / "scan", 2)
    final = tmp_path / "scan" / "recon" / "scan-fast"
    final.mkdir(parents=True)
    (final / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 1.5, "converged": False,
                                                   "warnings": ["stopped on its budget at 3% of its steps"]}))
    (final / "report.html").write_text("<html></html>")
    (final / "coverage.png").write_bytes(b"\x89PNG coverage")
    live = tmp_path / "scan" / "recon" / "live"
    live.mkdir()
    (live / "status.json").write_text(json.dumps({"views_used": 12, "steps": 300, "converged": False}))
    (live / "preview.png").write_bytes(b"\x89PNG")
    (tmp_path / "scan" / "recon" / "scan-fast.replaced-20260101T000000Z-abcd").mkdir()
    with serving(tmp_path) as server:
        (scan,) = status(server)["scans"]
        first, second = scan["recons"]
        assert first["kind"] == "live" and first["summary"]["views_used"] == 12
        assert "view3d.html" not in first["files"]  # no live mesh yet
        assert second["summary"]["warnings"] == ["stopped on its budget at 3% of its steps"]
        assert second["summary"]["converged"] is False
        assert get(server, second["files"]["report.html"]) == (200, b"<html></html>")
        assert get(server, first["files"]["preview.png"])[0] == 200
        assert get(server, second["files"]["coverage.png"]) == (200, b"\x89PNG coverage")
        assert "coverage.png" not in first["files"] and "preview.png" not in second["files"]


def test_every_url_of_a_scan_or_job_with_an_odd_name_is_served(tmp_path):
    import trimesh

    names = ["cup #2 100%", "what?", "gain 100%41", "tasse-é", os.fsdecode(b"caf\xe9 #1")]  # the last: not UTF-8
    held = {}
    for name in names:
        complete_scan(tmp_path / name, 2)
        held[name] = add_final_recon(tmp_path / name)
    live = tmp_path / names[0] / "recon" / "live"
    live.mkdir()
    (live / "status.json").write_text(json.dumps({"views_used": 2, "steps": 10}))
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(live / "mesh.ply")
    with serving(tmp_path) as server:
        scans = {s["name"]: s for s in status(server)["scans"]}
        assert sorted(scans) == sorted(names)
        for name in names:
            final = next(r for r in scans[name]["recons"] if r["kind"] == "final")
            assert final["id"] == "job #1?" and set(final["files"]) == set(held[name])
            for file, data in held[name].items():
                assert get(server, final["files"][file]) == (200, data), (name, final["files"][file])
        (live_row,) = [r for r in scans[names[0]]["recons"] if r["kind"] == "live"]
        assert get(server, live_row["files"]["mesh.ply"])[0] == 200
        code, page = get(server, live_row["files"]["view3d.html"])
        assert code == 200 and b"cup #2 100% (live)" in page


def test_a_scan_folder_linked_out_of_the_root_is_listed_without_links_and_says_why(tmp_path):
    from spadscan.dashboard.scans import LINKED_OUT

    root, elsewhere = tmp_path / "captures", tmp_path / "otherdisk"
    for folder in (root / "here", elsewhere / "cup"):
        complete_scan(folder, 2)
        add_final_recon(folder, "job1")
    (root / "cup").symlink_to(elsewhere / "cup")  # captures moved to a bigger disk and linked back
    (root / "alias").symlink_to(root / "here")  # a link inside the root is served like the folder itself
    with serving(root) as server:
        rows = {s["name"]: s for s in status(server)["scans"]}
        assert rows["cup"]["state"] == "complete" and rows["cup"]["note"] == LINKED_OUT
        (recon,) = rows["cup"]["recons"]
        assert recon["summary"]["chamfer_mm"] == 1.0 and recon["files"] == {}
        assert get(server, "/files/cup/recon/job1/report.html")[0] == 404  # what the missing links would answer
        for name in ("here", "alias"):
            (recon,) = rows[name]["recons"]
            assert rows[name]["note"] is None and get(server, recon["files"]["report.html"])[0] == 200


def test_five_hundred_scans_cost_one_read_each_once_and_nothing_after(tmp_path):
    import shutil

    complete_scan(tmp_path / "scan-000", 2)
    for i in range(1, 500):
        shutil.copytree(tmp_path / "scan-000", tmp_path / f"scan-{i:03d}")
    with serving(tmp_path) as server:
        dashboard = server.RequestHandlerClass.keywords["dashboard"]
        assert len(status(server)["scans"]) == 500
        first_reads = dashboard.scans.reads
        assert first_reads <= 2 * 500  # each manifest and the last chunk's records, once
        assert len(status(server)["scans"]) == 500
        assert dashboard.scans.reads == first_reads  # nothing changed, nothing read again


def test_a_live_mesh_gets_its_3d_view_made_on_demand(tmp_path):
    import trimesh

    complete_scan(tmp_path / "scan", 2)
    live = tmp_path / "scan" / "recon" / "live"
    live.mkdir(parents=True)
    (live / "status.json").write_text(json.dumps({"views_used": 2, "steps": 10}))
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(live / "mesh.ply")
    with serving(tmp_path) as server:
        (recon,) = status(server)["scans"][0]["recons"]
        code, page = get(server, recon["files"]["view3d.html"])
        assert code == 200 and b"OfflineLocalView.load" in page and b"scan (live)" in page
        assert get(server, recon["files"]["view3d.html"]) == (200, page)  # kept while the mesh is unchanged


def test_the_command_refuses_an_empty_host_and_a_queue_that_is_not_there_in_one_line(tmp_path, capsys):
    from spadscan.cli import main

    (tmp_path / "afile").write_text("x")
    cases = [(["--host", ""], "--host '' would listen on every interface"),
             (["--queue", str(tmp_path / "nope")], f"--queue {tmp_path / 'nope'}: no such queue folder"),
             (["--queue", str(tmp_path / "afile")], "(a file, not a folder)")]
    for extra, message in cases:
        assert main(["dashboard", "--root", str(tmp_path), "--port", "0", *extra]) == 1
        err = capsys.readouterr().err
        assert err.startswith("spadscan: error: ") and message in err and err.count("\n") == 1, err
    assert main(["dashboard", "--root", str(tmp_path / "afile")]) == 1
    assert "no such captures root (a file, not a folder)" in capsys.readouterr().err


def test_a_paused_scan_says_so_and_why_and_shows_no_frame_rate(tmp_path):
    """The daemon records a pause in scan.json (the operator's, or a fault's): the page shows the scan in hand as
    paused with the reason, not as running at its last frame rate; its last update is its last pose's."""
    writer, poses = start_scan(tmp_path / "held", 8)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    mark_paused(tmp_path / "held", "sensor silent: no frame within 5 s")
    with serving(tmp_path) as server:
        current = status(server)["current"]
        assert (current["name"], current["state"]) == ("held", "paused")
        assert current["reason"] == "sensor silent: no frame within 5 s"
        assert "frames_per_s" not in current
        writer.set_state("running")  # resumed
        add_pose(writer, poses, 3, t_s=11.5)
        current = status(server)["current"]
        assert current["state"] == "running" and current["reason"] is None and current["frames_per_s"] > 0
        last = max((tmp_path / "held").glob("chunk-*")).stat().st_mtime
        assert current["updated_utc"] >= _dt.datetime.fromtimestamp(last, _dt.timezone.utc).isoformat(
            timespec="milliseconds")


def test_a_running_scan_whose_daemon_was_killed_shows_as_interrupted_without_a_frame_rate(tmp_path):
    """The daemon holds the root's lock for its life and the kernel drops it when the daemon dies (kill -9 too):
    `spadscan dashboard` then shows its scan as interrupted, not as running at its last frame rate."""
    writer, poses = start_scan(tmp_path / "s1", 8)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    with lock_holder(tmp_path) as daemon, dashboard_command(tmp_path) as url:
        current = fetch_status(url)["current"]
        assert (current["name"], current["state"]) == ("s1", "running") and current["frames_per_s"] > 0
        daemon.kill()  # SIGKILL: the daemon has no say
        daemon.wait(30)
        st = fetch_status(url)
        current = st["current"]
        assert (current["name"], current["state"], current["reason"]) == ("s1", "interrupted", "no daemon running")
        assert "frames_per_s" not in current and "poses_per_min" not in current
        assert (current["poses"], current["planned"]) == (3, 8)  # what is on disk is still shown
        (row,) = st["scans"]
        assert (row["state"], row["reason"]) == ("interrupted", "no daemon running")


def test_a_scan_in_hand_is_interrupted_only_while_no_daemon_holds_the_root(tmp_path):
    complete_scan(tmp_path / "done", 2)
    writer, poses = start_scan(tmp_path / "going", 8)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    with serving(tmp_path, daemon_running=daemon_running) as server:
        st = status(server)
        rows = {s["name"]: s for s in st["scans"]}
        assert rows["going"]["state"] == "interrupted" and rows["done"]["state"] == "complete"
        assert st["scans"][0]["name"] == st["current"]["name"] == "going"  # still listed first, still in hand
        assert "frames_per_s" not in st["current"]
        with RootLock(tmp_path):  # a daemon started on the root: the scan is its again
            current = status(server)["current"]
            assert (current["state"], current["reason"]) == ("running", None)
            assert current["frames_per_s"] == pytest.approx(2.0)
        mark_paused(tmp_path / "going", "operator: cable check")  # paused, then the daemon went
        current = status(server)["current"]
        assert current["state"] == "interrupted" and "frames_per_s" not in current
        assert current["reason"] == "no daemon running; it was paused: operator: cable check"
    with serving(tmp_path) as server:  # no way to ask: shown as scan.json says
        assert status(server)["current"]["state"] == "paused"


def test_non_finite_numbers_in_damaged_files_are_null_and_every_scan_is_still_listed(tmp_path):
    """json.loads reads NaN and Infinity, which a browser's JSON.parse refuses: /api/status stays strict JSON."""
    scan_with_non_finite_results(tmp_path / "done")
    complete_scan(tmp_path / "torn", 2)
    last = max((tmp_path / "torn").glob("chunk-*")) / "meta.json"
    meta = json.loads(last.read_text())
    meta["measurements"][-1]["pose_index"] = float("inf")  # int() of it overflows
    last.write_text(json.dumps(meta))
    writer, poses = start_scan(tmp_path / "going", 8)
    for i in range(4):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    last = max((tmp_path / "going").glob("chunk-*")) / "meta.json"
    meta = json.loads(last.read_text())
    meta["measurements"][-1]["t_end"] = float("nan")
    last.write_text(json.dumps(meta))
    with serving(tmp_path) as server:
        code, body = get(server, "/api/status")
    assert code == 200
    st = strict_json(body)
    rows = {s["name"]: s for s in st["scans"]}
    assert set(rows) == {"done", "torn", "going"}
    live_row, final_row = rows["done"]["recons"]
    assert live_row["summary"] == {"views_used": 3, "chamfer_mm": None}
    assert final_row["summary"] == {"preset": "fast", "chamfer_mm": None, "seconds": None}
    assert "torn" in rows["torn"]["error"] and "unreadable measurement records" in rows["torn"]["error"]
    assert st["current"]["name"] == "going"
    current = st["current"]  # rates over the three good records (t_end 10.25 .. 11.25)
    assert (current["frames_per_s"], current["poses_per_min"]) == (pytest.approx(2.0), pytest.approx(120.0))


def test_one_captures_folder_given_as_the_root_is_refused_naming_its_parent(tmp_path, capsys):
    """The page of one capture would list no scans and a queue that does not exist; the worker refuses it too."""
    from spadscan.cli import main
    from spadscan.dashboard.server import make_server

    complete_scan(tmp_path / "m1", 2)
    with pytest.raises(SpadscanError) as info:
        make_server(tmp_path / "m1", "127.0.0.1", 0)
    assert str(info.value) == (f"{tmp_path / 'm1'} holds scan.json: it is a capture, not a captures root "
                               f"(use --root {tmp_path})")
    assert main(["dashboard", "--root", str(tmp_path / "m1"), "--port", "0"]) == 1
    err = capsys.readouterr().err
    assert err == f"spadscan: error: {info.value}\n", err


def serve_once(monkeypatch):
    """Make `spadscan dashboard` stop as Ctrl-C stops it as soon as it would serve (its start-up lines written)."""
    import spadscan.dashboard.server as server_module

    real = server_module.make_server

    def stopping(*args, **kwargs):
        server = real(*args, **kwargs)

        def interrupted(**_):
            raise KeyboardInterrupt
        server.serve_forever = interrupted
        return server

    monkeypatch.setattr(server_module, "make_server", stopping)


def test_a_root_without_scans_is_served_saying_there_are_none_yet(tmp_path, capsys, monkeypatch):
    from spadscan.cli import main

    serve_once(monkeypatch)
    (tmp_path / ".queue").mkdir()  # the worker's queue is no scan
    (tmp_path / "notes").mkdir()
    assert main(["dashboard", "--root", str(tmp_path), "--port", "0"]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3 and " at http://127.0.0.1:" in lines[0] and lines[2] == "spadscan dashboard: stopped", lines
    assert lines[1] == (f"spadscan dashboard: no scans in {tmp_path} yet (a scan is a sub-folder holding scan.json); "
                        f"the page lists them as they appear"), lines
    complete_scan(tmp_path / "m1", 2)
    assert main(["dashboard", "--root", str(tmp_path), "--port", "0"]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and " at http://127.0.0.1:" in lines[0], lines
    missing = tmp_path / "not-yet"  # a dashboard service started before the daemon's first scan
    assert main(["dashboard", "--root", str(missing), "--port", "0"]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert lines[1] == (f"spadscan dashboard: the captures root {missing} does not exist yet; the page waits for it "
                        f"(the daemon creates it at its first scan)"), lines
    assert not missing.exists(), "the dashboard only reads"


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_dashboard_stopped_by_ctrl_c_or_sigterm_says_so_and_exits_0(tmp_path, stop):
    complete_scan(tmp_path / "m1", 2)
    # SIGINT at its default, as a terminal's Ctrl-C finds it (a child of a background job would inherit it ignored).
    proc = subprocess.Popen([sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, "
                             "signal.default_int_handler); from spadscan.cli import main; sys.exit(main(sys.argv[1:]))",
                             "dashboard", "--root", str(tmp_path), "--port", "0"], stderr=subprocess.PIPE, text=True)
    try:
        url = re.search(r" at (http://\S+/) ", proc.stderr.readline()).group(1)
        assert fetch_status(url)["scans"]  # serving: the signal comes while it waits for requests
        proc.send_signal(stop)
        rest = proc.stderr.read()
        assert proc.wait(30) == 0, rest
    finally:
        proc.kill()
        proc.wait(30)
    assert rest.splitlines() == ["spadscan dashboard: stopped"], rest


def test_connections_left_open_are_closed_and_capped(tmp_path, monkeypatch):
    """1,020 idle connections took every file and a thread each of the dashboard, and every page's polls timed out.
    A silent connection is closed after IDLE_S, and one more than MAX_CONNECTIONS gets a 503 and is closed."""
    import socket

    from spadscan.dashboard import server as dashboard_server

    monkeypatch.setattr(dashboard_server.DashboardServer, "max_connections", 2)
    monkeypatch.setattr(dashboard_server.Handler, "timeout", 0.3)
    complete_scan(tmp_path / "a")
    with serving(tmp_path) as server:
        where = server.server_address[:2]
        idle = [socket.create_connection(where, timeout=30) for _ in range(2)]  # accepted in order: both served
        extra = socket.create_connection(where, timeout=30)
        try:
            turned_away = extra.makefile("rb").read()
            assert turned_away.startswith(b"HTTP/1.0 503 Service Unavailable\r\n"), turned_away
            assert turned_away.endswith(b"\r\n\r\ntoo many connections open to the dashboard\n"), turned_away
            for conn in idle:  # closed by the server after their silence, nothing said
                assert conn.makefile("rb").read() == b""
            for _ in range(600):  # their slots given back as their threads end: served again
                code, _ = get(server, "/api/status")
                if code == 200:
                    break
                time.sleep(0.05)
            assert code == 200
        finally:
            for conn in [*idle, extra]:
                conn.close()
