"""`spadscan sweep-plot`: Figure A as a PNG, and a page with the picture and the table, checked in a real browser."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.cli import main
from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from page_helpers import browser_page, screenshot_pixels
from sweep_helpers import FAILING_POWER, write_tiny
from test_sweep_store import fake_result

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def finished_sweep(tmp_path):
    """The tiny sweep's folder with made-up results: the power 1e-7 point failed in every method."""
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    for task in plan.points.values():
        failed = ("fast", "reprojection", "space-carving") if task.params["power"] == FAILING_POWER else ()
        out.write_point(fake_result(task, failed))
    out.write_results(plan)
    return tmp_path / "out"


def test_sweep_plot_writes_figure_a_and_its_page(finished_sweep, capsys):
    assert main(["sweep-plot", str(finished_sweep)]) == 0
    assert "figure_a.html (open this first), figure_a.png" in capsys.readouterr().out
    png = (finished_sweep / "figure_a.png").read_bytes()
    assert png.startswith(PNG) and len(png) > 10_000
    page = (finished_sweep / "figure_a.html").read_text()
    assert '<img src="figure_a.png"' in page and "(a) number of views" in page and "(b) illumination power" in page
    assert page.count("<tr>") == 1 + 4 and page.count('class="missing">failed') == 3
    assert "reprojection found no surface" in page


def test_sweep_plot_of_a_folder_that_is_not_a_sweep_is_one_line(tmp_path, capsys):
    assert main(["sweep-plot", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "holds no sweep.json" in err and err.count("\n") == 1


def test_sweep_plot_of_a_file_says_it_is_a_file(tmp_path, capsys):
    (tmp_path / "results.csv").write_text("scene\n")
    assert main(["sweep-plot", str(tmp_path / "results.csv")]) == 1
    err = capsys.readouterr().err
    assert "no such sweep folder (a file, not a folder)" in err and err.count("\n") == 1, err
    assert main(["sweep-plot", str(tmp_path / "absent")]) == 1
    err = capsys.readouterr().err
    assert err.strip().endswith("absent: no such sweep folder"), err



def test_a_results_csv_re_saved_with_a_byte_order_mark_still_plots(finished_sweep, capsys):
    """A spreadsheet that saves the table as "CSV UTF-8" puts a byte-order mark before the first column's name."""
    csv_path = finished_sweep / "results.csv"
    csv_path.write_text(csv_path.read_text(encoding="utf-8"), encoding="utf-8-sig")
    assert csv_path.read_bytes().startswith(b"\xef\xbb\xbf")
    assert main(["sweep-plot", str(finished_sweep)]) == 0
    assert "figure_a.png" in capsys.readouterr().out
    assert (finished_sweep / "figure_a.html").read_text().count("<tr>") == 1 + 4


def _without_column(text: str, name: str) -> str:
    lines = [line.split(",") for line in text.splitlines()]
    i = lines[0].index(name)
    return "\n".join(",".join(cells[:i] + cells[i + 1:]) for cells in lines) + "\n"


@pytest.mark.parametrize("damage, expected", [
    (lambda folder: (folder / "results.csv").write_text(
        _without_column((folder / "results.csv").read_text(), "scene")), "lacks the column scene"),
    (lambda folder: (folder / "results.csv").write_text("a,b\n1,2\n"),
     "lacks the columns scene, axis, value, point, status, reason"),
    (lambda folder: _edit_meta(folder, grid=None), "'grid' is not an object"),
    (lambda folder: _edit_meta(folder, grid={"views": 8}), "'grid' is not an object"),
    (lambda folder: _edit_meta(folder, mode=3), "'mode' is not a string"),
    (lambda folder: _edit_meta(folder, scenes="builtin:sphere"), "'scenes' is not a list"),
    (lambda folder: _edit_meta(folder, methods=[1]), "must hold names"),
], ids=["no-scene-column", "other-table", "grid-null", "grid-scalar-values", "mode", "scenes", "methods"])
def test_a_damaged_results_table_or_sweep_json_is_one_line(finished_sweep, capsys, damage, expected):
    damage(finished_sweep)
    assert main(["sweep-plot", str(finished_sweep)]) == 1
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err, err


def _edit_meta(folder, **changes) -> None:
    import json

    path = folder / "sweep.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def test_the_help_names_the_pictures_as_they_are_written():
    from spadscan.commands import sweep_plot
    from spadscan.sweep.figure_a import picture_name

    scenes = ["builtin:sphere", "builtin:cup"]
    assert picture_name("builtin:cup", scenes) in sweep_plot.__doc__
    assert "figure_a-<n>-<scene>.png" in sweep_plot.__doc__ and picture_name("builtin:cup", ["builtin:cup"]) in \
        sweep_plot.__doc__

def test_the_page_shows_in_a_browser(finished_sweep):
    assert main(["sweep-plot", str(finished_sweep)]) == 0
    with browser_page() as (page, seen):
        page.goto((finished_sweep / "figure_a.html").as_uri())
        page.wait_for_load_state("load")
        assert page.locator("table tr").count() == 5
        image = page.locator("img")
        assert image.evaluate("img => img.complete && img.naturalWidth") > 500  # the PNG loaded
        # The figure drew: its picture holds the blue of the fast method's line.
        pixels = screenshot_pixels(image).astype(int)
        assert np.all(np.abs(pixels - [31, 119, 180]) <= 12, axis=-1).sum() > 50
        assert page.locator("td.failed").count() == 1
    assert not seen.errors, seen.errors
    assert all(url.startswith("file://") for url in seen.requests), seen.requests  # nothing from the network


@pytest.mark.parametrize("low, high", [(5.2, 46.0), (12.0, 30.0), (0.8, 150.0)])
def test_a_panels_chamfer_axis_carries_at_least_two_labelled_values(tmp_path, low, high):
    """5.2-46 mm straddles one power of ten: its only major label is 10, so the minor ticks are labelled too."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from spadscan.sweep.plot import _panel
    from spadscan.sweep.results import SweepResults

    rows = [{"scene": "s", "axis": "views", "views": str(v), "fast_status": "done", "fast_chamfer_mm": str(c)}
            for v, c in ((8, high), (16, (low * high) ** 0.5), (32, low))]
    results = SweepResults(folder=tmp_path, mode="one-at-a-time", grid={"views": [8, 16, 32]}, base={"views": 16},
                           scenes=["s"], methods=["fast"], presets=["fast"], rows=rows)
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    _panel(ax, results, rows, "views", 0)
    fig.canvas.draw()
    bottom, top = ax.get_ylim()
    ticks = [*zip(ax.yaxis.get_majorticklocs(), ax.yaxis.get_majorticklabels()),
             *zip(ax.yaxis.get_minorticklocs(), ax.yaxis.get_minorticklabels())]
    labelled = {round(v, 6) for v, label in ticks if bottom <= v <= top and label.get_text()}
    assert len(labelled) >= 2, (bottom, top, sorted(labelled))


def test_scenes_whose_safe_names_coincide_get_pictures_of_their_own():
    import re

    from spadscan.sweep.figure_a import picture_name

    scenes = ["a/b.obj", "a_b.obj", 'cup<b>&"v2".ply', "cup_b_v2_.ply"]
    names = [picture_name(scene, scenes) for scene in scenes]
    assert len(set(names)) == len(scenes), names
    assert all(re.fullmatch(r"figure_a-\d+-[A-Za-z0-9_.-]+\.png", name) for name in names), names


def _power_panel(tmp_path):
    """A panel whose Chamfer values span 13.5-280 mm, where two of three methods failed at the low power."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from spadscan.sweep.plot import _panel
    from spadscan.sweep.results import SweepResults

    rows = [{"scene": "s", "axis": "power", "power": "1e-07", "fast_status": "done", "fast_chamfer_mm": "280",
             "reprojection_status": "failed", "space_carving_status": "failed"},
            {"scene": "s", "axis": "power", "power": "1", "fast_status": "done", "fast_chamfer_mm": "13.5",
             "reprojection_status": "done", "reprojection_chamfer_mm": "23.6",
             "space_carving_status": "done", "space_carving_chamfer_mm": "34.8"}]
    results = SweepResults(folder=tmp_path, mode="one-at-a-time", grid={"power": [1e-7, 1.0]}, base={"power": 1.0},
                           scenes=["s"], methods=["fast", "reprojection", "space-carving"], presets=["fast"],
                           rows=rows)
    fig = Figure(figsize=(3.6, 3.6))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    _panel(ax, results, rows, "power", 0)
    fig.tight_layout()
    fig.canvas.draw()
    return fig, ax


def test_a_chamfer_axis_over_more_than_a_decade_has_labels_that_do_not_overlap(tmp_path):
    fig, ax = _power_panel(tmp_path)
    renderer = fig.canvas.get_renderer()
    bottom, top = ax.get_ylim()
    labels = sorted(((t.get_window_extent(renderer), t.get_text())
                     for t in ax.yaxis.get_majorticklabels() + ax.yaxis.get_minorticklabels()
                     if t.get_text() and bottom <= t.get_position()[1] <= top), key=lambda b: b[0].y0)
    assert len(labels) >= 2
    overlapping = [(a[1], b[1]) for a, b in zip(labels, labels[1:]) if a[0].overlaps(b[0])]
    assert not overlapping


def test_failure_crosses_sit_above_every_value_where_no_value_is_labelled(tmp_path):
    _, ax = _power_panel(tmp_path)
    crosses = [line for line in ax.get_lines() if line.get_marker() == "x"]
    assert len(crosses) == 2
    to_data = ax.transData.inverted()
    for line in crosses:
        (x,), (y,) = line.get_data()
        _, y_data = to_data.transform(line.get_transform().transform((x, y)))
        assert y_data > 280.0 * 1.05, y_data  # above the largest value drawn, not among the values
        labels = [t.get_text() for t in ax.yaxis.get_majorticklabels() + ax.yaxis.get_minorticklabels()
                  if t.get_text() and t.get_position()[1] >= y_data / 1.2]
        assert not labels, labels


def _panel_of(tmp_path, axis: str, values: list, chamfers: list):
    """The panel of one axis drawn from rows of the fast method's Chamfer distances (None: failed there)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from spadscan.sweep.plot import _panel
    from spadscan.sweep.results import SweepResults

    rows = [{"scene": "s", "axis": axis, axis: str(v), "fast_status": "failed" if c is None else "done",
             "fast_chamfer_mm": "" if c is None else str(c)} for v, c in zip(values, chamfers)]
    results = SweepResults(folder=tmp_path, mode="one-at-a-time", grid={axis: values}, base={axis: values[1]},
                           scenes=["s"], methods=["fast"], presets=["fast"], rows=rows)
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    _panel(ax, results, rows, axis, 0)
    fig.canvas.draw()
    return ax


def test_a_linear_parameter_from_zero_gets_a_linear_axis(tmp_path):
    """Elevations 0-60 degrees drew on a symlog axis, linear to 15 and logarithmic above (equal steps squeezed
    against the right edge); ambient light from none keeps it, a log parameter of its own."""
    assert _panel_of(tmp_path, "min_elevation_deg", [0.0, 15.0, 30.0, 45.0, 60.0], [3, 2, 2, 2, 3]).get_xscale() \
        == "linear"
    assert _panel_of(tmp_path, "ambient", [0.0, 1e-4, 1e-3], [2, 2, 3]).get_xscale() == "symlog"


def test_a_panel_where_every_method_failed_has_a_log_axis_without_negative_values(tmp_path):
    ax = _panel_of(tmp_path, "power", [1e-6, 1.0, 100.0], [None, None, None])
    assert ax.get_yscale() == "log"
    bottom, top = ax.get_ylim()
    assert 0 < bottom < top, (bottom, top)
    assert len([line for line in ax.get_lines() if line.get_marker() == "x"]) == 1
