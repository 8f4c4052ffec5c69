"""The table under a measured object: found in the histograms however much of each view the object fills."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import elevation_rings
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.sim_table import SimTable
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.table_height import last_peaks


def _histograms(rng, n: int, bright_at: int, faint_at: int | None, faint_share: float, bins: int = 128):
    """n Poisson histograms (n, 1, bins) over 20,000 cycles: a bright return at `bright_at` with a 6-bin exponential
    tail, and optionally a faint return `faint_share` of its height at `faint_at`; background 2e-4 per bin."""
    b = np.arange(bins, dtype=float)
    rate = np.full(bins, 2e-4)
    rate += 0.3 * np.where(b >= bright_at, np.exp(-(b - bright_at) / 6.0), 0.0)
    rate += 0.3 * np.exp(-0.5 * ((b - bright_at) / 1.2) ** 2)
    if faint_at is not None:
        rate += faint_share * 0.6 * np.exp(-0.5 * ((b - faint_at) / 1.2) ** 2)
    cycles = 20000.0
    counts = rng.poisson(rate * cycles, size=(n, 1, bins)).astype(float)
    return counts, np.full(n, cycles), np.full((n, 1), 2e-4)


def test_a_faint_return_behind_a_bright_one_is_the_last_peak():
    rng = np.random.default_rng(0)
    counts, cycles, background = _histograms(rng, 50, bright_at=30, faint_at=90, faint_share=0.01)
    # 1% of the bright peak: under the old threshold of 5% of the highest peak, yet ~15 sigmas above the noise
    last = last_peaks(counts, cycles, background)
    assert (np.abs(last - 90) <= 1).all(), np.unique(last)


def test_the_tail_of_a_bright_return_is_no_peak_of_its_own():
    rng = np.random.default_rng(1)
    counts, cycles, background = _histograms(rng, 500, bright_at=30, faint_at=None, faint_share=0.0)
    last = last_peaks(counts, cycles, background)
    assert (np.abs(last - 30) <= 1).all(), np.unique(last)


@pytest.fixture(scope="module")
def tall_on_dark_table(tmp_path_factory):
    """A white 0.40 m column topped by a 0.2 m ball on a black table (albedo 0.02) at z = 0.05 m, seen from 0.35 m
    by the TMF8820 model on rings looking at mid-height: the object fills most zones of most views."""
    column = trimesh.creation.cylinder(radius=0.04, height=0.30, sections=48).apply_translation([0, 0, 0.20])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.08).apply_translation([0, 0, 0.40])
    mesh = trimesh.util.concatenate([column, ball])
    poses = elevation_rings(4, 8, 0.35, target=(0.0, 0.0, 0.30), min_elevation_deg=36, max_elevation_deg=80)
    path = tmp_path_factory.mktemp("dark_table") / "tall"
    simulate_capture(mesh, sensor_preset("tmf8820"), poses, path, settings=SimSettings(rays_per_zone=256), seed=4,
                     progress=False, table=SimTable(0.05, 0.02, 1.0))
    return path


def test_a_black_table_under_a_tall_white_object_is_found(tall_on_dark_table):
    from spadscan.worker.recon.fast.problem import _table_plane
    from spadscan.worker.recon.scene_data import load_scene

    scene = load_scene(tall_on_dark_table)
    normal, offset, fitted, source = _table_plane(scene, scene.pulse(1))
    assert source == "detected, then fitted" and fitted
    assert offset == pytest.approx(0.05, abs=0.01)


def test_the_hull_of_a_tall_object_reaches_down_to_its_table(tall_on_dark_table):
    from spadscan.worker.recon.fast.config import fast_config
    from spadscan.worker.recon.fast.problem import build_problem
    from spadscan.worker.recon.forward import choose_terms
    from spadscan.worker.recon.scene_data import load_scene

    scene = load_scene(tall_on_dark_table)
    problem = build_problem(scene, fast_config(), "cpu", choose_terms(scene))
    # the column stands on the table at z = 0.05 m; the scene sphere, centred on the first returns, stops above it
    assert float(scene.box[0, 2]) > 0.08
    assert problem.floor_z == pytest.approx(0.05, abs=0.01)
    assert problem.box[0][2] < 0.06


@pytest.mark.parametrize("candidate_rays_per_sr", [2000.0, None])
def test_a_table_a_wide_zone_sees_at_a_slant_is_found_whatever_rays_the_fit_uses(table_capture, candidate_rays_per_sr):
    # 12 views of a cylinder on a slab (top at z = 0) through one 30 degree wide zone: the slab's return is a broad
    # ramp whose peak only rays spread over the whole zone place right. The fit's own candidate rays, thinned by a
    # stride, lay on one arm of their spiral: at 2000 per sr the table was missed and put at the scene data's start,
    # 6 cm up, at the cylinder's top.
    from spadscan.worker.recon.config import with_overrides
    from spadscan.worker.recon.fast.problem import build_problem
    from spadscan.worker.recon.forward import choose_terms
    from spadscan.worker.recon.presets import preset_config
    from spadscan.worker.recon.scene_data import load_scene

    config = preset_config("fast")
    if candidate_rays_per_sr is not None:
        config = with_overrides(config, {"schedule.candidate_rays_per_sr": candidate_rays_per_sr})
    scene = load_scene(table_capture)
    problem = build_problem(scene, config, "cpu", choose_terms(scene))
    assert problem.floor_z == pytest.approx(0.0, abs=0.01)


def test_histograms_left_out_for_a_corrupt_bin_do_not_move_the_table(tall_on_dark_table, tmp_path):
    # A converter that wrote -1 as unsigned: three bins of a third of the histograms at 2^32 - 1, over the 24-bit
    # counter's limit. Those histograms are left out of the fit, and must be left out of the table's search too:
    # their spurious peak read as the farthest surface put the table 18 cm under the real one.
    import shutil

    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.worker.baselines.floor import measured_table_height
    from spadscan.worker.recon.fast.problem import _table_plane
    from spadscan.worker.recon.scene_data import load_scene

    corrupt = tmp_path / "corrupt"
    shutil.copytree(tall_on_dark_table, corrupt)
    hists_file = sorted(corrupt.glob("chunk-*"))[0] / "hists.npy"
    hists = np.load(hists_file)
    n = len(hists) // 3
    hists[:n, :, 60:63] = 2**32 - 1
    np.save(hists_file, hists)

    scene = load_scene(corrupt)
    assert int((~scene.usable).sum()) == n * hists.shape[1]  # every one of them left out
    _, offset, _, source = _table_plane(scene, scene.pulse(1))
    assert source == "detected, then fitted" and offset == pytest.approx(0.05, abs=0.01)
    assert scene.table.offset > 0.0  # the scene data's own start: at the returns, not under the spurious peak
    assert measured_table_height(CaptureReader(corrupt).load()) == pytest.approx(0.05, abs=0.01)  # the baselines'
