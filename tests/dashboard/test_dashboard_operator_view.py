"""What an operator sees stay put or said once on the dashboard: the live 3D view keeps the camera they turned it to
when the live mesh changes, a result's warnings are printed in full once, and a daemon that is down says so."""

from __future__ import annotations

import json
import os
from contextlib import contextmanager

import trimesh

from dashboard_helpers import complete_scan, serving
from page_helpers import browser_page
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, and a live view made on demand, on a busy machine
FRAME = "document.getElementById('viewer-3d')"


def _live_fit(scan, subdivisions: int, views: int) -> None:
    """Publish a live fit of `scan` as the live job does: its mesh, then its status (whose time names the view)."""
    live = scan / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.05).export(live / "mesh.ply")
    status = live / "status.json"
    status.write_text(json.dumps({"views_used": views, "views_published": views, "steps": 10 * views,
                                  "state": "live"}))
    if views > 1:  # a later publish always has a later time, however coarse the file system's clock
        later = status.stat().st_mtime + views
        os.utime(status, (later, later))


def _wait_for_scene(page, not_src: str = "") -> str:
    """The frame's address once a view other than `not_src` has loaded its scene in it (the document in the frame
    is the one its address names: the old one stays there, loaded, until the new one replaces it)."""
    page.wait_for_function(
        f"""() => {{ const f = {FRAME}; const body = f.contentDocument && f.contentDocument.body;
                    return !f.hidden && f.src && f.src !== {json.dumps(not_src)} &&
                           f.contentWindow.location.href === f.src && body &&
                           body.dataset.sceneLoaded === 'yes'; }}""", timeout=WAIT_MS)
    return page.evaluate(f"() => {FRAME}.src")


@contextmanager
def _live_bowl_in_view(root):
    """A live job's first fit of a scan `bowl` under `root`, its 3D view loaded in the dashboard: yields (the scan's
    folder, the page, what the browser saw, the view's address)."""
    scan = root / "bowl"
    complete_scan(scan, 2)
    _live_fit(scan, 1, 1)
    with serving(root) as server, browser_page() as (page, seen):
        page.goto(address(server))
        yield scan, page, seen, _wait_for_scene(page)


def _press_in_view(page) -> tuple[float, float]:
    """Press the mouse button down inside the 3D view, as an operator starting to turn it; returns where."""
    box = page.locator("#viewer-3d").bounding_box()
    x, y = box["x"] + box["width"] * 0.6, box["y"] + box["height"] * 0.6
    page.mouse.move(x, y)
    page.mouse.down()
    return x, y


def test_the_live_3d_view_keeps_the_operators_camera_when_the_live_mesh_changes(tmp_path):
    with _live_bowl_in_view(tmp_path) as (scan, page, seen, first):
        assert page.evaluate(f"() => {FRAME}.contentWindow.spadscanCamera()") is None  # the scene's own camera
        x, y = _press_in_view(page)
        page.mouse.move(x + 90, y + 40, steps=8)  # the operator turns the shape
        page.mouse.up()
        turned = page.evaluate(f"() => {FRAME}.contentWindow.spadscanCamera()")
        assert turned is not None, "the drag did not turn the view"
        _live_fit(scan, 2, 20)  # the live fit moves on: a new mesh, a new view
        second = _wait_for_scene(page, not_src=first)
        assert second.split("#")[0] != first.split("#")[0]
        kept = page.evaluate(f"() => {FRAME}.contentWindow.spadscanCamera()")
        assert kept is not None, "the new view starts from its own camera: the operator's turn is lost"
        for key in ("position", "focalPoint", "viewUp"):
            assert kept[key] == turned[key] or max(abs(a - b) for a, b in zip(kept[key], turned[key])) < 1e-9, key
    assert not seen.errors, seen.errors


def test_a_live_update_during_a_drag_waits_for_its_end(tmp_path):
    with _live_bowl_in_view(tmp_path) as (scan, page, seen, first):
        x, y = _press_in_view(page)
        page.mouse.move(x + 60, y + 20, steps=6)  # the operator is turning the shape
        _live_fit(scan, 2, 20)  # and the live fit moves on meanwhile
        link = "() => [...document.querySelectorAll('#viewer-links a')].find(a => a.textContent === 'view3d.html')"
        page.wait_for_function(f"([first]) => {{ const a = ({link})(); return a && "
                               "a.getAttribute('href') !== new URL(first).pathname + new URL(first).search; }",
                               arg=[first.split("#")[0]], timeout=WAIT_MS)  # the page has seen the new view
        assert page.evaluate(f"() => {FRAME}.src") == first, "the view was reloaded under the operator's drag"
        page.mouse.move(x + 90, y + 40, steps=4)  # the drag goes on, uninterrupted
        turned = page.evaluate(f"() => {FRAME}.contentWindow.spadscanCamera()")
        assert turned is not None, "the drag did not turn the view"
        page.mouse.up()
        _wait_for_scene(page, not_src=first)  # once the drag ends, the new view comes, with the operator's camera
        kept = page.evaluate(f"() => {FRAME}.contentWindow.spadscanCamera()")
        assert kept is not None
        for key in ("position", "focalPoint", "viewUp"):
            assert max(abs(a - b) for a, b in zip(kept[key], turned[key])) < 1e-9, key
    assert not seen.errors, seen.errors


def _done_job_with_warnings(root, scan: str, warnings: list[str]) -> None:
    """A done job of `scan` whose result, `<scan>/recon/<scan>-fast`, gives `warnings`."""
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    complete_scan(root / scan, 2)
    result = root / scan / "recon" / f"{scan}-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 2.5, "warnings": warnings}))
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=f"{scan}-fast", scan=scan))
    queue.finish(queue.claim(), result=str(result))


def test_a_results_warnings_are_printed_once_and_counted_where_else_it_is_listed(tmp_path):
    warnings = {"mug": ["the mesh is in 8 pieces", "stopped on its budget at 3% of its steps", "few views of the top"],
                "vase": ["the vase's own warning"]}
    for scan, said in warnings.items():
        _done_job_with_warnings(tmp_path, scan, said)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.locator('#queue tr[data-job="vase-fast"]').wait_for(timeout=WAIT_MS)
        for scan, said in (("mug", "3 warnings"), ("vase", "1 warning")):  # the scans row and the queue row count
            assert page.locator(f'#scans tr[data-scan="{scan}"] a[data-warnings]').all_text_contents() == [said]
            assert page.locator(f'#queue tr[data-job="{scan}-fast"] a[data-warnings]').all_text_contents() == [said]
        for shown in ("mug", "vase"):
            page.locator(f'#queue tr[data-job="{shown}-fast"] a[data-warnings]').click()  # the count leads to them
            page.wait_for_function(
                f"() => document.querySelector('#viewer-name').textContent.startsWith('{shown} / fast')",
                timeout=WAIT_MS)
            text = page.locator("body").inner_text()
            for scan, said in warnings.items():  # in full once, in the panel, for the result in view only
                for w in said:
                    assert text.count(w) == (scan == shown), (w, text)
            assert page.locator("#viewer-notes .warning").all_text_contents() == warnings[shown]
    assert not seen.errors, seen.errors


def test_an_idle_rig_whose_daemon_is_down_says_so_at_the_top(tmp_path):
    from spadscan.commands.dashboard import daemon_running
    from spadscan.daemon.root_lock import RootLock

    complete_scan(tmp_path / "mug", 2)  # idle: no scan in hand to show the daemon's absence
    said = "() => document.querySelector('#daemon').textContent"
    lock = RootLock(tmp_path)
    with serving(tmp_path, daemon_running=daemon_running) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function(f"{said}.includes('no daemon running')", timeout=WAIT_MS)
        assert page.locator("#daemon").text_content() == \
            " · no daemon running: start one with `spadscan daemon --config rig.toml`"
        assert page.locator("#daemon").get_attribute("class") == "down"
        assert page.locator("#daemon").evaluate("e => getComputedStyle(e).color") == "rgb(187, 0, 0)"
        with lock:  # a daemon starts on the root
            page.wait_for_function(f"{said} === ' · daemon: idle'", timeout=WAIT_MS)  # its own word, no scan held
            assert page.locator("#daemon").get_attribute("class") == ""
        page.wait_for_function(f"{said}.includes('no daemon running')", timeout=WAIT_MS)  # and stops
    assert not seen.errors, seen.errors


def test_a_dashboard_that_cannot_tell_says_nothing_of_the_daemon(tmp_path):
    complete_scan(tmp_path / "mug", 2)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#link').textContent.startsWith('updated')",
                               timeout=WAIT_MS)
        assert page.locator("#daemon").text_content() == ""
    assert not seen.errors, seen.errors
