"""Returns -> transients: splat ranged returns onto a fine time axis, convolve with the pulse, integrate to bins.

The fine axis holds `oversample` cells per bin and `pad` extra bins on either side of the histogram, so that a pulse
that arrives just before bin 0 (its tail) or just after the last bin (its leading edge) still adds what it should.
A return at bin coordinate t is split linearly between the two nearest fine-cell centres, which keeps its mean arrival
time exact to well under a bin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FineAxis:
    """An oversampled time axis: fine cell j covers bin coordinates [j / oversample - pad, (j + 1) / oversample - pad).
    """

    n_bins: int
    oversample: int
    pad: int

    @property
    def n_fine(self) -> int:
        return (self.n_bins + 2 * self.pad) * self.oversample

    def splat(self, channel: np.ndarray, t_bins: np.ndarray, weight: np.ndarray, n_channels: int) -> np.ndarray:
        """Accumulate returns into (n_channels, n_fine).

        channel: (H,) int index of the histogram each return belongs to; t_bins: (H,) arrival bin coordinates;
        weight: (H,) contribution. Returns arriving outside the padded axis are dropped.
        """
        u = (t_bins + self.pad) * self.oversample - 0.5
        j0 = np.floor(u)
        frac = u - j0
        j0 = j0.astype(np.int64)
        out = np.zeros(n_channels * self.n_fine)
        for j, w in ((j0, weight * (1.0 - frac)), (j0 + 1, weight * frac)):
            ok = (j >= 0) & (j < self.n_fine)
            out += np.bincount(channel[ok] * self.n_fine + j[ok], weights=w[ok], minlength=out.size)
        return out.reshape(n_channels, self.n_fine)

    def to_bins(self, fine: np.ndarray) -> np.ndarray:
        """Integrate (..., n_fine) back to (..., n_bins), dropping the padding."""
        per_bin = fine.reshape(*fine.shape[:-1], self.n_bins + 2 * self.pad, self.oversample).sum(axis=-1)
        return per_bin[..., self.pad: self.pad + self.n_bins]


def convolve_pulse(fine: np.ndarray, kernel: np.ndarray, origin: int) -> np.ndarray:
    """Convolve (..., F) with a causal-or-not kernel whose index `origin` is the arrival time (FFT, same length F)."""
    f = fine.shape[-1]
    size = f + kernel.size - 1
    nfft = 1 << (size - 1).bit_length()
    spec = np.fft.rfft(fine, nfft, axis=-1) * np.fft.rfft(kernel, nfft)
    out = np.fft.irfft(spec, nfft, axis=-1)[..., origin: origin + f]
    return np.maximum(out, 0.0)  # FFT round-off can dip below zero by ~1e-17 of the peak


def pulse_pad_bins(kernel: np.ndarray, origin: int, oversample: int) -> int:
    """Bins of padding so that any part of the pulse that can reach the histogram is on the axis."""
    return int(np.ceil(max(origin, kernel.size - origin) / oversample)) + 2
