"""The 3D view you can turn: view3d.html, one page that holds its viewer and its scene and fetches nothing.

The scene (the reconstruction, the ground truth when there is one, the sensor poses as small cones) is built with VTK in
a window that never draws (no display or off-screen OpenGL needed: the browser draws it) and serialised by trame-vtk's
vtk.js serialisers, without a server; trame-vtk's standalone vtk.js viewer (its OfflineLocalView page) shows it: drag to
turn, shift-drag to pan, the wheel to zoom. The scene is embedded in the page, so the report folder can be zipped and
mailed and the page opens from disk with no network. Our part is a small panel that shows or hides each layer, and the
camera handed on when a page replaces the view (below).
"""

from __future__ import annotations

import base64
import html
import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spadscan.protocol.atomic_files import write_atomic

from . import offscreen

VIEW3D = "view3d.html"
CONE_SHARE = 0.05
"""A pose cone's length as a share of the sensors' median distance from the object (2.5 cm at 0.5 m), for up to
CONE_FULL_SIZE poses; more poses get smaller cones (by the square root of their number) so as not to hide the object."""
CONE_FULL_SIZE = 64
CONE_HALF_ANGLE_DEG = 15.0


@dataclass(frozen=True)
class Layer:
    """One thing the panel shows or hides: its label and whether it starts visible."""

    label: str
    visible: bool = True


def pose_cones(poses: np.ndarray, center: np.ndarray) -> object:
    """One pyvista PolyData of a small cone per sensor pose (N, 4, 4 sensor-to-world, metres): apex at the sensor,
    opening along the direction it looks (+z of the pose)."""
    import pyvista as pv

    poses = np.asarray(poses, dtype=np.float64)
    origins, axes = poses[:, :3, 3], poses[:, :3, 2]
    crowd = min(1.0, float(np.sqrt(CONE_FULL_SIZE / len(poses))))
    length = CONE_SHARE * crowd * float(np.median(np.linalg.norm(origins - center, axis=1)) or 1.0)
    radius = length * np.tan(np.radians(CONE_HALF_ANGLE_DEG))
    cones = [pv.Cone(center=o + a * length / 2, direction=-a, height=length, radius=radius, resolution=12)
             for o, a in zip(origins, axes)]
    return pv.merge(cones) if len(cones) > 1 else cones[0]


WINDOW_PX = (800, 600)
"""The scene's window (width, height); the viewer fits the scene to its own frame."""
AZIMUTH_DEG, ELEVATION_DEG, VIEW_ANGLE_DEG = 30.0, 25.0, 30.0
"""The first camera."""
MESH_SPECULAR, GT_OPACITY = 0.15, 0.45
SPECULAR_POWER = 100.0
"""pyvista's default highlight power, as the pictures have it."""


@dataclass
class Scene:
    """What `scene_zip` serialises: a render window and its renderer."""

    render_window: object
    renderer: object


def build_scene(mesh, gt=None, poses: np.ndarray | None = None) -> tuple[Scene, list[Layer]]:
    """(the scene, its layers in the order of their actors). The server only describes the scene, which the browser
    draws (WebGL): it is built in VTK's generic OpenGL window, which is given no context and so never draws, and needs
    no display, EGL or OSMesa (a worker or a dashboard in a rack or a container serves it all the same)."""
    from vtkmodules.vtkRenderingCore import vtkLightKit, vtkRenderer
    # loaded, it makes VTK's renderer and actors the OpenGL ones, which the serialiser and the viewer read
    from vtkmodules.vtkRenderingOpenGL2 import vtkGenericOpenGLRenderWindow

    renderer = vtkRenderer()
    renderer.SetBackground(_rgb(offscreen.BACKGROUND))
    layers = [Layer("reconstruction")]
    renderer.AddActor(_actor(offscreen.polydata(mesh), offscreen.MESH_COLOUR, specular=MESH_SPECULAR))
    if gt is not None:
        layers.append(Layer("ground truth"))
        renderer.AddActor(_actor(offscreen.polydata(gt), offscreen.GT_COLOUR, opacity=GT_OPACITY))
    center, half = offscreen.frame([mesh] + ([gt] if gt is not None else []))
    if poses is not None and len(poses):
        layers.append(Layer("sensor poses"))
        renderer.AddActor(_actor(pose_cones(poses, center), offscreen.POSE_COLOUR, smooth=False))
    vtkLightKit().AddLightsToRenderer(renderer)
    window = vtkGenericOpenGLRenderWindow()
    window.SetSize(*WINDOW_PX)
    window.AddRenderer(renderer)
    _frame_camera(renderer, center, half)
    return Scene(window, renderer), layers


def _rgb(colour: str) -> tuple[float, float, float]:
    import pyvista as pv

    return pv.Color(colour).float_rgb


def _actor(data, colour: str, *, opacity: float = 1.0, specular: float = 0.0, smooth: bool = True):
    """An actor of surface `data` (offscreen.polydata, or any PolyData) in `colour`: shaded smoothly by its own point
    normals (`smooth`) or flat, lit by diffuse light only but for `specular`."""
    from vtkmodules.vtkRenderingCore import vtkActor, vtkDataSetMapper

    mapper = vtkDataSetMapper()
    mapper.SetInputData(data)
    mapper.ScalarVisibilityOff()
    actor = vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(_rgb(colour))
    prop.SetOpacity(opacity)
    prop.SetAmbient(0.0)
    prop.SetDiffuse(1.0)
    prop.SetSpecular(specular)
    prop.SetSpecularPower(SPECULAR_POWER)
    if smooth:
        prop.SetInterpolationToPhong()
    else:
        prop.SetInterpolationToFlat()
    return actor


def _frame_camera(renderer, center: np.ndarray, half: float) -> None:
    """The first camera: from (AZIMUTH_DEG, ELEVATION_DEG) around `center`, moved to hold the whole frame."""
    eye, focal, up = offscreen.orbit_camera(center, half, AZIMUTH_DEG, ELEVATION_DEG)
    camera = renderer.GetActiveCamera()
    camera.SetPosition(eye)
    camera.SetFocalPoint(focal)
    camera.SetViewUp(up)
    camera.SetViewAngle(VIEW_ANGLE_DEG)
    renderer.ResetCamera(*np.ravel(np.stack([center - half, center + half]), order="F"))
    renderer.ResetCameraClippingRange()


def scene_zip(pl: Scene) -> bytes:
    """The scene as vtk.js's OfflineLocalView reads it: a zip holding index.json (the serialised render
    window and every data array it uses)."""
    from trame_vtk.modules.vtk.serializers import (SynchronizationContext, extract_array_hash,
                                                   initialize_serializers, reference_id, serialize)

    initialize_serializers()
    context = SynchronizationContext()
    window = pl.render_window
    state = serialize(None, window, "spadscan-view", context, 1)
    camera = pl.renderer.GetActiveCamera()
    state["extra"] = {"vtkRefId": reference_id(window), "centerOfRotation": camera.GetFocalPoint(),
                      "camera": reference_id(camera)}
    hashes = {e["hash"]: dict(e, content=context.get_cached_data_array(e["hash"], False))
              for e in extract_array_hash(state)}
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("index.json", json.dumps({"hashes": hashes, "scene": state}), compress_type=zipfile.ZIP_DEFLATED)
    return buffer.getvalue()


PANEL = """<div id="spadscan-scene" style="position:fixed;top:0;left:0;right:0;bottom:0"></div>
<div id="spadscan-layers" style="position:fixed;top:8px;left:8px;z-index:10;background:rgba(255,255,255,0.9);
 font:13px sans-serif;padding:6px 10px;border:1px solid #bbb;border-radius:4px">
<strong>{title}</strong><br>
{boxes}
<div style="color:#555;font-size:11px;margin-top:4px">drag: turn &middot; shift-drag: pan &middot; wheel: zoom</div>
</div>
<script>
(function () {{
  // vtk.js adds favicon links to a web site as it loads: this page must fetch nothing, so they are not added.
  var head = document.head, append = head.appendChild.bind(head);
  head.appendChild = function (node) {{
    return (node.tagName === "LINK" && /^https?:/i.test(node.getAttribute("href") || "")) ? node : append(node);
  }};
  function actors() {{
    // The scene's renderer is the last one: the viewer's window starts with an empty renderer of its own.
    var rw = (window.global || {{}}).renderWindow, renderers = rw ? rw.getRenderers() : [];
    return renderers.length ? [rw, renderers[renderers.length - 1].getActors()] : [null, []];
  }}
  function camera() {{
    var rw = (window.global || {{}}).renderWindow, renderers = rw ? rw.getRenderers() : [];
    return renderers.length ? renderers[renderers.length - 1].getActiveCamera() : null;
  }}
  function cameraState(cam) {{
    return {{position: cam.getPosition(), focalPoint: cam.getFocalPoint(), viewUp: cam.getViewUp(),
             viewAngle: cam.getViewAngle()}};
  }}
  // A page that shows this view in a frame and replaces it (the dashboard, when the live mesh changes) keeps the
  // operator's camera: it asks spadscanCamera() (null while the camera is the scene's own) and hands the answer to
  // the new page as its address's #camera=JSON, applied once the scene has loaded.
  var sceneCamera = null;
  window.spadscanCamera = function () {{
    var cam = camera(), now = cam && sceneCamera ? cameraState(cam) : null;
    return now && JSON.stringify(now) !== sceneCamera ? now : null;
  }};
  function handedCamera() {{
    var found = /[#&]camera=([^&]*)/.exec(location.hash);
    if (!found) return null;
    var state;
    try {{ state = JSON.parse(decodeURIComponent(found[1])); }} catch (err) {{ return null; }}
    var triple = function (v) {{ return Array.isArray(v) && v.length === 3 && v.every(isFinite); }};
    return state && triple(state.position) && triple(state.focalPoint) && triple(state.viewUp) &&
      isFinite(state.viewAngle) ? state : null;
  }}
  function applyCamera(state) {{
    var cam = camera(), rw = window.global.renderWindow;
    cam.setPosition.apply(cam, state.position);
    cam.setFocalPoint.apply(cam, state.focalPoint);
    cam.setViewUp.apply(cam, state.viewUp);
    cam.setViewAngle(state.viewAngle);
    rw.getRenderers()[rw.getRenderers().length - 1].resetCameraClippingRange();
    rw.render();
  }}
  function show(box) {{
    var found = actors(), actor = found[1][Number(box.dataset.layer)];
    if (actor) {{ actor.setVisibility(box.checked); found[0].render(); }}
  }}
  document.querySelectorAll("#spadscan-layers input").forEach(function (box) {{
    box.addEventListener("change", function () {{ show(box); }});
  }});
  // Layers that start hidden are hidden once the scene has loaded.
  var tries = 0, wait = setInterval(function () {{
    var list = actors()[1];
    if (list.length || ++tries > 600) {{
      clearInterval(wait);
      document.querySelectorAll("#spadscan-layers input").forEach(function (box) {{ if (!box.checked) show(box); }});
      if (list.length) {{
        sceneCamera = JSON.stringify(cameraState(camera()));
        var handed = handedCamera();
        if (handed) applyCamera(handed);
      }}
      document.body.dataset.sceneLoaded = list.length ? "yes" : "no";
    }}
  }}, 50);
}})();
</script>
"""


def viewer_html(scene: bytes, layers: list[Layer], title: str) -> str:
    """trame-vtk's standalone vtk.js viewer with `scene` (a scene_zip) embedded, titled, with the layer panel."""
    from trame_vtk.tools.vtksz2html import HTML_VIEWER_PATH

    page = Path(HTML_VIEWER_PATH).read_text(encoding="utf-8")
    boxes = "<br>\n".join(
        f'<label><input type="checkbox" data-layer="{i}"{" checked" if layer.visible else ""}> '
        f"{html.escape(layer.label)}</label>" for i, layer in enumerate(layers))
    ours = (PANEL.format(title=html.escape(title), boxes=boxes)
            + "<script>\nfunction loadDataSet() {\n"
            + "  const container = document.getElementById('spadscan-scene');\n"
            + f'  OfflineLocalView.load(container, {{ base64Str: "{base64.b64encode(scene).decode()}" }});\n'
            + "}\n</script>\n")
    start, end = page.find("<title>"), page.find("</title>")
    if 0 <= start < end:
        page = page[:start] + f"<title>{html.escape(title)}</title>" + page[end + len("</title>"):]
    cut = page.rfind("</body>")
    return page[:cut] + ours + page[cut:]


def view3d_html(mesh, gt=None, poses: np.ndarray | None = None, title: str = "3D view") -> str:
    """The whole page for a mesh (trimesh, metres), an optional ground truth and optional sensor poses (N, 4, 4)."""
    scene, layers = build_scene(mesh, gt, poses)
    return viewer_html(scene_zip(scene), layers, title)


def write_view3d(folder, mesh, gt=None, poses: np.ndarray | None = None, title: str = "3D view") -> Path:
    """Write `folder`/view3d.html (temporary file, then rename). Returns its path."""
    folder = Path(folder)
    return write_atomic(folder / VIEW3D, view3d_html(mesh, gt, poses, title))
