"""Still pictures of meshes, drawn off screen by pyvista: the preview (reconstruction with the ground truth beside it)
and the mesh coloured by its per-vertex normal error.

A machine that cannot draw off screen (see offscreen.py) gets a one-line warning and no picture: the report says the
picture was not written, and the run that asked for it goes on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import offscreen

VIEWS = ((30.0, 25.0), (150.0, 25.0), (270.0, 25.0), (0.0, 89.0))
"""(azimuth, elevation) degrees of the panels: three around the object and one from above."""


def _add(pl, mesh, **style) -> None:
    data = offscreen.polydata(mesh)
    if len(getattr(mesh, "faces", ())):
        pl.add_mesh(data, smooth_shading=True, specular=0.15, **style)
    else:  # a point cloud (the reprojection baseline)
        pl.add_mesh(data, render_points_as_spheres=True, point_size=3, **style)


def preview_png(mesh, path, gt=None, pixels: int = 280) -> Path | None:
    """The mesh from four angles, and below each panel the ground truth from the same angle at the same scale when
    given. Returns the PNG's path, or None when this machine cannot draw off screen (a warning says why)."""
    rows = [("reconstruction", mesh, offscreen.MESH_COLOUR)]
    if gt is not None:
        rows.append(("ground truth", gt, offscreen.GT_COLOUR))
    try:
        pl = offscreen.plotter((len(rows), len(VIEWS)), (pixels, pixels))
    except offscreen.OffscreenUnavailable as exc:
        offscreen.warn(f"no {Path(path).name}: {exc}")
        return None
    center, half = offscreen.frame([m for _, m, _ in rows])
    try:
        for r, (name, m, colour) in enumerate(rows):
            for c, (az, el) in enumerate(VIEWS):
                pl.subplot(r, c)
                _add(pl, m, color=colour)
                pl.add_text(f"{name}, az {az:.0f} el {el:.0f}", position="upper_left", font_size=7, color="black")
                offscreen.set_view(pl, center, half, az, el)
        pl.screenshot(str(path))
    finally:
        pl.close()
    return Path(path)


def normals_png(mesh, vertex_error_deg: np.ndarray, path, pixels: int = 300, vmax: float = 45.0) -> Path | None:
    """The mesh coloured by per-vertex normal error (degrees, 0 .. vmax) from four angles, with a colour bar and a
    title that names the measure. Returns the PNG's path, or None when this machine cannot draw off screen."""
    from .pictures import _plt, normals_title

    try:
        pl = offscreen.plotter((1, len(VIEWS)), (pixels, pixels))
    except offscreen.OffscreenUnavailable as exc:
        offscreen.warn(f"no {Path(path).name}: {exc}")
        return None
    center, half = offscreen.frame([mesh])
    data = offscreen.polydata(mesh)
    data.point_data["normal error (deg)"] = np.asarray(vertex_error_deg, dtype=np.float64)
    try:
        for c, (az, el) in enumerate(VIEWS):
            pl.subplot(0, c)
            pl.add_mesh(data, scalars="normal error (deg)", cmap="viridis", clim=(0.0, vmax), smooth_shading=True,
                        show_scalar_bar=False)
            pl.add_text(f"az {az:.0f} el {el:.0f}", position="upper_left", font_size=7, color="black")
            offscreen.set_view(pl, center, half, az, el)
        image = pl.screenshot(return_img=True)
    finally:
        pl.close()
    plt = _plt()
    import matplotlib as mpl

    fig, ax = plt.subplots(figsize=(3.2 * len(VIEWS), 3.6))
    ax.imshow(image)
    ax.set_axis_off()
    sm = mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, vmax), cmap=mpl.colormaps["viridis"])
    fig.colorbar(sm, ax=ax, fraction=0.02, label="per-vertex normal error (deg)")
    fig.suptitle(normals_title(np.asarray(vertex_error_deg)), fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
