"""The dashboard page in a real headless browser: it follows a scan as its poses are published, shows a finished
reconstruction's 3D view, opens the links of any scan name, shows the queue as `spadscan worker --status` does, shows
a scan whose daemon is gone as interrupted, outlives damaged numbers, and asks nothing of any server but its own;
once a live reconstruction is done it shows its result, a live one its state, note and age, and a finished scan as the
last one, without a frame rate."""

from __future__ import annotations

import datetime as _dt
import json

import trimesh

from dashboard_helpers import (add_final_recon, complete_scan, queue_with_a_kept_result_and_a_damaged_record,
                               scan_with_non_finite_results, serving, skip_where_no_off_screen_drawing)
from page_helpers import add_pose, browser_page, drawn_share, screenshot_pixels, start_scan
from spadscan.commands.dashboard import daemon_running
from spadscan.daemon.root_lock import RootLock
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine


def test_the_page_follows_a_scan_as_it_runs(tmp_path, monkeypatch):
    from spadscan.worker.report.view3d import write_view3d

    skip_where_no_off_screen_drawing(monkeypatch)  # the result's 3D view is the worker's own, made in a plotter
    complete_scan(tmp_path / "earlier", 2)
    final = tmp_path / "earlier" / "recon" / "earlier-fast"
    final.mkdir(parents=True)
    (final / "report.json").write_text('{"preset": "fast", "chamfer_mm": 2.5}')
    write_view3d(final, trimesh.creation.icosphere(subdivisions=3, radius=0.05))
    writer, poses = start_scan(tmp_path / "now", 6)
    add_pose(writer, poses, 0)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        poses_text = page.locator("#current-poses")
        page.wait_for_function("() => document.querySelector('#current-poses').textContent.startsWith('1 / 6')",
                               timeout=WAIT_MS)
        for i in range(1, 6):  # the page moves on with every pose the scan publishes, without a reload
            add_pose(writer, poses, i)
            page.wait_for_function(
                f"() => document.querySelector('#current-poses').textContent.startsWith('{i + 1} / 6')",
                timeout=WAIT_MS)
        assert poses_text.text_content().startswith("6 / 6")
        assert page.locator("#hist polyline").count() == 9  # the last frame's nine zones
        assert page.locator("#scans tbody tr").count() == 2
        page.locator('#scans tr[data-scan="earlier"] a.pick').click()  # the scan in hand has no result: pick one
        frame = page.frame_locator("#viewer-3d")
        frame.locator("body[data-scene-loaded='yes']").wait_for(state="attached", timeout=WAIT_MS)
        page.wait_for_timeout(300)
        assert drawn_share(screenshot_pixels(page.locator("#viewer-3d"))[10:-3, 10:-3]) > 0.01
        writer.finish()
        page.wait_for_function(
            "() => document.querySelector('#current-state').textContent.startsWith('complete')", timeout=WAIT_MS)
    assert not seen.errors, seen.errors
    assert seen.requests and all(url.startswith(address(server)) for url in seen.requests), \
        [u for u in seen.requests if not u.startswith(address(server))]


def test_the_links_of_a_scan_named_with_hash_and_percent_open_and_a_linked_out_scan_has_none(tmp_path):
    from spadscan.dashboard.scans import LINKED_OUT

    root, name = tmp_path / "captures", "cup #2 100%"  # '#' starts a fragment, '%' an escape
    complete_scan(root / name, 2)
    add_final_recon(root / name)
    complete_scan(tmp_path / "otherdisk" / "elsewhere", 2)
    add_final_recon(tmp_path / "otherdisk" / "elsewhere")
    (root / "elsewhere").symlink_to(tmp_path / "otherdisk" / "elsewhere")
    with serving(root) as server, browser_page() as (page, seen):
        page.goto(address(server))
        row = page.locator(f'#scans tr[data-scan="{name}"]')
        report = row.locator("a[target=_blank]", has_text="report")
        report.wait_for(timeout=WAIT_MS)
        with page.context.expect_event("response", lambda r: "report.html" in r.url, timeout=WAIT_MS) as answer, \
                page.expect_popup(timeout=WAIT_MS) as opened:
            report.click()
        assert answer.value.status == 200
        assert opened.value.locator("p").text_content() == f"report of {name}"
        row.locator("a.pick").click()  # the viewer shows its preview
        page.wait_for_function("() => { const img = document.querySelector('#viewer-preview');"
                               " return !img.hidden && img.complete && img.naturalWidth === 4; }", timeout=WAIT_MS)
        linked = page.locator('#scans tr[data-scan="elsewhere"]')
        assert linked.locator(".note").text_content() == LINKED_OUT
        assert linked.locator("a[target=_blank]").count() == 0  # its files would answer 404
    assert not seen.errors, seen.errors


def test_the_queue_table_shows_kept_results_and_damaged_files_as_worker_status_does(tmp_path):
    said = queue_with_a_kept_result_and_a_damaged_record(tmp_path)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        for job_id, detail in said.items():
            cell = page.locator(f'#queue tr[data-job="{job_id}"] td').last
            cell.wait_for(timeout=WAIT_MS)
            assert cell.text_content() == detail
    assert not seen.errors, seen.errors


def test_a_scan_whose_daemon_went_shows_as_interrupted_and_comes_back_when_a_daemon_holds_the_root(tmp_path):
    writer, poses = start_scan(tmp_path / "s1", 8)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    lock = RootLock(tmp_path)
    lock.acquire()  # the daemon writing s1
    try:
        with serving(tmp_path, daemon_running=daemon_running) as server, browser_page() as (page, seen):
            page.goto(address(server))
            page.wait_for_function("() => document.querySelector('#current-rate').textContent === '2.00 frames/s'",
                                   timeout=WAIT_MS)
            assert page.locator("#current-state").text_content() == "scanning"  # as the daemon says it
            lock.release()  # the daemon died: the kernel dropped its lock
            page.wait_for_function(
                "() => document.querySelector('#current-state').textContent === 'interrupted (no daemon running)'",
                timeout=WAIT_MS)
            assert page.locator("#current-name").text_content() == "s1"
            assert page.locator("#current-rate").text_content() == page.locator("#current-ppm").text_content() == "-"
            assert page.locator("#current-state").get_attribute("class") == "state-interrupted"
            state_cell = page.locator('#scans tr[data-scan="s1"] td').nth(1)
            assert state_cell.text_content() == "interrupted"
            assert state_cell.get_attribute("class") == "state-interrupted"
            assert state_cell.evaluate("td => getComputedStyle(td).color") == "rgb(187, 0, 0)"  # as errors are
            lock.acquire()  # a daemon started on the root takes the scan over
            page.wait_for_function("() => document.querySelector('#current-state').textContent === 'scanning'",
                                   timeout=WAIT_MS)
    finally:
        lock.release()
    assert not seen.errors, seen.errors


def test_the_page_keeps_updating_with_non_finite_numbers_in_a_report_and_a_live_status(tmp_path):
    scan_with_non_finite_results(tmp_path / "done", steps=40)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#link').textContent.startsWith('updated')",
                               timeout=WAIT_MS)
        assert page.locator("#link").get_attribute("class") != "down"
        picks = page.locator('#scans tr[data-scan="done"] a.pick')
        assert picks.all_text_contents() == ["live (3 views, 40 steps)", "fast"]  # no Chamfer to show
        complete_scan(tmp_path / "next", 1)  # and it goes on following the root
        page.locator('#scans tr[data-scan="next"]').wait_for(timeout=WAIT_MS)
    assert not seen.errors, seen.errors


def test_once_a_live_reconstruction_is_done_the_page_shows_its_result_picture_and_figures_together(tmp_path):
    scan = tmp_path / "demo"
    complete_scan(scan, 2)
    add_final_recon(scan, "demo-fast")  # its report.json: Chamfer 1.00 mm
    # a live job's result records its live fit (worker/live/job.py)
    (scan / "recon" / "demo-fast" / "report.json").write_text(json.dumps(
        {"preset": "fast", "chamfer_mm": 1.0, "live": {"views_used": 18, "steps": 0}}))
    live = scan / "recon" / "live"
    live.mkdir()
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(live / "mesh.ply")
    (live / "preview.png").write_bytes((scan / "recon" / "demo-fast" / "preview.png").read_bytes())
    status = {"views_used": 18, "views_published": 18, "steps": 0, "chamfer_mm": 119.13, "state": "live",
              "job": "demo-fast"}
    (live / "status.json").write_text(json.dumps(status))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        name = page.locator("#viewer-name")
        page.wait_for_function("() => document.querySelector('#viewer-name').textContent.includes('live')",
                               timeout=WAIT_MS)
        assert name.text_content().endswith("(18 views, 0 steps), the live fit's Chamfer against the ground truth "
                                            "on its 18 views: 119.13 mm")
        assert "/recon/live/preview.png" in page.locator("#viewer-preview").get_attribute("src")
        (live / "status.json").write_text(json.dumps({**status, "views_used": 64, "views_published": 64,
                                                      "steps": 242, "chamfer_mm": 1.0, "state": "done",
                                                      "result": str(scan / "recon" / "demo-fast")}))
        page.wait_for_function("() => document.querySelector('#viewer-name').textContent.includes('1.00 mm')",
                               timeout=WAIT_MS)
        assert "/recon/demo-fast/preview.png" in page.locator("#viewer-preview").get_attribute("src"), \
            "the result's figures over the live fit's picture"
        assert name.text_content() == ("demo / fast, Chamfer to the ground truth 1.00 mm (the live reconstruction's "
                                       "result)")
        assert page.locator('#viewer-links a', has_text="report.html").count() == 1
        assert page.locator('#scans tr[data-scan="demo"] a.pick').all_text_contents() == [
            "fast, Chamfer to the ground truth 1.00 mm (the live reconstruction's result)"]
    assert not seen.errors, seen.errors


def test_a_live_reconstruction_shows_its_state_its_note_and_its_age_once_it_no_longer_updates(tmp_path):
    def live(name, **fields):
        complete_scan(tmp_path / name, 1)
        (tmp_path / name / "recon" / "live").mkdir(parents=True)
        (tmp_path / name / "recon" / "live" / "status.json").write_text(json.dumps(
            {"views_used": 33, "views_published": 62, "steps": 136, "chamfer_mm": 39.1556, **fields}))

    now = _dt.datetime.now(_dt.timezone.utc)
    live("aborted", state="aborted", note="scan aborted: aborted by user",
         updated_utc=(now - _dt.timedelta(minutes=3)).isoformat())
    live("quiet", state="live", updated_utc=(now - _dt.timedelta(seconds=45)).isoformat())
    live("running", state="live", updated_utc=(now + _dt.timedelta(minutes=10)).isoformat())  # fresh all along
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        picks = {name: page.locator(f'#scans tr[data-scan="{name}"] a.pick')
                 for name in ("aborted", "quiet", "running")}
        picks["running"].wait_for(timeout=WAIT_MS)
        fit = "(33 views, 136 steps), the live fit's Chamfer against the ground truth on its 33 views: 39.16 mm"
        assert picks["aborted"].text_content() == f"live, ended (the scan was aborted) {fit}, updated 3 min ago"
        assert page.locator('#scans tr[data-scan="aborted"] .note').text_content() == "scan aborted: aborted by user"
        quiet = picks["quiet"].text_content()  # 45 s ago, or a little more on a busy machine
        behind = fit.replace("(33 views", "(fit of 33 of 62 views")  # the status counts 62 views published
        assert quiet.startswith(f"live, following the scan {behind}, updated ") and \
            quiet.endswith(" ago"), quiet
        assert picks["running"].text_content() == f"live, following the scan {behind}"
        picks["aborted"].click()
        page.wait_for_function("() => document.querySelector('#viewer-notes').textContent"
                               ".includes('scan aborted: aborted by user')", timeout=WAIT_MS)
    assert not seen.errors, seen.errors


def test_a_finished_scan_is_the_last_scan_and_shows_no_frame_rate(tmp_path):
    writer, poses = start_scan(tmp_path / "s", 3)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#current-rate').textContent === '2.00 frames/s'",
                               timeout=WAIT_MS)
        writer.finish()
        page.wait_for_function("() => document.querySelector('#current-state').textContent === 'complete'",
                               timeout=WAIT_MS)
        assert page.locator("#current-rate").text_content() == page.locator("#current-ppm").text_content() == "-"
        assert page.locator("#current-title").text_content() == "Last scan"
    assert not seen.errors, seen.errors
