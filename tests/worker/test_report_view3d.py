"""Every report gets a 3D view to turn (view3d.html beside report.html): the reconstruction, the ground truth and the
sensor poses as layers, in a page that opens from disk and fetches nothing."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
import trimesh

from page_helpers import add_pose, browser_page, drawn_share, screenshot_pixels, start_scan
from spadscan.worker.report.report_html import REPORT_HTML, write_report_html
from spadscan.worker.report.view3d import VIEW3D

LOAD_TIMEOUT_MS = 60_000  # software WebGL on a busy 2-core machine


@pytest.fixture
def result_folder(tmp_path, draws_off_screen):
    """A results folder as a reconstruction leaves it: mesh.ply, ground_truth.ply, report.json naming both, and the
    capture (8 poses) it came from. Its 3D view is drawn off screen: where that cannot be, the test skips."""
    capture = tmp_path / "scan"
    writer, poses = start_scan(capture, 8)
    for i in range(8):
        add_pose(writer, poses, i)
    writer.finish()
    out = tmp_path / "recon"
    out.mkdir()
    trimesh.creation.icosphere(subdivisions=3, radius=0.06).apply_translation((0, 0, 0.08)).export(out / "mesh.ply")
    trimesh.creation.box((0.1, 0.1, 0.1)).export(out / "ground_truth.ply")
    report = {"capture": str(capture), "preset": "fast", "steps": 10, "chamfer_mm": 3.0,
              "ground_truth": "/elsewhere/.tmp-job/ground_truth.ply"}  # written before its folder was renamed
    (out / "report.json").write_text(json.dumps(report))
    return out, report


def test_the_report_page_shows_its_3d_view_with_every_layer(result_folder):
    out, report = result_folder
    write_report_html(report, out)
    page = (out / REPORT_HTML).read_text()
    assert f'<iframe class=view3d src="{VIEW3D}"' in page
    view = (out / VIEW3D).read_text()
    for layer in ("reconstruction", "ground truth", "sensor poses"):
        assert f"> {layer}</label>" in view
    assert "OfflineLocalView.load" in view and "base64Str" in view  # the scene travels inside the page


def test_a_built_in_ground_truth_is_a_layer_too(result_folder):
    """Every capture simulated from a built-in scene names `builtin:NAME` as its ground truth, which is no file: its
    view had no ground-truth layer although the run was scored against it."""
    out, report = result_folder
    (out / "ground_truth.ply").unlink()
    write_report_html({**report, "ground_truth": "builtin:sphere"}, out)
    assert "> ground truth</label>" in (out / VIEW3D).read_text()


def test_a_view_newer_than_its_mesh_is_kept_and_an_older_one_made_again(result_folder):
    out, report = result_folder
    write_report_html(report, out)
    view = out / VIEW3D
    view.write_text("kept")
    write_report_html(report, out)  # adding a note to a finished report does not redo its view
    assert view.read_text() == "kept"
    later = time.time() + 5
    os.utime(out / "mesh.ply", (later, later))
    write_report_html(report, out)
    assert "OfflineLocalView" in view.read_text()


def test_a_folder_without_a_mesh_has_no_3d_view(tmp_path):
    write_report_html({"preset": "fast"}, tmp_path)
    assert not (tmp_path / VIEW3D).exists()
    assert "3D view" not in (tmp_path / REPORT_HTML).read_text()


def _scene_loaded(frame) -> None:
    frame.locator("body[data-scene-loaded]").wait_for(state="attached", timeout=LOAD_TIMEOUT_MS)
    assert frame.locator("body").get_attribute("data-scene-loaded") == "yes"


def _scene_pixels(page, element) -> np.ndarray:
    """The 3D view's pixels, less the layer panel in its top-left corner and the frame's border."""
    page.wait_for_timeout(300)  # the next animation frame after a change
    pixels = screenshot_pixels(element)
    return pixels[pixels.shape[0] // 4:-3, pixels.shape[1] // 3:-3]


def test_the_3d_view_draws_offline_and_its_layers_hide(result_folder):
    out, report = result_folder
    write_report_html(report, out)
    with browser_page() as (page, seen):
        page.goto((out / REPORT_HTML).as_uri())
        iframe = page.locator("iframe.view3d")
        iframe.scroll_into_view_if_needed()
        frame = page.frame_locator("iframe.view3d")
        _scene_loaded(frame)
        everything = _scene_pixels(page, iframe)
        assert drawn_share(everything) > 0.01  # the canvas is not blank
        frame.locator("input[data-layer='1']").uncheck()  # ground truth off
        without_gt = _scene_pixels(page, iframe)
        assert np.abs(without_gt.astype(int) - everything.astype(int)).max(axis=2).mean() > 0.5
        for layer in ("0", "2"):
            frame.locator(f"input[data-layer='{layer}']").uncheck()
        assert drawn_share(_scene_pixels(page, iframe)) < 0.002  # every layer hidden: nothing left
        page.goto((out / VIEW3D).as_uri())  # the view on its own page, as the report's link opens it
        _scene_loaded(page)
        page.wait_for_timeout(500)  # a page asks for its icons once it has loaded
    assert not seen.errors, seen.errors
    folder = out.as_uri() + "/"
    assert seen.requests and all(url.startswith(folder) for url in seen.requests), seen.requests
