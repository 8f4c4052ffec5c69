"""Still pictures of meshes, drawn off screen by pyvista: the preview (reconstruction with the ground truth beside it),
the mesh coloured by its per-vertex normal error, and the mesh coloured by how many views see each part of it (where
it is a measurement and where it is the prior's guess).

A machine that cannot draw off screen (see offscreen.py) gets a one-line warning and no picture: the report says the
picture was not written, and the run that asked for it goes on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..coverage import UNDERSIDE_NZ
from . import offscreen

VIEWS = ((30.0, 25.0), (150.0, 25.0), (270.0, 25.0), (0.0, 89.0))
"""(azimuth, elevation) degrees of the panels: three around the object and one from above."""
COVERAGE_VIEWS = VIEWS + ((30.0, -50.0),)
"""The coverage picture's panels: those, and one from below, where a scan from above sees least."""
COVERAGE_COLOURS = ("#d62728", "#ff9f1c", "#b8c4d0", "#5f5f5f")
"""Colours of the coverage picture's classes of surface: seen by no view, by too few, by enough; and an underside,
which the report's coverage leaves out (no view from above the table can see it, and none is owed)."""
UNDERSIDE_CLASS = 3


def _add(pl, mesh, data, **style) -> None:
    """Add `mesh` as `data` (its offscreen.polydata) to the current panel: a shaded surface, or a point cloud."""
    if len(getattr(mesh, "faces", ())):
        offscreen.add_shaded(pl, data, specular=0.15, **style)
    else:  # a point cloud (the reprojection baseline)
        pl.add_mesh(data, render_points_as_spheres=True, point_size=3, **style)


def preview_png(mesh, path, gt=None, pixels: int = 280) -> Path | None:
    """The mesh from four angles, and below each panel the ground truth from the same angle at the same scale when
    given. Returns the PNG's path, or None when this machine cannot draw off screen (a warning says why)."""
    try:
        return draw_preview(mesh, path, gt, pixels)
    except offscreen.OffscreenUnavailable as exc:
        offscreen.warn(no_preview_warning(exc, path))
        return None


def preview_or_warning(mesh, path, gt=None, pixels: int = 280) -> str | None:
    """`preview_png`, for a run's report: None where the preview was drawn, else the one-line warning its report's
    "warnings" take (`no_preview_warning`; on stderr too), so that the report, and the dashboard that lists it, say
    why the result has no preview."""
    try:
        draw_preview(mesh, path, gt, pixels)
    except offscreen.OffscreenUnavailable as exc:
        offscreen.warn(no_preview_warning(exc, path))
        return no_preview_warning(exc, path)
    return None


def no_preview_warning(exc: Exception, path="preview.png") -> str:
    """The warning of a preview that was not drawn: "no preview.png: <why>", one line."""
    return f"no {Path(path).name}: {' '.join(str(exc).split())}"


def draw_preview(mesh, path, gt=None, pixels: int = 280) -> Path:
    """preview_png's picture, saying nothing: OffscreenUnavailable where this machine cannot draw off screen (the
    live job says it once in its status, not at every publication)."""
    rows = [("reconstruction", mesh, offscreen.MESH_COLOUR)]
    if gt is not None:
        rows.append(("ground truth", gt, offscreen.GT_COLOUR))
    pl = offscreen.plotter((len(rows), len(VIEWS)), (pixels, pixels))
    center, half = offscreen.frame([m for _, m, _ in rows])
    try:
        for r, (name, m, colour) in enumerate(rows):
            data = offscreen.polydata(m)
            for c, (az, el) in enumerate(VIEWS):
                pl.subplot(r, c)
                _add(pl, m, data, color=colour)
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
            offscreen.add_shaded(pl, data, scalars="normal error (deg)", cmap="viridis", clim=(0.0, vmax),
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


def coverage_classes(vertex_views: np.ndarray, few_views: int = 3) -> np.ndarray:
    """(n,) float: 0 for a part seen by no view, 1 for one seen by fewer than `few_views`, 2 for the rest."""
    v = np.asarray(vertex_views)
    return np.where(v <= 0, 0, np.where(v < few_views, 1, 2)).astype(np.float64)


def coverage_panels(mesh, vertex_views: np.ndarray, few_views: int = 3, pixels: int = 260,
                    underside: np.ndarray | None = None) -> np.ndarray:
    """The mesh coloured by coverage class (COVERAGE_COLOURS: `coverage_classes` of `vertex_views`, (n_vertices,)
    int; UNDERSIDE_CLASS where `underside`, (n_vertices,) bool, says so) from each of COVERAGE_VIEWS, side by side:
    an RGB image (pixels, pixels x panels, 3). offscreen.OffscreenUnavailable where this machine cannot draw off
    screen."""
    from matplotlib.colors import ListedColormap

    views = np.asarray(vertex_views)
    if views.shape != (len(mesh.vertices),):
        raise ValueError(f"vertex_views has shape {views.shape}, the mesh {len(mesh.vertices)} vertices")
    pl = offscreen.plotter((1, len(COVERAGE_VIEWS)), (pixels, pixels))
    center, half = offscreen.frame([mesh])
    data = offscreen.polydata(mesh)
    classes = coverage_classes(views, few_views)
    if underside is not None:
        classes = np.where(np.asarray(underside, bool), UNDERSIDE_CLASS, classes)
    data.point_data["class"] = classes
    cmap = ListedColormap(COVERAGE_COLOURS)
    try:
        for c, (az, el) in enumerate(COVERAGE_VIEWS):
            pl.subplot(0, c)
            offscreen.add_shaded(pl, data, scalars="class", cmap=cmap, clim=(-0.5, len(COVERAGE_COLOURS) - 0.5),
                                 interpolate_before_map=False,
                                 show_scalar_bar=False)
            pl.add_text(f"az {az:.0f} el {el:.0f}", position="upper_left", font_size=7, color="black")
            offscreen.set_view(pl, center, half, az, el)
        return pl.screenshot(return_img=True)
    finally:
        pl.close()


def coverage_png(mesh, vertex_views: np.ndarray, path, few_views: int = 3, area_views: np.ndarray | None = None,
                 pixels: int = 260) -> Path | None:
    """coverage_panels with a legend giving each class's share of the surface (of `area_views`, the views of
    area-uniform samples of the surface less its undersides, as the report's coverage counts it, when given, else of
    the vertices) and a title that says what it means. Returns the PNG's
    path, or None when this machine cannot draw off screen (a warning says why)."""
    from matplotlib.patches import Patch

    from .pictures import _plt

    # Where the share leaves the undersides out, so does the picture: grey, not the red of a part no view saw.
    underside = None if area_views is None else mesh.vertex_normals[:, 2] < UNDERSIDE_NZ
    try:
        image = coverage_panels(mesh, vertex_views, few_views, pixels, underside)
    except offscreen.OffscreenUnavailable as exc:
        offscreen.warn(f"no {Path(path).name}: {exc}")
        return None
    counted = coverage_classes(vertex_views if area_views is None else area_views, few_views)
    shares = [float((counted == k).mean()) for k in range(3)]
    plt = _plt()
    fig, ax = plt.subplots(figsize=(2.9 * len(COVERAGE_VIEWS), 3.6))
    ax.imshow(image)
    ax.set_axis_off()
    labels = ("seen by no view", f"seen by 1-{few_views - 1} views", f"seen by {few_views} or more views")
    handles = [Patch(color=colour, label=f"{label}: {share:.0%}")
               for label, colour, share in zip(labels, COVERAGE_COLOURS, shares)]
    if underside is not None:
        handles.append(Patch(color=COVERAGE_COLOURS[UNDERSIDE_CLASS], label="underside: not counted"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles), fontsize=8,
              frameon=False)
    fig.suptitle(f"Where the mesh is measured: views that see each part of it (share of the "
                 f"{'vertices' if area_views is None else 'surface, undersides left out'}); where fewer than "
                 f"{few_views} do, its shape "
                 "is the fit's smoothness prior, not the data", fontsize=9)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return Path(path)
