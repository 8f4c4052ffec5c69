"""Reports of a reconstruction run: report.json, report.html, pictures (preview, error against time, histogram fit,
normals) and view3d.html, the 3D view you can turn.

Plots are drawn with matplotlib's Agg backend; meshes by pyvista (VTK) off screen, which needs no display but an
off-screen OpenGL (EGL or OSMesa, see offscreen.py); the 3D view is vtk.js, shipped by trame-vtk, in one page.
"""
