"""Off-screen rendering with pyvista (VTK): a plotter that needs no display, meshes turned into VTK data, and orbit
cameras that frame several meshes alike.

VTK's wheels pick their OpenGL at run time: X when there is a display, else EGL (libEGL with a Mesa or GPU vendor
library), else OSMesa. A machine with neither display nor EGL/OSMesa cannot draw: `OffscreenUnavailable` says what to
install instead of letting VTK crash.
"""

from __future__ import annotations

import ctypes.util
import importlib
import importlib.util
import os
import sys

import numpy as np

from spadscan.protocol.errors import SpadscanError

BACKGROUND = "white"
MESH_COLOUR = "#c9a66b"
"""The reconstruction's colour: a warm clay, told apart from the ground truth's blue."""
GT_COLOUR = "#6b9bd1"
POSE_COLOUR = "#d1495b"
INSTALL_HINT = ("install an off-screen OpenGL: on Debian/Ubuntu `apt-get install libegl1 libegl-mesa0` (EGL) or "
                "`apt-get install libosmesa6` (OSMesa)")


class OffscreenUnavailable(SpadscanError):
    """No OpenGL that VTK can draw into without a display."""


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_offscreen() -> None:
    """Make sure VTK can draw here, and on a machine without a display make it go straight to EGL (or OSMesa)
    instead of trying X first and warning about it. Raises OffscreenUnavailable with what to install."""
    if _has_display() or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return
    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    elif ctypes.util.find_library("OSMesa"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSMesaRenderWindow"
    else:
        raise OffscreenUnavailable(f"no display and no EGL or OSMesa library to draw meshes off screen: "
                                   f"{INSTALL_HINT}")


def load_triton_first() -> None:
    """Import triton, where it is installed, before VTK opens its first OpenGL context.

    Mesa's OpenGL (EGL, OSMesa or GLX) loads the system's libLLVM when the first context opens; triton (which
    torch's CUDA build ships and imports lazily: torch.optim, torch.compile) carries an LLVM of its own, and loaded
    after Mesa's its start-up code runs on Mesa's LLVM and the process dies (SIGSEGV). Loaded first, both work."""
    if "triton" in sys.modules or importlib.util.find_spec("triton") is None:
        return
    try:
        importlib.import_module("triton")
    except Exception:  # a broken triton: torch says so itself when it needs it; the pictures need none
        pass


def plotter(shape: tuple[int, int] = (1, 1), panel_px: tuple[int, int] = (320, 320)):
    """An off-screen pyvista Plotter of `shape` (rows, columns) panels of `panel_px` (width, height) pixels each."""
    check_offscreen()
    load_triton_first()
    import pyvista as pv

    rows, cols = shape
    pl = pv.Plotter(off_screen=True, shape=shape, border=False,
                    window_size=(cols * panel_px[0], rows * panel_px[1]))
    pl.set_background(BACKGROUND)
    return pl


def polydata(mesh):
    """A trimesh.Trimesh (or PointCloud) as a pyvista PolyData, in the same units (metres)."""
    import pyvista as pv

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        return pv.PolyData(vertices)
    data = pv.PolyData.from_regular_faces(vertices, np.asarray(faces, dtype=np.int64))
    # The mesh's vertex normals, for `add_shaded`: pyvista's smooth shading computes them anew for every panel
    # (the nine panels of a run's pictures: 2 s of its end on a 256-cell mesh).
    data.point_data["Normals"] = np.asarray(mesh.vertex_normals, dtype=np.float64)
    data.point_data.active_normals_name = "Normals"
    return data


def add_shaded(pl, data, **style):
    """Add surface `data` (from `polydata`) to plotter `pl`, shaded smoothly by its own point normals; returns the
    actor. The same picture as pyvista's `smooth_shading=True`, without computing the normals again."""
    actor = pl.add_mesh(data, smooth_shading=False, **style)
    actor.prop.interpolation = "phong"
    return actor


def frame(meshes) -> tuple[np.ndarray, float]:
    """(centre (3,), half size in metres) of a view that holds every mesh, so that several panels share one scale."""
    lo = np.min([np.asarray(m.bounds[0]) for m in meshes], axis=0)
    hi = np.max([np.asarray(m.bounds[1]) for m in meshes], axis=0)
    return 0.5 * (lo + hi), 0.55 * float(np.linalg.norm(hi - lo)) + 1e-6


def orbit_camera(center: np.ndarray, half: float, azimuth_deg: float, elevation_deg: float) -> list:
    """pyvista camera position [eye, focal point, view up] looking at `center` from (azimuth, elevation) degrees
    (z up); the eye stands 4 half sizes away, far enough for an orthographic view not to clip."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([0.0, 0.0, 1.0]) if abs(elevation_deg) < 85 else np.array([-np.cos(az), -np.sin(az), 0.0])
    eye = np.asarray(center, dtype=np.float64) + 4.0 * half * toward
    return [tuple(eye), tuple(np.asarray(center, dtype=np.float64)), tuple(up)]


def set_view(pl, center: np.ndarray, half: float, azimuth_deg: float, elevation_deg: float) -> None:
    """Point the active panel's camera: orthographic, `half` metres from the centre to the panel's edge."""
    pl.camera_position = orbit_camera(center, half, azimuth_deg, elevation_deg)
    pl.enable_parallel_projection()
    pl.camera.parallel_scale = half
    pl.reset_camera_clipping_range()


def warn(message: str) -> None:
    """One line on stderr: a picture that could not be drawn never fails the run that asked for it."""
    print(f"spadscan: warning: {message}", file=sys.stderr, flush=True)
