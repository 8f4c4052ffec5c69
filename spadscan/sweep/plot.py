"""Figure A: one panel per parameter, Chamfer distance (log axis) against the parameter, every method, failures marked.

In a one-at-a-time sweep each panel holds the entries of its axis (every other parameter at the base condition,
whose value is a dotted vertical line). In a product sweep each panel has one line per method and per combination of
the other axes (fainter lines for later combinations). A method that gave no surface at a point is drawn as a cross
in a strip along the panel's top edge, above every value and apart from them, in its colour.
"""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, NullFormatter, NullLocator
from matplotlib.transforms import blended_transform_factory

from .params import PARAMS
from .plan import PRODUCT_AXIS
from .results import SweepResults, number

COLOURS = {"fast": "#1f77b4", "paper": "#9467bd", "reprojection": "#d62728", "space-carving": "#2ca02c"}
LABELS = {"fast": "fast (ours)", "paper": "paper (published method)", "reprojection": "reprojection",
          "space-carving": "space carving"}
COLUMNS = 4
FAILED_ROW = 0.06  # the height of a method's row of failure crosses, as a fraction of the panel's height


def method_label(method: str) -> str:
    return LABELS.get(method, method)


def panel_title(index: int, axis: str) -> str:
    label = PARAMS[axis].label if axis in PARAMS else axis
    return f"({chr(ord('a') + index)}) {label}" if index < 26 else label


def figure_png(results: SweepResults, scene: str, path: Path) -> Path:
    """Draw Figure A of `scene` into the PNG `path`."""
    axes_names = list(results.grid)
    rows_of_scene = [r for r in results.rows if r["scene"] == scene]
    n = max(1, len(axes_names))
    cols = min(COLUMNS, n)
    lines = math.ceil(n / cols)
    # A bare Figure (no pyplot): no global backend or figure registry is touched.
    fig = Figure(figsize=(3.6 * cols, 3.0 * lines + 0.6))
    grid = fig.subplots(lines, cols, squeeze=False)
    for i, axis in enumerate(axes_names):
        _panel(grid[i // cols][i % cols], results, rows_of_scene, axis, i)
    for j in range(len(axes_names), lines * cols):
        grid[j // cols][j % cols].set_visible(False)
    handles = [Line2D([], [], color=COLOURS.get(m, "k"), marker="o", label=method_label(m))
               for m in results.methods]
    handles.append(Line2D([], [], color="0.3", marker="x", linestyle="none", label="failed (no result)"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=9)
    fig.suptitle(f"{scene}: Chamfer distance against each imaging parameter", fontsize=11)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    fig.savefig(path, dpi=110)
    return path


def _panel(ax, results: SweepResults, rows: list[dict], axis: str, index: int) -> None:
    if results.mode == "one-at-a-time":
        groups = [[r for r in rows if r["axis"] == axis]]
    else:
        others = [a for a in results.grid if a != axis]
        keyed: dict[tuple, list] = {}
        for r in rows:
            if r["axis"] == PRODUCT_AXIS:
                keyed.setdefault(tuple(r.get(a) for a in others), []).append(r)
        groups = list(keyed.values())
    top = blended_transform_factory(ax.transData, ax.transAxes)
    any_value = False
    any_failed = False
    for g, group in enumerate(groups):
        alpha = 1.0 if g == 0 else max(0.25, 1.0 - 0.15 * g)
        for m, method in enumerate(results.methods):
            pts = sorted((x, results.method_value(r, method)) for r in group
                         if (x := number(r.get(axis))) is not None and not results.method_failed(r, method))
            failed = sorted(x for r in group if (x := number(r.get(axis))) is not None
                            and results.method_failed(r, method))
            colour = COLOURS.get(method, "k")
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", ms=4, color=colour, alpha=alpha)
                any_value = True
            if failed:
                any_failed = True
                # Stacked down from the top edge, one row per method, so that crosses at one x all show.
                ax.plot(failed, [1.0 - FAILED_ROW * (m + 0.5)] * len(failed), marker="x", ms=7, mew=2,
                        linestyle="none", color=colour, alpha=alpha, transform=top, clip_on=False)
    values = [v for v in results.grid.get(axis, []) if isinstance(v, (int, float))]
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    if any_value:
        ax.set_yscale("log")
        low, high = ax.get_ylim()
        # No value is labelled in the failures' strip above the data: a cross there is no Chamfer distance.
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}" if v <= high * 1.0001 else ""))
        ax.yaxis.set_minor_formatter(_minor_formatter(low, high))
        if any_failed:
            _make_room_for_failures(ax, low, high, len(results.methods))
    if PARAMS.get(axis) is not None and PARAMS[axis].log and values and min(values) > 0:
        ax.set_xscale("log")
    elif values and min(values) == 0 and max(values) > 0:
        ax.set_xscale("symlog", linthresh=min(v for v in values if v > 0))
    if values:
        ax.set_xticks(sorted(values))
        ax.xaxis.set_major_formatter(plain)
        ax.xaxis.set_minor_locator(NullLocator())
        if len(values) > 4:
            ax.tick_params(axis="x", labelrotation=45)
    base = results.base.get(axis)
    if results.mode == "one-at-a-time" and isinstance(base, (int, float)):
        ax.axvline(base, color="0.5", linestyle=":", linewidth=1)
    ax.set_title(panel_title(index, axis), fontsize=10)
    ax.set_xlabel(PARAMS[axis].label if axis in PARAMS else axis, fontsize=8)
    ax.set_ylabel("Chamfer (mm)", fontsize=8)
    ax.tick_params(labelsize=8)
    ax.grid(True, which="both", alpha=0.25)


def _minor_formatter(low: float, high: float):
    """Labels for the minor ticks of a log axis from `low` to `high` (mm).

    Where two powers of ten fall inside the limits, their labels say enough. Otherwise the minor ticks are labelled
    too: all of them within a factor of 3 (they stand far enough apart), else only those at 2 and 5 times a power
    of ten (all nine in a decade and more print on top of each other).
    """
    powers = math.floor(math.log10(high)) - math.ceil(math.log10(low)) + 1
    if powers >= 2:
        return NullFormatter()
    every = high / low <= 3.0

    def label(v: float, _) -> str:
        leading = round(v / 10 ** math.floor(math.log10(v) + 1e-9))
        return f"{v:g}" if v <= high * 1.0001 and (every or leading in (2, 5)) else ""

    return FuncFormatter(label)


def _make_room_for_failures(ax, low: float, high: float, methods: int) -> None:
    """Raise the top of a log axis so that the failure crosses' rows sit above every value, behind a line."""
    strip = FAILED_ROW * methods
    span = math.log10(high) - math.log10(low)
    ax.set_ylim(low, 10 ** (math.log10(low) + span / (1.0 - strip)))
    ax.axhline(high, color="0.6", linewidth=0.8, linestyle="--")


__all__ = ["figure_png", "method_label", "panel_title", "COLOURS"]
