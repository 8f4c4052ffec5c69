"""The report's pictures: mesh preview, error against time, measured versus rendered histograms, normal errors.

Every function writes one PNG with matplotlib's Agg backend (no display needed) and returns its path.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .raster import shade, splat, surface_samples, view_rotation

VIEWS = ((30.0, 25.0), (150.0, 25.0), (270.0, 25.0), (0.0, 89.0))
"""(azimuth, elevation) degrees of the preview's panels."""


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _frame(meshes) -> tuple[np.ndarray, float]:
    lo = np.min([m.bounds[0] for m in meshes], axis=0)
    hi = np.max([m.bounds[1] for m in meshes], axis=0)
    return 0.5 * (lo + hi), 0.55 * float(np.linalg.norm(hi - lo)) + 1e-6


def _mesh_image(mesh, rot, center, half, pixels, values=None, samples=None):
    pts, nrm, _ = samples if samples is not None else surface_samples(mesh, 12 * pixels * pixels // 4)
    vals = shade(nrm, rot)[:, None] if values is None else values
    return splat(pts, vals, rot, center, half, pixels)


def preview_png(mesh, path, gt=None, pixels: int = 280) -> Path:
    """The mesh from four angles (three around, one from above); a second row shows the ground truth if given."""
    plt = _plt()
    rows = [("reconstruction", mesh)] + ([("ground truth", gt)] if gt is not None else [])
    center, half = _frame([m for _, m in rows])
    fig, axes = plt.subplots(len(rows), len(VIEWS), figsize=(3 * len(VIEWS), 3 * len(rows)), squeeze=False)
    for r, (name, m) in enumerate(rows):
        samples = surface_samples(m, 12 * pixels * pixels // 4)
        for c, (az, el) in enumerate(VIEWS):
            rot = view_rotation(az, el)
            img, mask = _mesh_image(m, rot, center, half, pixels, samples=samples)
            ax = axes[r, c]
            ax.imshow(np.where(mask, img[..., 0], 1.0), cmap="gray", vmin=0, vmax=1)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{name}, az {az:.0f} el {el:.0f}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


ERROR_TITLE = "error against run time"
LOSS_TITLE = "loss against run time (no checkpoint Chamfer)"
"""What error_vs_time.png shows: the Chamfer with the loss, or the loss alone when no checkpoint has a Chamfer (no
ground truth, or none of its evaluations gave a surface)."""


def error_vs_time_png(trace: list[dict], path, title: str = "") -> Path:
    """Chamfer (mm, where known) and loss against training seconds, one point per checkpoint.

    The words "error against run time" in title (its default) become "loss against run time ..." when no checkpoint
    has a Chamfer, so that the title names what is plotted."""
    plt = _plt()
    fig = error_vs_time_figure(trace, title)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def error_vs_time_figure(trace: list[dict], title: str = ""):
    """The matplotlib figure error_vs_time_png saves."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    ch = chamfer_points(trace)
    if ch:
        ax.plot(*zip(*ch), "o-", color="tab:blue", label="Chamfer (mm)")
        ax.set_ylabel("Chamfer distance (mm)", color="tab:blue")
        ax2 = ax.twinx()
    else:
        ax2 = ax
    pts = [(p["seconds"], p["loss"]) for p in trace if p.get("loss") is not None and p["loss"] > 0]
    if pts:
        ax2.plot(*zip(*pts), "s--", color="tab:red", label="loss", markersize=3)
        ax2.set_yscale("log")
        plain_log_ticks(ax2.yaxis)
        ax2.set_ylabel("loss", color="tab:red")
    ax.set_xlabel("training time (s, checkpoint evaluation excluded)")
    title = title or ERROR_TITLE
    ax.set_title(title if ch else title.replace(ERROR_TITLE, LOSS_TITLE), fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def chamfer_points(trace) -> list[tuple[float, float]]:
    """(seconds, Chamfer mm) of the trace's checkpoints that have a Chamfer."""
    return [(p["seconds"], p["chamfer_mm"]) for p in trace or []
            if isinstance(p, dict) and p.get("chamfer_mm") is not None]


def plain_log_ticks(axis) -> None:
    """Label a log axis's ticks with plain numbers (20, 0.05) rather than 2x10^1, keeping matplotlib's choice of
    which ticks get a label. An axis that reaches below 1e-4 or above 1e6 keeps the scientific form throughout:
    plain numbers there are long, and one axis should not mix the two."""
    from matplotlib.ticker import LogFormatterSciNotation

    class Plain(LogFormatterSciNotation):
        def __call__(self, x, pos=None):
            label = super().__call__(x, pos)
            lo, hi = sorted(self.axis.get_view_interval()) if self.axis is not None else (x, x)
            return _plain_number(x) if label and 1e-4 <= lo and hi < 1e6 else label

    axis.set_major_formatter(Plain())
    axis.set_minor_formatter(Plain(labelOnlyBase=False))


def _plain_number(x: float) -> str:
    return np.format_float_positional(float(x), precision=4, unique=True, fractional=False, trim="-")


def fit_png(measured: np.ndarray, rendered: np.ndarray, view_ids, path, zones=None) -> Path:
    """Measured counts (dots) against the model's expected counts (lines) for a few views.

    measured, rendered: (n, Z, B); zones: zone indices to show (default: all of a single-zone sensor, else the
    first, centre and last); the x range is cut to where either curve rises above its own floor."""
    plt = _plt()
    n, z, b = measured.shape
    zones = list(zones) if zones is not None else sorted({0, z // 2, z - 1})
    fig, axes = plt.subplots(n, 1, figsize=(7, 2.2 * n), squeeze=False)
    bins = np.arange(b)
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    for i in range(n):
        ax = axes[i, 0]
        lo, hi = _signal_range(measured[i, zones], rendered[i, zones])
        for k, zi in enumerate(zones):
            col = colours[k % len(colours)]
            ax.plot(bins[lo:hi], measured[i, zi, lo:hi], ".", color=col, markersize=3,
                    label=f"zone {zi} measured")
            ax.plot(bins[lo:hi], rendered[i, zi, lo:hi], "-", color=col, linewidth=1, label=f"zone {zi} model")
        ax.set_ylabel(f"view {view_ids[i]}\ncounts", fontsize=8)
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=6, ncol=2)
    axes[-1, 0].set_xlabel("bin")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def _signal_range(meas: np.ndarray, rend: np.ndarray) -> tuple[int, int]:
    """Bin range [lo, hi) around where the curves (k, B) rise above their medians, padded; whole axis if none."""
    b = meas.shape[-1]
    excess = np.maximum(meas - np.median(meas, axis=-1, keepdims=True), rend - np.median(rend, axis=-1,
                                                                                         keepdims=True)).max(0)
    idx = np.flatnonzero(excess > 0.1 * excess.max()) if excess.max() > 0 else np.array([], int)
    if idx.size == 0:
        return 0, b
    pad = max(8, (idx[-1] - idx[0]) // 2)
    return max(0, idx[0] - pad), min(b, idx[-1] + pad + 1)


def vertex_normal_error_deg(mesh, gt, n_gt: int = 300_000, seed: int = 0) -> np.ndarray:
    """Per-vertex angle (degrees) between the mesh's vertex normal and the ground truth's normal at the nearest of
    n_gt area-uniform ground-truth samples, using |<n, n~>| (orientation-free, as in the paper). (n_vertices,)."""
    from scipy.spatial import cKDTree

    g_pts, g_nrm, _ = surface_samples(gt, n_gt, seed)
    _, idx = cKDTree(g_pts).query(np.asarray(mesh.vertices), workers=-1)
    vn = np.asarray(mesh.vertex_normals)
    cos = np.clip(np.abs(np.einsum("ij,ij->i", vn, g_nrm[idx])), 0.0, 1.0)
    return np.degrees(np.arccos(cos))


def normals_title(vertex_error_deg: np.ndarray) -> str:
    """normals.png's title. It names its measure: the metrics' "normal error" (area samples of both meshes, each
    against the other) is a different number for the same run, and the two must not read as disagreeing."""
    return (f"per-vertex normal error (mesh vertices against the nearest ground-truth normal): "
            f"mean {vertex_error_deg.mean():.1f} deg, median {np.median(vertex_error_deg):.1f} deg")


def normals_png(mesh, vertex_error_deg: np.ndarray, path, pixels: int = 300, vmax: float = 45.0) -> Path:
    """The mesh coloured by per-vertex normal error (degrees, 0 .. vmax), from four angles, with a colour bar."""
    plt = _plt()
    import matplotlib as mpl

    cmap = mpl.colormaps["viridis"]
    pts, nrm, face = surface_samples(mesh, 12 * pixels * pixels // 4)
    err = vertex_error_deg[np.asarray(mesh.faces)[face]].mean(1)  # face-average of its vertices' errors
    center, half = _frame([mesh])
    fig, axes = plt.subplots(1, len(VIEWS), figsize=(3.2 * len(VIEWS), 3.4), squeeze=False)
    for c, (az, el) in enumerate(VIEWS):
        rot = view_rotation(az, el)
        colour = cmap(np.clip(err / vmax, 0, 1))[:, :3] * shade(nrm, rot)[:, None] ** 0.5
        img, mask = splat(pts, colour, rot, center, half, pixels)
        img[~mask] = 1.0
        axes[0, c].imshow(img)
        axes[0, c].set_xticks([])
        axes[0, c].set_yticks([])
        axes[0, c].set_title(f"az {az:.0f} el {el:.0f}", fontsize=8)
    sm = mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, vmax), cmap=cmap)
    fig.colorbar(sm, ax=axes[0, :].tolist(), fraction=0.02, label="per-vertex normal error (deg)")
    fig.suptitle(normals_title(vertex_error_deg), fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
