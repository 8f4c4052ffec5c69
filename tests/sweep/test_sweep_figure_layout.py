"""Figure A's layout: its title, legend and labels lie inside the saved picture however many panels it has, and each
panel's Chamfer axis carries labels at or beyond both ends of its values."""

from __future__ import annotations

import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.text import Text

from spadscan.cli import main
from spadscan.sweep.plot import figure, figure_png
from spadscan.sweep.results import SweepResults

from test_sweep_store import _finished

AXES = {"views": [8, 16, 32], "power": [0.1, 1.0, 10.0], "bin_ps": [8.0, 16.0, 33.0], "fov_deg": [10.0, 30.0],
        "cycles": [1000, 5000, 20000]}
BASE = {"views": 16, "power": 1.0, "bin_ps": 16.0, "fov_deg": 30.0, "cycles": 5000}
METHODS = ["fast", "paper", "reprojection", "space-carving"]
CHAMFER = {"fast": 5.47, "paper": 3.1, "reprojection": 18.0, "space-carving": 39.9}
"""The Chamfer distances (mm) of the tiny one-axis sweep that clipped its picture: 5.5 and 40-43 mm."""


def results(tmp_path, n_axes: int, methods=("fast", "space-carving"), scene="builtin:sphere") -> SweepResults:
    """A one-at-a-time sweep of `n_axes` parameters whose Chamfer grows along each axis (the last point failed for
    reprojection, when it is a method)."""
    grid = dict(list(AXES.items())[:n_axes])
    rows = []
    for axis, values in grid.items():
        for i, value in enumerate(values):
            row = {"scene": scene, "axis": axis, axis: str(value)}
            for method in methods:
                key = method.replace("-", "_")
                if method == "reprojection" and i == len(values) - 1:
                    row[f"{key}_status"] = "failed"
                else:
                    row[f"{key}_status"] = "done"
                    row[f"{key}_chamfer_mm"] = str(CHAMFER[method] * (1 + 0.04 * i))
            rows.append(row)
    return SweepResults(folder=tmp_path, mode="one-at-a-time", grid=grid, base={k: BASE[k] for k in grid},
                        scenes=[scene], methods=list(methods),
                        presets=[m for m in methods if m in ("fast", "paper")], rows=rows)


def drawn(fig):
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def texts_drawn(fig, monkeypatch) -> list[Text]:
    """The texts that drawing `fig` draws (not, say, the label of a tick outside its axis's limits)."""
    seen = []
    draw = Text.draw

    def recording(self, renderer):
        if self.get_visible() and self.get_text():
            seen.append(self)
        return draw(self, renderer)

    monkeypatch.setattr(Text, "draw", recording)
    drawn(fig)
    return seen


@pytest.mark.parametrize("n_axes", [1, 2, 3, 5])
@pytest.mark.parametrize("methods", [("fast", "space-carving"), tuple(METHODS)])
def test_every_text_of_the_figure_lies_inside_its_picture(tmp_path, monkeypatch, n_axes, methods):
    fig = figure(results(tmp_path, n_axes, methods), "builtin:sphere")
    texts = texts_drawn(fig, monkeypatch)
    renderer = fig.canvas.get_renderer()
    canvas = fig.bbox
    assert any("Chamfer distance against each imaging parameter" in t.get_text() for t in texts)
    assert any(t.get_text() == "failed (no result)" for t in texts)
    outside = []
    for text in texts:
        box = text.get_window_extent(renderer)
        if box.x0 < canvas.x0 - 0.5 or box.x1 > canvas.x1 + 0.5 or box.y0 < canvas.y0 - 0.5 or \
                box.y1 > canvas.y1 + 0.5:
            outside.append((text.get_text(), box.bounds, canvas.bounds))
    assert not outside, outside


def test_a_long_scene_name_widens_the_picture_to_hold_the_title(tmp_path):
    scene = "/home/lab/scans/2026-12-05/a rather long folder name/teapot_with_handle_and_lid.obj"
    fig = figure(results(tmp_path, 1, scene=scene), scene)
    renderer = drawn(fig)
    title = next(t for t in fig.texts if scene in t.get_text())
    box = title.get_window_extent(renderer)
    assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1, (box.bounds, fig.bbox.bounds)


def test_the_saved_picture_is_the_figure_that_was_laid_out(tmp_path):
    """figure_png saves the canvas as laid out (nothing cropped or added when saving)."""
    import matplotlib.image

    data = results(tmp_path, 1)
    fig = figure(data, "builtin:sphere")
    path = figure_png(data, "builtin:sphere", tmp_path / "figure_a.png")
    height, width = matplotlib.image.imread(path).shape[:2]
    assert (width, height) == pytest.approx((fig.get_figwidth() * 110, fig.get_figheight() * 110), abs=1)


@pytest.mark.parametrize("n_axes", [1, 3])
def test_each_chamfer_axis_is_labelled_at_or_beyond_both_ends_of_its_values(tmp_path, n_axes):
    data = results(tmp_path, n_axes)
    fig = figure(data, "builtin:sphere")
    drawn(fig)
    values = [float(v) for r in data.rows for k, v in r.items() if k.endswith("_chamfer_mm")]
    for ax in [a for a in fig.axes if a.get_visible()]:
        bottom, top = ax.get_ylim()
        ticks = [*zip(ax.yaxis.get_majorticklocs(), ax.yaxis.get_majorticklabels()),
                 *zip(ax.yaxis.get_minorticklocs(), ax.yaxis.get_minorticklabels())]
        labelled = sorted(v for v, label in ticks if bottom * 0.9999 <= v <= top * 1.0001 and label.get_text())
        assert labelled and labelled[0] <= min(values) and labelled[-1] >= max(values), (labelled, bottom, top)


def test_sweep_plot_of_a_one_axis_sweep_writes_the_picture(tmp_path, capsys):
    """The command end to end on a folder such as a one-axis `spadscan sweep` leaves (made-up results)."""
    sweep = tmp_path / "one.toml"
    sweep.write_text('[sweep]\nscenes = ["builtin:sphere"]\npresets = ["fast"]\nbaselines = ["space-carving"]\n'
                     '[base]\nviews = 16\n[grid]\nviews = [16, 24]\n')
    _finished(tmp_path, sweep)
    assert main(["sweep-plot", str(tmp_path / "out")]) == 0
    assert "figure_a.png" in capsys.readouterr().out
    assert (tmp_path / "out" / "figure_a.png").stat().st_size > 10_000
