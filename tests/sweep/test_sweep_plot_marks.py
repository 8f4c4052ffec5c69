"""What Figure A and its page mark beyond the Chamfer distances: results whose run warned, baselines' thresholds at
an end of those tried, a product sweep's lines and rows, and a sweep without a grid."""

from __future__ import annotations

import re

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from spadscan.sweep.page import write_page
from spadscan.sweep.plot import _panel, figure
from spadscan.sweep.results import SweepResults

from page_helpers import browser_page

METHODS = ["fast", "reprojection"]
STEP_WARNING = "the run stopped on its step count well before convergence"
COVERAGE_WARNING = "27 % of the surface was seen by fewer than 3 views"


def row(axis: str, point: str, chamfer: dict, value="", warnings=None, **params) -> dict:
    """A results.csv row of both methods (`chamfer`: method -> mm, None for a failure); `warnings`: the fast
    preset's lines; reprojection's threshold 5 at the lowest end of those tried."""
    r = {"scene": "s", "axis": axis, "value": value, "point": point, "status": "done", "reason": "",
         **{k: str(v) for k, v in params.items()}}
    if value != "":
        r[axis] = str(value)
    for m, c in chamfer.items():
        key = m.replace("-", "_")
        r[f"{key}_status"] = "done" if c is not None else "failed"
        r[f"{key}_chamfer_mm"] = "" if c is None else str(c)
    r["fast_converged"] = "False" if warnings else "True"
    r["fast_warning_count"] = str(len(warnings or []))
    r["fast_warnings"] = " | ".join(warnings or [])
    r["reprojection_threshold"] = "5"
    r["reprojection_threshold_edge"] = "lowest"
    return r


def one_axis(tmp_path) -> SweepResults:
    rows = [row("views", "p8", {"fast": 12.0, "reprojection": 20.0}, 8, [STEP_WARNING, COVERAGE_WARNING]),
            row("views", "p16", {"fast": 4.0, "reprojection": 18.0}, 16)]
    return SweepResults(folder=tmp_path, mode="one-at-a-time", grid={"views": [8, 16]}, base={"views": 16},
                        scenes=["s"], methods=METHODS, presets=["fast"], rows=rows)


def product(tmp_path) -> SweepResults:
    """views x power, its rows in the order of their ids (a hash), not of their values."""
    rows = [row("product", "f0", {"fast": 5.0, "reprojection": 19.0}, views=16, power=1.0),
            row("product", "a1", {"fast": None, "reprojection": None}, views=16, power=1e-6),
            row("product", "c2", {"fast": 15.0, "reprojection": 24.0}, views=8, power=1.0),
            row("product", "b3", {"fast": None, "reprojection": None}, views=8, power=1e-6)]
    return SweepResults(folder=tmp_path, mode="product", grid={"views": [8, 16], "power": [1e-6, 1.0]},
                        base={"views": 16, "power": 1.0}, scenes=["s"], methods=METHODS, presets=["fast"], rows=rows)


def panel(results: SweepResults, axis: str):
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    _panel(ax, results, results.rows, axis, 0)
    fig.canvas.draw()
    return ax


def markers_at(ax, x: float) -> list:
    """The marker lines of `ax` that hold a point at `x`."""
    return [line for line in ax.get_lines() if line.get_marker() not in ("None", "", None, "x")
            and x in list(line.get_xdata())]


def test_a_result_whose_run_warned_is_a_hollow_marker_explained_in_the_legend(tmp_path):
    results = one_axis(tmp_path)
    ax = panel(results, "views")
    white = to_rgba("white")
    (warned,) = [line for line in markers_at(ax, 8) if to_rgba(line.get_color()) == to_rgba("#1f77b4")]
    assert to_rgba(warned.get_markerfacecolor()) == white
    assert all(to_rgba(line.get_markerfacecolor()) != white for line in markers_at(ax, 16))
    assert all(to_rgba(line.get_markerfacecolor()) != white for line in markers_at(ax, 8) if line is not warned)
    legend = [t.get_text() for t in figure(results, "s").legends[0].get_texts()]
    assert "hollow: the run warned (see the table)" in legend
    clean = one_axis(tmp_path)
    for r in clean.rows:
        r.update(fast_warnings="", fast_converged="True")
    assert not any("hollow" in t.get_text() for t in figure(clean, "s").legends[0].get_texts())


def test_a_preset_that_did_not_converge_and_says_nothing_still_counts_as_warned(tmp_path):
    results = one_axis(tmp_path)
    results.rows[1].update(fast_converged="False")
    assert results.method_warnings(results.rows[1], "fast") == ["the run did not converge"]
    assert results.method_warnings(results.rows[1], "reprojection") == []


def test_a_product_panel_names_the_other_axes_value_of_each_line(tmp_path):
    ax = panel(product(tmp_path), "views")
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["power=1e-06", "power=1"]
    ax = panel(product(tmp_path), "power")
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["views=8", "views=16"]
    # Each line of one combination has its own marker: told apart without fading.
    shapes = {line.get_marker() for line in markers_at(ax, 1.0)}
    assert len(shapes) == 2


def test_a_product_page_lists_its_rows_by_the_axes_values(tmp_path):
    page = write_page(product(tmp_path), {}, tmp_path).read_text()
    shown = re.findall(r"views=(\S+) power=([^<]+)</td>", page)
    assert shown == [("8", "1e-06"), ("8", "1"), ("16", "1e-06"), ("16", "1")], shown


def test_a_sweep_without_a_grid_draws_each_methods_chamfer_at_the_base(tmp_path):
    rows = [row("base", "p0", {"fast": 3.8, "reprojection": None})]
    results = SweepResults(folder=tmp_path, mode="one-at-a-time", grid={}, base={"views": 16}, scenes=["s"],
                           methods=METHODS, presets=["fast"], rows=rows)
    fig = figure(results, "s")
    (ax,) = [a for a in fig.axes if a.get_visible()]
    assert ax.get_title() == "(a) the base condition"
    assert [t.get_text() for t in ax.get_xticklabels()] == ["fast (ours)", "reprojection"]
    assert [line.get_marker() for line in markers_at(ax, 0)] == ["o"] and not markers_at(ax, 1)
    assert list(markers_at(ax, 0)[0].get_ydata()) == [3.8]
    assert any(line.get_marker() == "x" for line in ax.get_lines())  # reprojection failed there
    assert "the base condition" in fig.texts[0].get_text()
    page = write_page(results, {}, tmp_path).read_text()
    assert "the base condition alone" in page


def test_a_base_result_done_without_a_figure_is_left_out_of_the_base_panel(tmp_path):
    """A method done without a Chamfer (no ground truth scored it) has no point to draw: it was formatted as one."""
    rows = [row("base", "p0", {"fast": 3.8, "reprojection": 20.0})]
    rows[0]["reprojection_chamfer_mm"] = ""
    results = SweepResults(folder=tmp_path, mode="one-at-a-time", grid={}, base={"views": 16}, scenes=["s"],
                           methods=METHODS, presets=["fast"], rows=rows)
    (ax,) = [a for a in figure(results, "s").axes if a.get_visible()]
    assert [line.get_marker() for line in markers_at(ax, 0)] == ["o"] and not markers_at(ax, 1)


def test_the_page_marks_warnings_and_a_threshold_at_the_edge_in_a_browser(tmp_path):
    page_path = write_page(one_axis(tmp_path), {}, tmp_path)
    with browser_page() as (page, seen):
        page.goto(page_path.as_uri())
        page.wait_for_load_state("load")
        mark = page.locator("td .warn")
        assert mark.count() == 1 and mark.is_visible() and mark.inner_text().startswith("\u26a0")
        assert mark.get_attribute("title") == f"{STEP_WARNING}\n{COVERAGE_WARNING}"
        edge = page.locator("td .edge")
        assert edge.count() == 2 and edge.first.is_visible()
        assert edge.first.inner_text() == "at the edge of the tried thresholds (the lowest tried)"
        details = page.locator("td.warnings details")
        assert details.count() == 1 and details.locator("summary").inner_text() == "fast (ours): 2 warnings"
        item = details.locator("li").first
        assert not item.is_visible()
        details.locator("summary").click()
        assert item.is_visible() and item.inner_text() == STEP_WARNING
        assert "1 with warnings" in page.locator("p").first.inner_text()
    assert not seen.errors, seen.errors
