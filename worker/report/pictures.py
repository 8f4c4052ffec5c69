"""The report's pictures: mesh preview, error against time, measured versus rendered histograms, normal errors.

Plots are drawn with matplotlib's Agg backend (no display needed); meshes by pyvista off screen (mesh_pictures.py,
whose functions are named here too, with the per-vertex normal error they colour by). Each function writes one PNG
and returns its path.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from ..metrics import vertex_normal_error_deg
from .mesh_pictures import (VIEWS, coverage_png, draw_preview, no_preview_warning, normals_png,
                            preview_or_warning, preview_png)

__all__ = ["VIEWS", "preview_png", "draw_preview", "preview_or_warning", "no_preview_warning", "normals_png",
           "coverage_png", "vertex_normal_error_deg", "error_vs_time_png", "error_vs_time_figure", "fit_png",
           "normals_title", "chamfer_points", "plain_log_ticks"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


ERROR_TITLE = "error against run time"
LOSS_TITLE = "loss against run time (no checkpoint Chamfer)"
"""What error_vs_time.png shows: the Chamfer with the loss, or the loss alone when no checkpoint has a Chamfer (no
ground truth, or none of its evaluations gave a surface)."""


TITLE_WIDTH = 70
"""Characters a line of error_vs_time.png's title holds at its size (6 x 4 in, 10 pt): a longer one wraps."""


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
    """The matplotlib figure error_vs_time_png saves: log axes both ways, so that the first checkpoints (tens of
    millimetres) do not flatten the last ones. A checkpoint at 0 s has no place on a log axis and is left out (the
    x label says so)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    ch = [(t, c) for t, c in chamfer_points(trace) if t > 0 and c > 0]
    if ch:
        ax.plot(*zip(*ch), "o-", color="tab:blue", label="Chamfer (mm)")
        ax.set_yscale("log")
        plain_log_ticks(ax.yaxis)
        ax.set_ylabel("Chamfer distance (mm)", color="tab:blue")
        ax2 = ax.twinx()
    else:
        ax2 = ax
    pts = [(p["seconds"], p["loss"]) for p in trace if p.get("loss") is not None and p["loss"] > 0
           and p.get("seconds") is not None and p["seconds"] > 0]
    if pts:
        ax2.plot(*zip(*pts), "s--", color="tab:red", label="loss", markersize=3)
        ax2.set_yscale("log")
        plain_log_ticks(ax2.yaxis)
        ax2.set_ylabel("loss", color="tab:red")
    if ch or pts:
        ax.set_xscale("log")
        plain_log_ticks(ax.xaxis)
    at_zero = any(isinstance(p, dict) and p.get("seconds") == 0 for p in trace or [])
    # Two lines where it is long: without a second y axis the axes are wider, but a label longer than the figure
    # runs off both its edges.
    ax.set_xlabel("training time (s, checkpoint evaluation excluded" + (";\nthe start at 0 s is off this log axis)"
                                                                      if at_zero else ")"))
    title = title or ERROR_TITLE
    title = title if chamfer_points(trace) else title.replace(ERROR_TITLE, LOSS_TITLE)
    ax.set_title(textwrap.fill(title, TITLE_WIDTH), fontsize=10)
    ax.grid(alpha=0.3, which="both")
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


def normals_title(vertex_error_deg: np.ndarray) -> str:
    """normals.png's title. It names its measure: the metrics' "normal error" (area samples of both meshes, each
    against the other) is a different number for the same run, and the two must not read as disagreeing."""
    return (f"per-vertex normal error (mesh vertices against the nearest ground-truth normal): "
            f"mean {vertex_error_deg.mean():.1f} deg, median {np.median(vertex_error_deg):.1f} deg")
