"""The report's pictures say what they plot: loss alone without a Chamfer, per-vertex normal error by name, and log
axes with readable numbers."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.worker.report import pictures

CHAMFER_TRACE = [{"step": 0, "seconds": 0.0, "loss": None, "chamfer_mm": 44.0},
                 {"step": 5, "seconds": 2.0, "loss": 38.0, "chamfer_mm": 40.0},
                 {"step": 9, "seconds": 4.0, "loss": 12.0, "chamfer_mm": 30.0}]
LOSS_TRACE = [{k: v for k, v in p.items() if k != "chamfer_mm"} for p in CHAMFER_TRACE]


def tick_labels(axis) -> list[str]:
    """The labels drawn on an axis's major and minor ticks (empty ones left out)."""
    axis.figure.canvas.draw()
    return [t.get_text() for t in axis.get_ticklabels() + axis.get_ticklabels(minor=True) if t.get_text()]


@pytest.fixture(autouse=True)
def close_figures():
    yield
    pictures._plt().close("all")


def test_a_loss_only_plot_is_titled_loss_against_run_time():
    fig = pictures.error_vs_time_figure(LOSS_TRACE, "fast: error against run time")
    assert fig.axes[0].get_title() == "fast: loss against run time (no checkpoint Chamfer)"
    assert pictures.error_vs_time_figure(LOSS_TRACE).axes[0].get_title().startswith("loss against run time")


def test_a_plot_with_chamfer_keeps_its_title():
    fig = pictures.error_vs_time_figure(CHAMFER_TRACE, "fast: error against run time")
    assert fig.axes[0].get_title() == "fast: error against run time"


def test_checkpoints_whose_chamfer_failed_count_as_no_chamfer():
    trace = [dict(p, chamfer_mm=None) for p in CHAMFER_TRACE]
    assert "loss against run time" in pictures.error_vs_time_figure(trace).axes[0].get_title()


@pytest.mark.parametrize("trace", [LOSS_TRACE, CHAMFER_TRACE])
def test_log_loss_axis_reads_plain_numbers(trace):
    loss_axis = pictures.error_vs_time_figure(trace).axes[-1].yaxis
    labels = tick_labels(loss_axis)
    assert labels and "20" in labels, labels
    for label in labels:
        assert "times" not in label and "^" not in label, labels
        float(label)


def test_a_loss_axis_over_many_decades_keeps_one_scientific_form():
    trace = [{"seconds": float(i), "loss": 10.0 ** -i} for i in range(9)]
    labels = tick_labels(pictures.error_vs_time_figure(trace).axes[0].yaxis)
    assert labels and all("10^" in label for label in labels), labels


def test_the_saved_plot_is_a_png(tmp_path):
    path = pictures.error_vs_time_png(LOSS_TRACE, tmp_path / "e.png", "fast: error against run time")
    assert path.read_bytes().startswith(b"\x89PNG")


def test_the_normals_picture_names_its_per_vertex_measure(tmp_path, monkeypatch):
    import matplotlib.figure
    import trimesh

    titles = []
    save = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda fig, *a, **k: (titles.append(fig.get_suptitle()), save(fig, *a, **k))[1])
    mesh = trimesh.creation.icosphere(subdivisions=1)
    err = np.linspace(0.0, 40.0, len(mesh.vertices))
    pictures.normals_png(mesh, err, tmp_path / "n.png", pixels=32)
    assert titles == [pictures.normals_title(err)]
    assert titles[0].startswith("per-vertex normal error") and "mean 20.0 deg, median 20.0 deg" in titles[0]
