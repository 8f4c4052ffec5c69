"""The `lcspc-sim` preset reproduces LCSPCData's simulated sphere scene from its own poses and ground-truth mesh.

Reads ../shared/datasets/lcspc when it is there (the `lcspc_dataset` fixture skips otherwise, saying why).
"""

import json

import numpy as np
import pytest

from spadscan.protocol.mesh_io import load_mesh
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import Simulator

pytestmark = pytest.mark.dataset


def smoothed_peak(h: np.ndarray, sigma: float) -> np.ndarray:
    """Peak bin of each histogram (n, bins) after Gaussian smoothing as wide as the pulse (against shot noise)."""
    x = np.arange(-int(4 * sigma), int(4 * sigma) + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return np.array([np.convolve(v, k, mode="same").argmax() for v in np.asarray(h, float)])


def load(root, scene):
    data = json.loads((root / "simulated" / scene / f"{scene}.json").read_text())
    hists = np.array([m["hists"] for m in data], dtype=np.float64)
    poses = np.array([m["pose"] for m in data], dtype=np.float64)
    return hists, poses, load_mesh(root / "simulated" / scene / f"{scene}.obj")


def test_sphere_scene_is_reproduced(lcspc_dataset):
    hists, poses, mesh = load(lcspc_dataset, "sphere")
    sensor = sensor_preset("lcspc-sim")
    frames = Simulator(mesh, sensor, seed=0).frames(poses)
    sim = frames.hists[:, 0].astype(np.float64)
    width = np.hypot(sensor.pulse.sigma_bins, sensor.pulse.tau_bins)  # the pulse's standard deviation (bins)
    peak_error = smoothed_peak(sim, width) - smoothed_peak(hists, width)
    count_ratio = sim.sum(axis=1) / hists.sum(axis=1)
    assert np.abs(peak_error).max() <= 2, f"peak bin errors {np.unique(peak_error, return_counts=True)}"
    assert np.abs(count_ratio - 1).max() <= 0.10, f"count ratios {count_ratio.min():.3f}..{count_ratio.max():.3f}"
    # and on average much better than the limits: no bias in time or in brightness
    assert abs(peak_error.mean()) < 0.3 and abs(count_ratio.mean() - 1) < 0.01


def test_returns_hold_the_signal_where_the_dataset_has_it(lcspc_dataset):
    """Beyond peaks and totals: the photons of each view's return, above its background, within a few percent."""
    hists, poses, mesh = load(lcspc_dataset, "sphere")
    sim = Simulator(mesh, sensor_preset("lcspc-sim"), seed=1)
    mu = sim.sensor.cycles * sim.detection_probabilities(sim.expected_rates(poses))[:, 0]
    peak = smoothed_peak(hists, 4.0)

    def return_photons(h):  # a window around the data's peak, minus the background before any return
        lo, hi = np.maximum(peak - 20, 0), np.minimum(peak + 40, h.shape[1])
        return np.array([h[i, a:b].sum() - np.median(h[i, :150]) * (b - a) for i, (a, b) in enumerate(zip(lo, hi))])

    ratio = return_photons(mu) / return_photons(hists)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    assert np.percentile(np.abs(ratio - 1), 90) < 0.06  # photon noise of ~1000-photon returns is ~3%


def test_dataset_poses_are_the_fibonacci_schedule(lcspc_dataset):
    _, poses, _ = load(lcspc_dataset, "sphere")
    ours = fibonacci_hemisphere(256, 0.5, max_elevation_deg=90.0)
    np.testing.assert_allclose(ours[:, :3, 3], poses[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(ours[:, :3, 2], poses[:, :3, 2], atol=1e-6)  # same view directions
