"""Figure A: one panel per parameter, Chamfer distance (log axis) against the parameter, every method, failures marked.

In a one-at-a-time sweep each panel holds the entries of its axis (every other parameter at the base condition,
whose value is a dotted vertical line). In a product sweep each panel has one line per method and per combination of
the other axes, each combination with its own marker and dashes, named in the panel's legend ("power=1"). A sweep
without a grid (the base condition alone) is one panel: each method's Chamfer distance there. A method that gave no
surface at a point is drawn as a cross in a strip along the panel's top edge, above every value and apart from them,
in its colour; a result whose run warned (it did not converge, or says why it is doubtful) is a hollow marker.
"""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, NullLocator
from matplotlib.transforms import blended_transform_factory

from .params import PARAMS
from .plan import PRODUCT_AXIS
from .results import SweepResults, number, value_key

COLOURS = {"fast": "#1f77b4", "paper": "#9467bd", "reprojection": "#d62728", "space-carving": "#2ca02c"}
LABELS = {"fast": "fast (ours)", "paper": "paper (published method)", "reprojection": "reprojection",
          "space-carving": "space carving"}
COLUMNS = 4
PANEL_IN = (3.6, 3.0)
"""A panel's width and height (inches)."""
DPI = 110
EDGE_IN = 0.1
"""The room kept between the title or the legend and the picture's edges (inches)."""
FAILED_ROW = 0.06  # the height of a method's row of failure crosses, as a fraction of the panel's height
FAILED_GAP = 0.04
"""The room between the largest value's line and the failure crosses' rows, as a fraction of the panel's height:
the label at that line stays apart from the crosses."""
NICE = (1.0, 2.0, 3.0, 5.0)
"""The leading digits a Chamfer axis may end at: an end is labelled, so that labels reach past every value."""
END_MARGIN = 1.05
"""A Chamfer axis ends at least this factor beyond its values, so that a marker at the end is drawn whole."""
EMPTY_RANGE_MM = (1.0, 100.0)
"""The Chamfer axis (mm) of a panel where every method failed: a log axis as every other panel's, over a range that
holds the figures a sweep usually draws."""
MARKERS = ("o", "s", "^", "D", "v", "P", "*")
DASHES = ("-", "--", ":", "-.")
"""A product sweep's combinations of the other axes, told apart by marker and dashes (7 x 4 combinations before one
repeats; a cross is a failure's)."""
MARKER_SIZE = 4.5
WARNED_LABEL = "hollow: the run warned (see the table)"


def method_label(method: str) -> str:
    return LABELS.get(method, method)


def panel_title(index: int, axis: str) -> str:
    label = PARAMS[axis].label if axis in PARAMS else axis
    return f"({chr(ord('a') + index)}) {label}" if index < 26 else label


def figure_png(results: SweepResults, scene: str, path: Path) -> Path:
    """Draw Figure A of `scene` into the PNG `path`."""
    figure(results, scene).savefig(path, dpi=DPI)
    return path


def figure(results: SweepResults, scene: str) -> Figure:
    """Figure A of `scene`, laid out."""
    axes_names = list(results.grid)
    rows_of_scene = [r for r in results.rows if r["scene"] == scene]
    n = max(1, len(axes_names))
    cols = min(COLUMNS, n)
    lines = math.ceil(n / cols)
    # A bare Figure (no pyplot): no global backend or figure registry is touched.
    fig = Figure(figsize=(PANEL_IN[0] * cols, PANEL_IN[1] * lines + 0.6))
    grid = fig.subplots(lines, cols, squeeze=False)
    if axes_names:
        for i, axis in enumerate(axes_names):
            _panel(grid[i // cols][i % cols], results, rows_of_scene, axis, i)
    else:
        _base_panel(grid[0][0], results, rows_of_scene)
    for j in range(n, lines * cols):
        grid[j // cols][j % cols].set_visible(False)
    handles = [Line2D([], [], color=COLOURS.get(m, "k"), marker="o", label=method_label(m))
               for m in results.methods]
    handles.append(Line2D([], [], color="0.3", marker="x", linestyle="none", label="failed (no result)"))
    if any(results.method_warnings(r, m) for r in rows_of_scene for m in results.methods):
        handles.append(Line2D([], [], color="0.3", marker="o", markerfacecolor="white", linestyle="none",
                              label=WARNED_LABEL))
    legend = fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=9)
    what = "against each imaging parameter" if axes_names else "at the base condition (no grid)"
    title = fig.suptitle(f"{scene}: Chamfer distance {what}", fontsize=11)
    _lay_out(fig, legend, title)
    return fig


def _lay_out(fig: Figure, legend, title) -> None:
    """Make the figure wide enough for its title and legend (a row of one or two panels is narrower than either),
    the panels keeping their width in the middle, and fit the panels above the legend (tight_layout leaves room
    for the title itself, not for a figure's legend)."""
    renderer = FigureCanvasAgg(fig).get_renderer()
    boxes = [artist.get_window_extent(renderer) for artist in (legend, title)]
    width = fig.get_figwidth()
    needed = max(box.width for box in boxes) / fig.dpi + 2 * EDGE_IN
    side = 0.0
    if needed > width:
        side = (needed - width) / 2 / needed
        fig.set_figwidth(needed)
    height_px = fig.get_figheight() * fig.dpi
    fig.tight_layout(rect=(side, (boxes[0].y1 + EDGE_IN * fig.dpi) / height_px, 1 - side, 1))


def _groups(results: SweepResults, rows: list[dict], axis: str) -> list[tuple[str, list[dict]]]:
    """The lines of a panel: (label, rows) per combination of the other axes' values (a product sweep, its label
    such as "power=1 seed=0", in the order of those values), or the axis's own entries, unlabelled."""
    if results.mode == "one-at-a-time":
        return [("", [r for r in rows if r["axis"] == axis])]
    others = [a for a in results.grid if a != axis]
    keyed: dict[tuple, list] = {}
    for r in rows:
        if r["axis"] == PRODUCT_AXIS:
            keyed.setdefault(tuple(r.get(a) for a in others), []).append(r)
    return [(" ".join(f"{a}={_shown(t)}" for a, t in zip(others, key)), keyed[key])
            for key in sorted(keyed, key=lambda key: tuple(map(value_key, key)))]


def _shown(text) -> str:
    v = number(text)
    return f"{v:g}" if v is not None else str(text)


def _draw(ax, method: str, pts: list, marker: str, dashes: str) -> None:
    """A method's line through `pts` ((x, Chamfer, warned)), a filled marker at each result and a hollow one at
    each result whose run warned."""
    colour = COLOURS.get(method, "k")
    ax.plot([p[0] for p in pts], [p[1] for p in pts], linestyle=dashes, color=colour)
    for warned in (False, True):
        at = [p for p in pts if p[2] == warned]
        if at:
            ax.plot([p[0] for p in at], [p[1] for p in at], marker=marker, ms=MARKER_SIZE, linestyle="none",
                    color=colour, **({"markerfacecolor": "white", "markeredgewidth": 1.3} if warned else {}))


def _panel(ax, results: SweepResults, rows: list[dict], axis: str, index: int) -> None:
    groups = _groups(results, rows, axis)
    top = blended_transform_factory(ax.transData, ax.transAxes)
    drawn: list[float] = []
    any_failed = False
    keys = []
    for g, (label, group) in enumerate(groups):
        marker, dashes = MARKERS[g % len(MARKERS)], DASHES[g % len(DASHES)]
        if label:
            keys.append(Line2D([], [], color="0.35", marker=marker, linestyle=dashes, ms=MARKER_SIZE, label=label))
        for m, method in enumerate(results.methods):
            pts = sorted((x, results.method_value(r, method), bool(results.method_warnings(r, method)))
                         for r in group
                         if (x := number(r.get(axis))) is not None and not results.method_failed(r, method))
            failed = sorted(x for r in group if (x := number(r.get(axis))) is not None
                            and results.method_failed(r, method))
            if pts:
                _draw(ax, method, pts, marker, dashes)
                drawn.extend(p[1] for p in pts)
            if failed:
                any_failed = True
                # Stacked down from the top edge, one row per method, so that crosses at one x all show.
                ax.plot(failed, [1.0 - FAILED_ROW * (m + 0.5)] * len(failed), marker="x", ms=7, mew=2,
                        linestyle="none", color=COLOURS.get(method, "k"), transform=top, clip_on=False)
    _chamfer_axis(ax, drawn, any_failed, len(results.methods))
    if len(keys) > 1:
        ax.legend(handles=keys, fontsize=7, loc="best", framealpha=0.8, handlelength=2.5)
    values = [v for v in results.grid.get(axis, []) if isinstance(v, (int, float))]
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    logarithmic = PARAMS.get(axis) is not None and PARAMS[axis].log
    if logarithmic and values and min(values) > 0:
        ax.set_xscale("log")
    elif logarithmic and values and min(values) == 0 and max(values) > 0:  # ambient light from none: linear to the
        # first value over 0, logarithmic above (a linear parameter from 0, an elevation, stays linear)
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
    ax.tick_params(which="both", labelsize=8)  # the minor ticks' labels too (the y axis labels some)
    ax.grid(True, which="both", alpha=0.25)


def _base_panel(ax, results: SweepResults, rows: list[dict]) -> None:
    """The one panel of a sweep without a grid: each method's Chamfer distance at the base condition, a method to a
    column (several seeds' worth of rows would stand in one column)."""
    top = blended_transform_factory(ax.transData, ax.transAxes)
    drawn: list[float] = []
    any_failed = False
    for m, method in enumerate(results.methods):
        pts = [(m, results.method_value(r, method), bool(results.method_warnings(r, method)))
               for r in rows if not results.method_failed(r, method)]
        pts = [p for p in pts if p[1] is not None]  # done without a figure (no ground truth to score it on)
        if pts:
            _draw(ax, method, pts, "o", "none")
            drawn.extend(p[1] for p in pts)
            for x, v, _ in pts:
                ax.annotate(f"{v:.3g} mm", (x, v), xytext=(6, 0), textcoords="offset points", va="center",
                            fontsize=8, color=COLOURS.get(method, "k"))
        if any(results.method_failed(r, method) for r in rows):
            any_failed = True
            ax.plot([m], [1.0 - FAILED_ROW * (m + 0.5)], marker="x", ms=7, mew=2, linestyle="none",
                    color=COLOURS.get(method, "k"), transform=top, clip_on=False)
    _chamfer_axis(ax, drawn, any_failed, len(results.methods))
    ax.set_xlim(-0.5, len(results.methods) - 0.5)
    ax.set_xticks(range(len(results.methods)))
    ax.set_xticklabels([method_label(m) for m in results.methods], rotation=20)
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_title("(a) the base condition", fontsize=10)
    ax.set_ylabel("Chamfer (mm)", fontsize=8)
    ax.tick_params(which="both", labelsize=8)
    ax.grid(True, which="both", axis="y", alpha=0.25)


def _chamfer_axis(ax, drawn: list, any_failed: bool, methods: int) -> None:
    """A log Chamfer axis (mm) over the values drawn, with room for the failures' strip above them."""
    drawn = [v for v in drawn if v is not None and v > 0]  # a log axis shows no 0
    ax.set_yscale("log")
    if drawn:
        low, high = _nice_below(min(drawn) / END_MARGIN), _nice_above(max(drawn) * END_MARGIN)
    else:  # every method failed: the failures' crosses above an empty decade, not a linear axis through 0
        low, high = EMPTY_RANGE_MM
    ax.set_ylim(low, high)
    # No value is labelled in the failures' strip above the data: a cross there is no Chamfer distance.
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}" if v <= high * 1.0001 else ""))
    ax.yaxis.set_minor_formatter(_minor_formatter(low, high))
    if any_failed:
        _make_room_for_failures(ax, low, high, methods)


def _nice_below(v: float) -> float:
    """The largest NICE leading digit times a power of ten that is at most `v` (> 0)."""
    power = 10.0 ** math.floor(math.log10(v))
    return max(d * power for d in NICE if d * power <= v * (1 + 1e-9))


def _nice_above(v: float) -> float:
    """The smallest NICE leading digit times a power of ten that is at least `v` (> 0)."""
    power = 10.0 ** math.floor(math.log10(v))
    return min((d * power for d in (*NICE, 10.0) if d * power >= v * (1 - 1e-9)))


def _minor_formatter(low: float, high: float):
    """Labels for the minor ticks of a log axis from `low` to `high` (mm), two NICE values.

    The ends are labelled, so that labels reach past every value. Where two powers of ten fall inside the limits,
    their labels say the rest. Otherwise the minor ticks are labelled too: all of them within a factor of 3 (they
    stand far enough apart), else only those at 2 and 5 times a power of ten (all nine in a decade and more print on
    top of each other).
    """
    powers = math.floor(math.log10(high)) - math.ceil(math.log10(low)) + 1
    every = high / low <= 3.0

    def label(v: float, _) -> str:
        if math.isclose(v, low, rel_tol=1e-6) or math.isclose(v, high, rel_tol=1e-6):
            return f"{v:g}"
        leading = round(v / 10 ** math.floor(math.log10(v) + 1e-9))
        inside = low * 0.9999 <= v <= high * 1.0001
        return f"{v:g}" if inside and powers < 2 and (every or leading in (2, 5)) else ""

    return FuncFormatter(label)


def _make_room_for_failures(ax, low: float, high: float, methods: int) -> None:
    """Raise the top of a log axis so that the failure crosses' rows sit above every value, behind a line."""
    strip = FAILED_ROW * methods + FAILED_GAP
    span = math.log10(high) - math.log10(low)
    ax.set_ylim(low, 10 ** (math.log10(low) + span / (1.0 - strip)))
    ax.axhline(high, color="0.6", linewidth=0.8, linestyle="--")


__all__ = ["figure_png", "figure", "method_label", "panel_title", "COLOURS"]
