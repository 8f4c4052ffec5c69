"""Reports of a reconstruction run: report.json and pictures (preview, error against time, histogram fit, normals).

Pictures are drawn with matplotlib's Agg backend (headless); meshes are drawn by a small z-buffer point renderer
(`raster`), which handles meshes of any size without a display or OpenGL.
"""
