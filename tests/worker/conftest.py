"""Fixtures shared by the worker's tests."""

from __future__ import annotations

import os

import matplotlib.figure
import pytest


@pytest.fixture
def draws_off_screen(monkeypatch):
    """Skips the test, saying why and what to install, on a machine that cannot draw meshes off screen (no display,
    no EGL, no OSMesa): the product's own check decides."""
    from spadscan.worker.report.offscreen import OffscreenUnavailable, check_offscreen

    # The check sets this variable to pick VTK's window: noted with monkeypatch, it is put back after the test.
    name = "VTK_DEFAULT_OPENGL_WINDOW"
    if name in os.environ:
        monkeypatch.setenv(name, os.environ[name])
    else:
        monkeypatch.delenv(name, raising=False)
    try:
        check_offscreen()
    except OffscreenUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture
def one_thread():
    """One torch thread: the test machine's cores are shared, and oversubscribed threads only spin."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def cylinder_capture(tmp_path_factory):
    """24 simulated views of worker_helpers.cylinder_mesh from 0.3 m (LCSPCData's simulated sensor)."""
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    from worker_helpers import cylinder_mesh

    path = tmp_path_factory.mktemp("cylinder") / "cyl"
    poses = fibonacci_hemisphere(24, 0.3, target=(0, 0, 0.03), min_elevation_deg=5)
    simulate_capture(cylinder_mesh(), sensor_preset("lcspc-sim"), poses, path,
                     settings=SimSettings(rays_per_zone=1024), seed=3, progress=False)
    return path


@pytest.fixture(scope="module")
def table_capture(tmp_path_factory):
    """12 simulated views of a cylinder standing on a wide slab whose top is the table (z = 0)."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    from worker_helpers import cylinder_mesh

    slab = trimesh.creation.box([0.6, 0.6, 0.02])
    slab.apply_translation([0.0, 0.0, -0.01])
    path = tmp_path_factory.mktemp("fast") / "table"
    poses = fibonacci_hemisphere(12, 0.3, target=(0, 0, 0.03), min_elevation_deg=35)
    simulate_capture(trimesh.util.concatenate([cylinder_mesh(), slab]), sensor_preset("lcspc-sim"), poses, path,
                     settings=SimSettings(rays_per_zone=512), seed=5, progress=False, scene={"table": True})
    return path


@pytest.fixture
def recon_stand_ins(monkeypatch):
    """Job child processes can import the stand-in reconstructions that live beside the tests (RECON strings like
    'test_worker_process:options_recon'): this folder and the tests' own (the helpers those modules import) go on
    their PYTHONPATH."""
    import os
    from pathlib import Path

    here = str(Path(__file__).resolve().parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([here, str(Path(here).parent), os.environ.get("PYTHONPATH", "")]))


@pytest.fixture
def saved_legends(monkeypatch):
    """The legend texts of every matplotlib figure saved during the test, one list per figure (a picture's legend
    states what it counts; the PNG alone does not let a test read it)."""
    legends = []
    save = matplotlib.figure.Figure.savefig

    def keep_legend(fig, *args, **kwargs):
        legends.append([t.get_text() for t in fig.axes[0].get_legend().get_texts()])
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep_legend)
    return legends
