"""The dashboard on a machine that cannot draw off screen (no display, no EGL, no OSMesa): the live 3D view is served
and drawn all the same (the browser draws it with WebGL; the server only describes the scene), and a result's mesh
without a preview says why it has none, in one line, with what to install in its title. The machine is simulated by
the means the product's own check asks (offscreen.check_offscreen: the environment and ctypes.util.find_library), so
that these run on a machine that has an off-screen OpenGL too; the live view is the report's own 3D view page.

The worker draws a preview on its own machine, which need not be the dashboard's: a result whose report says why it has
no preview says that, whatever the dashboard's machine can do; the dashboard's machine's own reason, said as its, is
only for a result that does not say."""

from __future__ import annotations

import base64
import io
import json
import zipfile

import numpy as np
import pytest
import pyvista as pv
import trimesh

from dashboard_helpers import (complete_scan, get, keep_opengl_window, preview_png, serving,
                               skip_where_no_off_screen_drawing, status, without_off_screen_opengl)
from page_helpers import browser_page, drawn_share, screenshot_pixels
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, and a live view made on demand, on a busy machine
SCENE_LOADED = """() => { const f = document.getElementById('viewer-3d'); const body = f.contentDocument &&
    f.contentDocument.body; return !f.hidden && body && body.dataset.sceneLoaded === 'yes'; }"""


# how many lines the text of an element takes, as laid out (the tops of its text's pieces)
LINES = """(s) => { const walker = document.createTreeWalker(document.querySelector(s), NodeFilter.SHOW_TEXT);
    const tops = new Set();
    while (walker.nextNode()) { const range = document.createRange(); range.selectNodeContents(walker.currentNode);
      for (const r of range.getClientRects()) if (r.width > 0) tops.add(Math.round(r.top)); }
    return tops.size; }"""


def live_mesh(scan, preview: bool = False) -> None:
    """A live job's first fit of `scan`: its mesh and status, and its preview only where the worker could draw it."""
    live = scan / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(live / "mesh.ply")
    if preview:
        (live / "preview.png").write_bytes(preview_png())
    (live / "status.json").write_text(json.dumps({"views_used": 2, "views_published": 2, "steps": 20,
                                                  "state": "live"}))


def test_the_live_3d_view_is_served_and_drawn_where_nothing_can_draw_off_screen(tmp_path, monkeypatch):
    from spadscan.worker.report.offscreen import OffscreenUnavailable, check_offscreen

    without_off_screen_opengl(monkeypatch)
    with pytest.raises(OffscreenUnavailable):
        check_offscreen()  # the product sees no off-screen OpenGL here
    complete_scan(tmp_path / "bowl", 2)
    live_mesh(tmp_path / "bowl")
    with serving(tmp_path) as server:
        answer = status(server)
        assert "EGL" in answer["cannot_draw"]
        (recon,) = answer["scans"][0]["recons"]
        code, body = get(server, recon["files"]["view3d.html"])
        assert code == 200 and b"OfflineLocalView.load" in body and b"bowl (live)" in body, body[:300]
        with browser_page() as (page, seen):
            page.goto(address(server))
            page.wait_for_function(SCENE_LOADED, timeout=WAIT_MS)
            page.wait_for_timeout(300)  # the first frame drawn after the scene loaded
            assert drawn_share(screenshot_pixels(page.locator("#viewer-3d"))[10:-3, 10:-3]) > 0.01
            # the picture the worker could not draw: said why, in a line or two of the box, and what to install in its
            # title
            none = page.locator("#preview-none")
            assert none.is_visible() and none.text_content() == DASHBOARD_CANNOT_DRAW
            assert none.get_attribute("title").startswith("this dashboard's machine: no display and no EGL")
            assert "apt-get install" in none.get_attribute("title")
            assert page.evaluate(LINES, "#preview-none") <= 2
    assert not seen.errors, seen.errors


DASHBOARD_CANNOT_DRAW = "no preview: this dashboard's machine cannot draw off screen"
WORKER_CANNOT_DRAW = "no preview: the worker's machine could not draw off screen"
# the warning an earlier version's report gave where its machine could not draw off screen (its 3D view needed an
# off-screen OpenGL then): such results are still on disk and still say why they have no preview
NO_VIEW = ("no 3D view: view3d.html could not be written (no display and no EGL or OSMesa library to draw meshes off "
           "screen: install an off-screen OpenGL: on Debian/Ubuntu `apt-get install libegl1 libegl-mesa0` (EGL) or "
           "`apt-get install libosmesa6` (OSMesa))")


def final_mesh(scan, warnings: list[str]) -> None:
    """A finished result of `scan`, made by a worker (on whatever machine): its report with `warnings`, and its mesh
    without a preview."""
    final = scan / "recon" / f"{scan.name}-fast"
    final.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(final / "mesh.ply")
    (final / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 2.0, "warnings": warnings}))


def preview_said(tmp_path, warnings: list[str]) -> tuple[str, str]:
    """What the preview's box says (its text and title) of a finished result with a mesh, no preview and a report
    with `warnings`, once it is in view."""
    complete_scan(tmp_path / "bowl", 2)
    final_mesh(tmp_path / "bowl", warnings)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.getElementById('viewer-name').textContent.startsWith('bowl / fast')",
                               timeout=WAIT_MS)
        none = page.locator("#preview-none")
        said = (none.text_content(), none.get_attribute("title") or "")
        assert none.is_visible() and page.evaluate(LINES, "#preview-none") <= 2
    assert not seen.errors, seen.errors
    return said


def worker_preview_warning(tmp_path) -> str:
    """The warning a worker's report gives where its machine could not draw the preview: made by the worker's own
    code (mesh_pictures.preview_or_warning, as reconstruct.py calls it) on a machine without off-screen OpenGL."""
    from spadscan.worker.report.pictures import preview_or_warning

    with pytest.MonkeyPatch.context() as worker_machine:
        without_off_screen_opengl(worker_machine)
        line = preview_or_warning(trimesh.creation.icosphere(), tmp_path / "preview.png")
    assert line is not None and not (tmp_path / "preview.png").exists()
    return line


@pytest.mark.parametrize("said_by", ["3D view", "preview"])
@pytest.mark.parametrize("dashboard_draws", [True, False])
def test_a_result_whose_worker_could_not_draw_says_so_whatever_the_dashboards_machine_can(tmp_path, monkeypatch,
                                                                                          dashboard_draws, said_by):
    warning = NO_VIEW if said_by == "3D view" else worker_preview_warning(tmp_path)
    if dashboard_draws:
        keep_opengl_window(monkeypatch)
        monkeypatch.setenv("DISPLAY", ":99")  # the product's check: a display draws
    else:
        without_off_screen_opengl(monkeypatch)
    assert preview_said(tmp_path, ["the run stopped on its budget", warning]) == (WORKER_CANNOT_DRAW, warning)


def test_a_results_own_reason_for_no_preview_is_said_not_the_dashboards_machines(tmp_path, monkeypatch):
    from spadscan.worker.report.mesh_pictures import no_preview_warning

    without_off_screen_opengl(monkeypatch)
    own = no_preview_warning(OSError(28, "No space left on device"))  # the worker's own line for a full disk
    assert preview_said(tmp_path, [own]) == (own, own)


def test_a_result_that_says_nothing_of_its_preview_gets_the_dashboards_machines_reason_as_its(tmp_path, monkeypatch):
    without_off_screen_opengl(monkeypatch)
    said, title = preview_said(tmp_path, ["the run stopped on its budget"])
    assert said == DASHBOARD_CANNOT_DRAW and title.startswith("this dashboard's machine: no display and no EGL")


def test_where_pictures_can_be_drawn_a_missing_preview_is_just_missing(tmp_path, monkeypatch):
    skip_where_no_off_screen_drawing(monkeypatch)
    complete_scan(tmp_path / "bowl", 2)
    live_mesh(tmp_path / "bowl")
    with serving(tmp_path) as server, browser_page() as (page, seen):
        assert status(server)["cannot_draw"] is None
        page.goto(address(server))
        page.wait_for_function(SCENE_LOADED, timeout=WAIT_MS)
        assert page.locator("#preview-none").text_content() == "no preview"
        assert not page.locator("#preview-none").get_attribute("title")
        live_mesh(tmp_path / "bowl", preview=True)
        page.locator("#viewer-preview:not([hidden])").wait_for(timeout=WAIT_MS)
    assert not seen.errors, seen.errors


def scene_of(page: bytes) -> dict:
    """The scene a 3D view page embeds (the viewer's base64 zip), as {type: [properties of each object]}."""
    start = page.index(b'base64Str: "') + len(b'base64Str: "')
    data = base64.b64decode(page[start:page.index(b'"', start)])
    scene = json.loads(zipfile.ZipFile(io.BytesIO(data)).read("index.json"))["scene"]
    found: dict = {}

    def walk(node):
        found.setdefault(node.get("type"), []).append(node.get("properties", {}))
        for child in node.get("dependencies", []):
            walk(child)

    walk(scene)
    return found


def test_the_reports_3d_view_with_every_layer_is_built_where_nothing_can_draw_off_screen(monkeypatch):
    """The report's 3D view (the dashboard's live view is the same page) is only described by the server: it is built
    without an off-screen OpenGL, its three layers coloured and lit as the pictures are. Before, it was built in an
    off-screen plotter: a worker or a dashboard without EGL wrote or served none."""
    from spadscan.worker.report import offscreen
    from spadscan.worker.report.view3d import AZIMUTH_DEG, ELEVATION_DEG, view3d_html

    without_off_screen_opengl(monkeypatch)
    with pytest.raises(offscreen.OffscreenUnavailable):
        offscreen.check_offscreen()
    mesh = trimesh.creation.box(extents=(0.1, 0.06, 0.2))
    gt = trimesh.creation.icosphere(radius=0.08)
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3], poses[:, 2, 3] = (-0.3, 0.0, 0.3), 0.4
    page = view3d_html(mesh, gt, poses, title="t")
    assert all(f"> {label}</label>" in page for label in ("reconstruction", "ground truth", "sensor poses"))
    scene = scene_of(page.encode())
    looks = scene["vtkOpenGLProperty"]
    colours = [offscreen.MESH_COLOUR, offscreen.GT_COLOUR, offscreen.POSE_COLOUR]
    assert [look["diffuseColor"] for look in looks] == [pytest.approx(pv.Color(c).float_rgb) for c in colours]
    assert [look["opacity"] for look in looks] == pytest.approx([1.0, 0.45, 1.0])
    assert [look["interpolation"] for look in looks] == [2, 2, 0], "phong, phong, flat"
    assert len(scene["vtkOpenGLLight"]) >= 3, "a light kit, as the pictures have"
    assert scene["vtkOpenGLRenderer"][0]["background"] == pytest.approx(pv.Color(offscreen.BACKGROUND).float_rgb)
    center, half = offscreen.frame([mesh, gt])
    eye = offscreen.orbit_camera(center, half, AZIMUTH_DEG, ELEVATION_DEG)[0]
    (camera,) = scene["vtkOpenGLCamera"]
    direction = np.subtract(camera["position"], camera["focalPoint"])
    assert direction / np.linalg.norm(direction) == pytest.approx((eye - center) / np.linalg.norm(eye - center))
