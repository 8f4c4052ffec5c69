"""The live reconstruction's 3D view: the report's own page (worker/report/view3d.py, trame-vtk's vtk.js viewer with
its scene embedded), whose scene the browser draws with WebGL.

The server only describes the scene; it draws nothing, so it needs no OpenGL of its own: on a machine without a
display, EGL or OSMesa (a server in a rack, a container) the 3D view is served all the same. The report's scene is
built in an off-screen plotter, which cannot be made without an off-screen OpenGL (and looks for a display, EGL and
OSMesa as it is made, warning of each one missing); the live view's is built here in VTK's generic OpenGL window,
which is given no context and so never draws, with the report's look for a mesh alone: its colour and shading, its
lights (pyvista's light kit) and its first camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv
from vtkmodules.vtkRenderingCore import vtkActor, vtkDataSetMapper, vtkLightKit, vtkRenderer
# loaded, it makes VTK's renderer and actor the OpenGL ones, as a plotter's are (what the viewer reads)
from vtkmodules.vtkRenderingOpenGL2 import vtkGenericOpenGLRenderWindow

from spadscan.worker.report import offscreen
from spadscan.worker.report.view3d import Layer, scene_zip, viewer_html

WINDOW_PX = (800, 600)
"""The scene's window (width, height): the report's. The viewer fits the scene to its own frame."""
AZIMUTH_DEG, ELEVATION_DEG, VIEW_ANGLE_DEG = 30.0, 25.0, 30.0
"""The first camera, as the report's 3D view starts."""
SPECULAR, SPECULAR_POWER = 0.15, 100.0
"""The mesh's highlights: the report's (its specular share, and pyvista's default power)."""


@dataclass
class Scene:
    """What `view3d.scene_zip` reads of a plotter: its render window and its renderer."""

    render_window: object
    renderer: object


def live_view_html(mesh, title: str) -> str:
    """The whole 3D view page of `mesh` (trimesh, metres), titled `title`; no OpenGL needed."""
    scene = build_scene(mesh)
    return viewer_html(scene_zip(scene), [Layer("reconstruction")], title)


def build_scene(mesh) -> Scene:
    """The mesh in a render window that never draws, lit and framed as the report's 3D view frames a mesh alone."""
    mapper = vtkDataSetMapper()
    mapper.SetInputData(offscreen.polydata(mesh))  # with the mesh's own normals: shaded smoothly
    mapper.ScalarVisibilityOff()
    actor = vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(pv.Color(offscreen.MESH_COLOUR).float_rgb)
    prop.SetAmbient(0.0)
    prop.SetDiffuse(1.0)
    prop.SetSpecular(SPECULAR)
    prop.SetSpecularPower(SPECULAR_POWER)
    prop.SetInterpolationToPhong()
    renderer = vtkRenderer()
    renderer.SetBackground(pv.Color(offscreen.BACKGROUND).float_rgb)
    renderer.AddActor(actor)
    vtkLightKit().AddLightsToRenderer(renderer)
    window = vtkGenericOpenGLRenderWindow()
    window.SetSize(*WINDOW_PX)
    window.AddRenderer(renderer)
    frame_camera(renderer, mesh)
    return Scene(window, renderer)


def frame_camera(renderer, mesh) -> None:
    """The report's first camera: from (AZIMUTH_DEG, ELEVATION_DEG) around the mesh's centre, then moved to hold its
    whole frame (offscreen.frame)."""
    center, half = offscreen.frame([mesh])
    eye, focal, up = offscreen.orbit_camera(center, half, AZIMUTH_DEG, ELEVATION_DEG)
    camera = renderer.GetActiveCamera()
    camera.SetPosition(eye)
    camera.SetFocalPoint(focal)
    camera.SetViewUp(up)
    camera.SetViewAngle(VIEW_ANGLE_DEG)
    renderer.ResetCamera(*np.ravel(np.stack([center - half, center + half]), order="F"))
    renderer.ResetCameraClippingRange()  # to the mesh itself, as the plotter does
