"""What /api/status says of a live reconstruction once it ended or stopped, of a scan no longer taking frames, and
that the server listens on an IPv6 address: a done live fit gives way to its result (never its final figures over
the live fit's last picture), a live fit says its state, note and age, rates are a running scan's only."""

from __future__ import annotations

import datetime as _dt
import http.client
import json
import os
import socket
import threading

import pytest
import trimesh

from dashboard_helpers import add_final_recon, complete_scan, get, serving, status
from page_helpers import add_pose, start_scan
from spadscan.dashboard.results import ResultIndex
from spadscan.dashboard.server import address, make_server


def live_status(scan_path, **fields) -> None:
    """A live folder with a mesh, a preview and a status.json of `fields`."""
    live = scan_path / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(live / "mesh.ply")
    (live / "preview.png").write_bytes(b"\x89PNG the live fit's last")
    (live / "status.json").write_text(json.dumps({"views_used": 18, "views_published": 18, "steps": 0, **fields}))


def test_a_done_live_reconstruction_gives_way_to_the_result_it_names(tmp_path):
    scan = tmp_path / "scan"
    complete_scan(scan, 2)
    add_final_recon(scan, "scan-fast")
    add_final_recon(scan, "scan-baseline")  # newer: listed first while the live fit runs
    later = (scan / "recon" / "scan-fast" / "report.json").stat().st_mtime + 5
    os.utime(scan / "recon" / "scan-baseline" / "report.json", (later, later))
    live_status(scan, state="final", chamfer_mm=119.1)
    with serving(tmp_path) as server:
        recons = status(server)["scans"][0]["recons"]
        assert [r["id"] for r in recons] == ["live", "scan-baseline", "scan-fast"], "while it runs: as it is"
        assert recons[0]["files"]["preview.png"].startswith("/files/scan/recon/live/preview.png")
        live_status(scan, views_used=64, views_published=64, steps=242, chamfer_mm=3.22, state="done",
                    result=str(scan / "recon" / "scan-fast"))
        recons = status(server)["scans"][0]["recons"]
        assert [(r["id"], r["kind"], r.get("from_live")) for r in recons] == [
            ("scan-fast", "final", True), ("scan-baseline", "final", None)], "its result first, in its place"
        assert recons[0]["files"]["preview.png"].startswith("/files/scan/recon/scan-fast/preview.png")
        live_status(scan, views_used=64, views_published=64, steps=242, chamfer_mm=3.22, state="done",
                    result=str(scan / "recon" / "scan-moved-away"))
        (live,) = [r for r in status(server)["scans"][0]["recons"] if r["kind"] == "live"]
        assert live["summary"]["chamfer_mm"] == 3.22 and live["summary"]["state"] == "done"
        assert not {"preview.png", "mesh.ply", "view3d.html"} & set(live["files"]), \
            "the result's figures over the live fit's picture: no picture"


def test_a_live_reconstruction_says_its_state_note_and_age(tmp_path):
    now = _dt.datetime(2026, 12, 3, 17, 30, tzinfo=_dt.timezone.utc)
    complete_scan(tmp_path / "v", 2)
    live_status(tmp_path / "v", state="aborted", note="scan aborted: aborted by user",
                updated_utc="2026-12-03T17:27:00.000+00:00")
    (live,) = ResultIndex(tmp_path).for_scan("v", now=now)
    assert (live["summary"]["state"], live["summary"]["note"], live["age_s"]) == (
        "aborted", "scan aborted: aborted by user", 180.0)
    live_status(tmp_path / "v", state="live", updated_utc="not a time")
    assert ResultIndex(tmp_path).for_scan("v", now=now)[0]["age_s"] is None


def test_frame_rates_are_a_running_scans_only(tmp_path):
    writer, poses = start_scan(tmp_path / "s", 4)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    with serving(tmp_path) as server:
        assert status(server)["current"]["frames_per_s"] == 2.0
        writer.finish("aborted", "aborted by user")
        current = status(server)["current"]
        assert current["state"] == "aborted" and "frames_per_s" not in current and "poses_per_min" not in current
    writer, poses = start_scan(tmp_path / "t", 2)
    for i in range(2):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    writer.finish()
    with serving(tmp_path) as server:
        current = status(server)["current"]
        assert current["state"] == "complete" and "frames_per_s" not in current


def ipv6_loopback_problem() -> str | None:
    """None when this machine can listen on IPv6's loopback (::1); else why not (IPv6 turned off, in the kernel or in
    a container), in words."""
    if not socket.has_ipv6:
        return "this Python was built without IPv6"
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as probe:
            probe.bind(("::1", 0))
    except OSError as exc:
        return f"IPv6 is off here: cannot listen on ::1 ({exc.strerror or exc})"
    return None


def test_the_server_listens_on_an_ipv6_address(tmp_path):
    problem = ipv6_loopback_problem()
    if problem is not None:
        pytest.skip(problem)
    complete_scan(tmp_path / "scan", 1)
    server = make_server(tmp_path, "::1", 0)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        assert address(server) == f"http://[::1]:{server.server_address[1]}/"
        conn = http.client.HTTPConnection("::1", server.server_address[1], timeout=30)
        conn.request("GET", "/api/status")
        answer = conn.getresponse()
        assert answer.status == 200 and json.loads(answer.read())["scans"][0]["name"] == "scan"
        conn.close()
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)
    with serving(tmp_path) as server:  # and IPv4 as before
        assert get(server, "/api/status")[0] == 200


def test_a_live_status_rewritten_alone_leaves_the_pictures_addresses_as_they_were(tmp_path):
    # The live job rewrites status.json every couple of seconds between two meshes: the page reloads a picture or
    # the 3D view when its address changes, so each address is versioned by its own file, not by the status.
    complete_scan(tmp_path / "v", 2)
    live_status(tmp_path / "v", state="live")
    index = ResultIndex(tmp_path)
    (before,) = index.for_scan("v")
    status_file = tmp_path / "v" / "recon" / "live" / "status.json"
    later = status_file.stat().st_mtime + 3
    status_file.write_text(json.dumps({"views_used": 20, "views_published": 21, "steps": 90, "state": "live"}))
    os.utime(status_file, (later, later))
    (after,) = index.for_scan("v")
    assert after["summary"]["views_used"] == 20, "the status itself is read again"
    assert {p: after["files"][p] for p in ("preview.png", "mesh.ply", "view3d.html")} == \
        {p: before["files"][p] for p in ("preview.png", "mesh.ply", "view3d.html")}
    mesh = tmp_path / "v" / "recon" / "live" / "mesh.ply"
    os.utime(mesh, (later + 1, later + 1))  # a new mesh: its addresses change, the preview's not
    os.utime(status_file, (later + 2, later + 2))
    (newer,) = index.for_scan("v")
    assert newer["files"]["mesh.ply"] != before["files"]["mesh.ply"]
    assert newer["files"]["view3d.html"] != before["files"]["view3d.html"]
    assert newer["files"]["preview.png"] == before["files"]["preview.png"]


def test_the_pace_of_a_resumed_scan_counts_from_its_resumption():
    # two frames a pose, a pose every 2 s; then a stop of a minute (a pause, a daemon restarted); then three poses at
    # the old pace: across the stop the rate read a tenth of the true one, and the time left ten times too long
    from spadscan.dashboard.scans import frame_rates

    def frames(poses, start_s, first_pose):
        return [{"pose_index": first_pose + p, "t_end": start_s + 2.0 * p + 0.5 * f} for p in range(poses)
                for f in range(2)]

    steady = frames(5, 0.0, 0)
    resumed = steady + frames(3, 8.0 + 60.0, 5)
    assert frame_rates(resumed[-16:]) == frame_rates(frames(3, 68.0, 5))
    assert frame_rates(resumed[-16:])["poses_per_min"] == 60.0 * 2 / 4.5  # its three poses over 4.5 s
    assert frame_rates(steady)["poses_per_min"] == 60.0 * 4 / 8.5, "no stop: the whole window counts"


def test_a_results_summary_carries_every_figure_of_its_report(tmp_path):
    """The API's summary of a result holds the figures a researcher compares, the normal error among them."""
    scan = tmp_path / "scan"
    complete_scan(scan, 2)
    add_final_recon(scan, "scan-fast")
    figures = {"chamfer_mm": 1.2, "accuracy_mm": 1.1, "completeness_mm": 1.3, "fscore_5mm": 0.97,
               "normal_error_deg": 11.5}
    (scan / "recon" / "scan-fast" / "report.json").write_text(json.dumps({"preset": "fast", **figures}))
    (result,) = ResultIndex(tmp_path).for_scan("scan")
    assert {k: result["summary"].get(k) for k in figures} == figures
