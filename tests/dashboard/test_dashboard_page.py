"""The dashboard page in a real headless browser: it follows a scan as its poses are published, shows a finished
reconstruction's 3D view, and asks nothing of any server but its own."""

from __future__ import annotations

import trimesh

from dashboard_helpers import complete_scan, serving
from page_helpers import add_pose, browser_page, drawn_share, screenshot_pixels, start_scan
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine


def test_the_page_follows_a_scan_as_it_runs(tmp_path):
    from spadscan.worker.report.view3d import write_view3d

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
