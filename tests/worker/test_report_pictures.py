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


@pytest.mark.parametrize("trace", [LOSS_TRACE, CHAMFER_TRACE])
def test_the_title_and_the_axis_labels_stay_inside_the_picture(trace):
    """A paper run whose checkpoints went unscored had its long title and its x label (the axes widest without a
    second y axis) cut at the picture's edges."""
    title = "paper: error against run time (checkpoint Chamfer: 96-cell mesh, 30,000 points; coarser than the final)"
    fig = pictures.error_vs_time_figure(trace, title)
    fig.canvas.draw()
    box = fig.bbox
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        for text in (ax.title, ax.xaxis.label, ax.yaxis.label):
            if text.get_text():
                extent = text.get_window_extent(renderer)
                assert box.x0 <= extent.x0 and extent.x1 <= box.x1, text.get_text()


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


@pytest.mark.usefixtures("draws_off_screen")
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


def sphere(center, radius=0.05):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    mesh.apply_translation(center)
    return mesh


def drawn(panel: np.ndarray) -> np.ndarray:
    """Mask of a panel's pixels that are not the white background."""
    return (255 - panel.astype(int)).max(axis=2) > 12


@pytest.mark.usefixtures("draws_off_screen")
def test_the_preview_shows_the_reconstruction_where_it_is_and_the_ground_truth_below_it(tmp_path):
    import matplotlib.image

    px = 96
    # The reconstruction stands 10 cm above the ground truth: at one scale, it must show higher in every side view.
    path = pictures.preview_png(sphere((0, 0, 0.1)), tmp_path / "preview.png", gt=sphere((0, 0, 0)), pixels=px)
    image = (matplotlib.image.imread(path)[..., :3] * 255).astype(np.uint8)
    assert image.shape[:2] == (2 * px, 4 * px)
    for col, (az, el) in enumerate(pictures.VIEWS):
        recon, truth = (drawn(image[r * px:(r + 1) * px, col * px:(col + 1) * px]) for r in (0, 1))
        assert recon.mean() > 0.02 and truth.mean() > 0.02, (az, el)  # both drawn, shaded, in every panel
        assert not recon[:, :3].any() and not recon[:, -3:].any(), (az, el)  # framed: nothing cut at the sides
        if el < 80:
            rows = np.arange(px)[:, None]
            recon_y, truth_y = (float((rows * m).sum() / m.sum()) for m in (recon, truth))
            assert recon_y < truth_y - 0.1 * px, (az, el, recon_y, truth_y)


@pytest.mark.usefixtures("draws_off_screen")
def test_the_preview_without_ground_truth_is_one_row(tmp_path):
    import matplotlib.image

    path = pictures.preview_png(sphere((0, 0, 0)), tmp_path / "preview.png", pixels=64)
    assert matplotlib.image.imread(path).shape[:2] == (64, 4 * 64)


def test_a_machine_that_cannot_draw_off_screen_gets_a_warning_and_no_picture(tmp_path, monkeypatch, capsys):
    from spadscan.worker.report import offscreen

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(offscreen.ctypes.util, "find_library", lambda name: None)
    assert pictures.preview_png(sphere((0, 0, 0)), tmp_path / "preview.png") is None
    assert not (tmp_path / "preview.png").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no preview.png" in err[0] and "libegl1" in err[0] and "libosmesa6" in err[0]


def test_log_axes_for_error_against_time():
    fig = pictures.error_vs_time_figure(CHAMFER_TRACE)
    assert fig.axes[0].get_xscale() == "log" and fig.axes[0].get_yscale() == "log"
    (line,) = fig.axes[0].get_lines()
    assert list(line.get_xdata()) == [2.0, 4.0]  # the checkpoint at 0 s has no place on a log axis
    assert "0 s is off this log axis" in fig.axes[0].get_xlabel()


def red(panel: np.ndarray) -> np.ndarray:
    """Mask of a panel's pixels in the coverage picture's red (seen by no view), shaded."""
    r, g, b = (panel[..., k].astype(int) for k in range(3))
    return (r > 60) & (r > 2 * g) & (r > 2 * b)


@pytest.mark.usefixtures("draws_off_screen")
def test_the_coverage_picture_shows_in_red_what_no_view_sees(tmp_path):
    from spadscan.worker.report import mesh_pictures

    # A sphere whose lower half no view sees: red from below, none from above, none from the side's upper half.
    mesh = sphere((0, 0, 0))
    views = np.where(mesh.vertices[:, 2] < 0, 0, 7)
    px = 96
    image = mesh_pictures.coverage_panels(mesh, views, pixels=px)
    assert image.shape[:2] == (px, px * len(mesh_pictures.COVERAGE_VIEWS))
    panels = {view: image[:, c * px:(c + 1) * px] for c, view in enumerate(mesh_pictures.COVERAGE_VIEWS)}
    assert red(panels[(30.0, -50.0)]).mean() > 0.1, "from below: the unseen half"
    assert not red(panels[(0.0, 89.0)]).any(), "from above: all seen"
    side = panels[(30.0, 25.0)]
    assert red(side[: px // 3]).sum() == 0 and red(side[px // 2:]).sum() > 0, "from the side: red only below"
    path = pictures.coverage_png(mesh, views, tmp_path / "coverage.png", area_views=np.array([0, 0, 5, 9]), pixels=48)
    assert path.read_bytes().startswith(b"\x89PNG")


@pytest.mark.usefixtures("draws_off_screen")
def test_an_underside_that_the_share_leaves_out_is_grey_not_red():
    """The legend's shares leave the undersides out (no view from above a table sees them, and none is owed): drawn
    red, a sphere's unseen bottom read as a gap the legend's 0 % denied."""
    from spadscan.worker.report import mesh_pictures

    mesh = sphere((0, 0, 0))
    views = np.where(mesh.vertices[:, 2] < 0, 0, 7)
    px = 96
    bottom = mesh.vertex_normals[:, 2] < -0.7
    c = mesh_pictures.COVERAGE_VIEWS.index((30.0, -50.0))

    def from_below(image):
        return image[:, c * px:(c + 1) * px]

    below = from_below(mesh_pictures.coverage_panels(mesh, views, pixels=px, underside=bottom))
    r, g, b = (below[..., k].astype(int) for k in range(3))
    grey = (abs(r - g) < 12) & (abs(g - b) < 12) & (r > 20) & (r < 140)
    assert grey.mean() > 0.05, "the bottom grey"
    all_red = red(from_below(mesh_pictures.coverage_panels(mesh, views, pixels=px))).mean()
    assert red(below).mean() < 0.75 * all_red, "the unseen side that is no underside stays red, the bottom does not"


@pytest.mark.usefixtures("draws_off_screen")
def test_the_coverage_picture_legend_gives_each_class_its_share(tmp_path, saved_legends):
    mesh = sphere((0, 0, 0))
    pictures.coverage_png(mesh, np.zeros(len(mesh.vertices), int), tmp_path / "c.png",
                          area_views=np.array([0, 1, 2, 3, 4, 5, 6, 7]), pixels=32)
    assert saved_legends == [["seen by no view: 12%", "seen by 1-2 views: 25%", "seen by 3 or more views: 62%",
                              "underside: not counted"]]


@pytest.mark.usefixtures("draws_off_screen")
def test_a_surface_is_shaded_by_its_own_normals_as_smooth_shading_would():
    """offscreen.add_shaded draws a mesh as pyvista's smooth shading does (the normals computed once, from the
    mesh, not anew for each panel), and unlike flat shading."""
    import trimesh

    from spadscan.worker.report import offscreen

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.05)  # coarse: flat facets show
    data = offscreen.polydata(mesh)
    np.testing.assert_allclose(data.point_data.active_normals, mesh.vertex_normals)

    def image(add) -> np.ndarray:
        pl = offscreen.plotter((1, 1), (96, 96))
        try:
            add(pl)
            offscreen.set_view(pl, np.zeros(3), 0.06, 30.0, 25.0)
            return pl.screenshot(return_img=True).astype(float)
        finally:
            pl.close()

    ours = image(lambda pl: offscreen.add_shaded(pl, data, color="white"))
    smooth = image(lambda pl: pl.add_mesh(offscreen.polydata(mesh), smooth_shading=True, color="white"))
    flat = image(lambda pl: pl.add_mesh(offscreen.polydata(mesh), color="white"))
    assert np.abs(ours - smooth).mean() < 0.25 * np.abs(flat - smooth).mean()
