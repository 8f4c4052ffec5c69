"""The height of the table under a measured object, found in the histograms (numpy only: the baselines use it too).

The table is the farthest surface every zone sees (docs/sensor_models.md: it is in every histogram of a real capture),
so at the right height a horizontal plane's predicted peak falls on each zone's last significant peak and nothing is
ever measured behind it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spadscan.protocol.errors import CaptureError

MIN_RANGE_M = 1e-3
RAYS_PER_ZONE = 48
"""Rays per zone `detect_height` wants: enough to place a plane's peak to a bin; more only cost time."""
PROMINENCE_BINS = 8
"""A peak must rise above the lowest level of this many bins before it (`last_peaks`)."""


@dataclass
class TablePlane:
    """The plane n . x = offset (n unit, pointing into the free half-space); `fitted` = its offset is learned."""

    normal: np.ndarray
    offset: float
    fitted: bool

    def height(self) -> float | None:
        """Height (metres) of a horizontal table, or None when it is tilted."""
        return self.offset / float(self.normal[2]) if abs(float(self.normal[2])) > 0.99 else None


def named_table(spec) -> TablePlane:
    """The table a capture's scene record gives: {"z": h} (horizontal) or {"normal": n, "offset": d}, either with
    "fit": true when its offset is to be learned. A malformed one is a one-line CaptureError (the caller names the
    manifest)."""
    if not isinstance(spec, dict):
        raise CaptureError("scene table must be true or a dict with 'z' or 'normal' and 'offset'")
    fitted = bool(spec.get("fit", False))
    try:
        if "z" in spec:
            return TablePlane(np.array([0.0, 0.0, 1.0]), _finite(spec["z"], "z"), fitted)
        normal = np.asarray(spec.get("normal", (0, 0, 1)), float)
        norm = float(np.linalg.norm(normal))
        if normal.shape != (3,) or not np.isfinite(norm) or norm < 1e-9 or "offset" not in spec:
            raise ValueError("not a plane")
        return TablePlane(normal / norm, _finite(spec["offset"], "offset") / norm, fitted)
    except (TypeError, ValueError):
        raise CaptureError("scene table needs a number 'z', or a non-zero 3-vector 'normal' and an 'offset' in "
                           "metres") from None


def _finite(value, key: str) -> float:
    """`value` as a float; a CaptureError naming scene.table.`key` when it is not finite (scan.json may hold NaN or
    Infinity, which Python's json reads: a table at z = nan left a fit that trained to the end and then failed)."""
    number = float(value)
    if not math.isfinite(number):
        raise CaptureError(f"scene.table.{key} {value!r} must be a finite number of metres")
    return number


def last_peaks(counts: np.ndarray, cycles: np.ndarray, background: np.ndarray, ignore_bins=(),
               window: int = PROMINENCE_BINS) -> np.ndarray:
    """Bin of the last significant peak of every histogram (V, Z), or -1 where there is none.

    counts (V, Z, B); cycles (V,); background (V, Z) per bin per cycle. A peak is a local maximum of the 3-bin mean
    excess rate that stands 5 Poisson sigmas above the background and rises 5 sigmas (of a difference) above the
    lowest 3-bin mean of the `window` bins before it. The rise, not a share of the histogram's highest peak, is what
    tells a return from the falling tail of the one before it: a black table behind a white object returns under 1 %
    of the object's photons and still stands 10-20 sigmas above the noise (a simulated 50 cm head on a can on a
    table of albedo 0.02: a threshold of 5 % of the highest peak saw the table in no zone and put it 22 cm high, at
    the can's top).
    """
    V, Z, B = counts.shape
    excess = counts / cycles[:, None, None] - background[..., None]
    if ignore_bins:
        excess[..., list(ignore_bins)] = 0.0
    sm = excess.copy()
    sm[..., 1:-1] = (excess[..., :-2] + excess[..., 1:-1] + excess[..., 2:]) / 3
    sd = np.sqrt(np.maximum(counts, 1.0)) / cycles[:, None, None] / math.sqrt(3)
    low = sm.copy()
    for k in range(1, int(window) + 1):
        low[..., k:] = np.minimum(low[..., k:], sm[..., :-k])
    significant = (sm > 5 * sd) & (sm - low > 5 * math.sqrt(2) * sd)
    local = np.zeros_like(significant)
    local[..., 1:-1] = (sm[..., 1:-1] >= sm[..., :-2]) & (sm[..., 1:-1] >= sm[..., 2:])
    return np.where(significant & local, np.arange(B), -1).max(axis=-1)


def plane_peak_bins(height: float, poses: np.ndarray, zone_dirs: np.ndarray, zone_weights: np.ndarray, sensor,
                    kernel: np.ndarray, origin: int) -> np.ndarray:
    """Bin (V, Z) where a horizontal plane at `height` alone would put each histogram's peak; -1 if out of view."""
    V, B = len(poses), sensor.n_bins
    dirs = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs)
    down = dirs[..., 2] < -1e-3
    t = (height - poses[:, 2, 3][:, None, None]) / np.where(down, dirs[..., 2], -1.0)
    ok = down & (t > MIN_RANGE_M)
    b = np.floor(sensor.bin_of_range(np.where(ok, t, 0.0))).astype(int)
    good = ok & (b >= 0) & (b < B)
    raw = np.zeros((V, zone_dirs.shape[0], B))
    vi, zi, _ = np.nonzero(good)
    np.add.at(raw, (vi, zi, b[good]), (zone_weights[None] * -dirs[..., 2] / np.maximum(t, MIN_RANGE_M) ** 2)[good])
    lag = np.arange(B)[None, :] - np.arange(B)[:, None] + origin  # conv[b, i] = kernel[origin + i - b]
    conv = np.where((lag >= 0) & (lag < kernel.size), kernel[np.clip(lag, 0, kernel.size - 1)], 0.0)
    pred = raw @ conv
    return np.where(pred.max(axis=-1) > 0, pred.argmax(axis=-1), -1)


def detect_height(counts: np.ndarray, cycles: np.ndarray, background: np.ndarray, poses: np.ndarray,
                  zone_dirs: np.ndarray, zone_weights: np.ndarray, sensor, kernel: np.ndarray, origin: int,
                  *, depth_m: float = 0.6, step_m: float = 0.02, min_score: float = 0.1,
                  ignore_bins=()) -> float | None:
    """Height (metres) of a horizontal table below every sensor, or None when no height explains the data.

    The table is the farthest surface each zone sees: a plane at the right height puts its peak where the zone's
    last significant peak is, and nothing is ever measured behind it. The score of a height is the fraction of zones
    (that would see the plane) whose last peak lies within 1.5 bins of the plane's, less the fraction whose last peak
    lies more than 1.5 bins behind it. Heights from 2 cm below the lowest sensor down `depth_m` are tried every
    `step_m`, then every step_m / 10 around the best. counts (V, Z, B); cycles (V,); background (V, Z);
    poses (V, 4, 4); zone_dirs (Z, D, 3) and zone_weights (Z, D) in the sensor frame, spread evenly over each zone
    (`zone_rays(zones, RAYS_PER_ZONE, seed)`; a stride through a longer list is no such spread: every 8th ray of a
    golden-angle spiral lies on one arm, 20 degrees on from the last, and on a wide zone looking down at a slant put
    the plane's peak up to 10 bins off, so that a table 0.3 m under the sensor was missed); kernel/origin: the pulse.
    """
    last = last_peaks(counts, cycles, background, ignore_bins)
    k = np.asarray(kernel, float)

    def score(h: float) -> float:
        pb = plane_peak_bins(h, poses, zone_dirs, zone_weights, sensor, k, origin)
        m = (pb >= 0) & (last >= 0)
        if not m.any():
            return -1.0
        return float((np.abs(pb - last)[m] <= 1.5).mean() - (last > pb + 1.5)[m].mean())

    top = float(poses[:, 2, 3].min()) - 0.02
    coarse = np.arange(top, top - depth_m, -step_m)
    h0 = float(coarse[int(np.argmax([score(h) for h in coarse]))])
    fine = np.arange(h0 + step_m, h0 - step_m, -step_m / 10)
    scores = [score(h) for h in fine]
    i = int(np.argmax(scores))
    return float(fine[i]) if scores[i] >= min_score else None


__all__ = ["RAYS_PER_ZONE", "TablePlane", "named_table", "detect_height", "last_peaks", "plane_peak_bins"]
