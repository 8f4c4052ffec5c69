"""The sensor model in torch: range binning, pulse, zone gains, crosstalk, background, pile-up and likelihoods.

Units. A *transient* holds, per bin, sum over rays of (ray solid angle) x (albedo / pi) x cos(incidence) / r^2 for
the returns whose range falls in the bin (what `render.render_rays` produces times the ray weights). The rate is
`lambda = signal_scale * pi * gain_z * (transient * pulse) + crosstalk * sum_z' (...) + background` photons per bin
per cycle, so that `signal_scale` keeps the sensor model's meaning (photons per cycle per unit albedo per sr/m^2).

Time axis. Bin i covers bin coordinates [i, i + 1); a return at range r arrives at `zero_bin + r / bin_width_m`.
Returns are splatted onto a fine axis of `oversample` cells per bin, split linearly between the two cells whose
centres bracket the arrival (a scatter-add, never a dense one-hot), convolved with the pulse sampled per fine cell
(`kernel[origin + k]` = the response k fine cells after the arrival), then summed back to bins. The fine axis runs
`pad_lo` bins before bin 0 and `pad_hi` bins after the last one, so that a pulse that starts before or ends after
the recorded window leaks into it as it should. This is the simulator's own scheme (protocol.transient), in torch.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from spadscan.protocol.sensor_model import SensorModel

from .errors import ReconstructionError

PILEUP_THRESHOLD = 0.01
"""Pile-up is modelled when some histogram's detections use more than this fraction of its cycles: bins at the end
of that histogram then read at least this much low."""
RATE_FLOOR = 1e-12
"""Smallest rate (photons per bin per cycle) the likelihoods ever see."""
EXACT_ABOVE_CYCLES = 1e7
"""Cycles of a view past which `nll` evaluates its value again in float64 (see there); below, float32 holds the
deviance to 1e-5 (a test holds it at 4e6, a TMF8820 frame's), and a fit step is spared a second evaluation (2.6x the
likelihood's time on a 1,024-bin view)."""
SHIFTED_SUM_ABOVE = 1e6
"""Running sum of rates (photons per cycle) past which `_before` sums the earlier bins' rates directly instead of
subtracting a bin's own rate from the running sum (float64 rounds that subtraction by 1e-16 of the sum)."""


@dataclass
class ModelTerms:
    """Which parts of the sensor model a reconstruction uses (decided from the capture by `choose_terms`, listed in
    the report). A preset that leaves out what the capture would allow reports its own (the fast preset: no TV, and
    no table where `parts.table` does not run)."""

    pileup: bool
    """First-photon (Coates) pile-up."""
    crosstalk: bool
    """Light leaking between zones (multi-zone sensors)."""
    table: bool
    """A table plane under the object."""
    tv: bool
    """Total-variation (normal smoothness) regulariser (the paper preset, on measured data)."""
    reference_pulse: bool
    """Pulse taken from the capture's reference histograms."""

    def to_dict(self) -> dict:
        return asdict(self)


def choose_terms(scene) -> ModelTerms:
    """Terms for a SceneData: pile-up when the sensor stops at its first photon and some histogram's detections
    exceed PILEUP_THRESHOLD of its cycles; crosstalk for multi-zone sensors with a crosstalk fraction; the table when
    the manifest names one; TV on measured data; the reference pulse when the capture provided it."""
    sensor = scene.sensor
    used = (scene.counts * scene.valid).sum(-1) / scene.cycles[:, None]
    return ModelTerms(
        pileup=bool(sensor.pileup and float(used.max()) > PILEUP_THRESHOLD),
        crosstalk=bool(sensor.n_zones > 1 and sensor.crosstalk > 0),
        table=scene.table is not None,
        tv=bool(scene.real),
        reference_pulse=scene.pulse_source == "reference",
    )


class TransientForward(torch.nn.Module):
    """From rendered returns to per-bin rates and likelihoods, for one sensor model. Z zones, B bins."""

    def __init__(self, sensor: SensorModel, terms: ModelTerms, pulse, pulse_origin: int, oversample: int = 1):
        super().__init__()
        pulse = torch.as_tensor(pulse)
        if pulse.ndim != 1 or pulse.numel() == 0 or not bool(torch.isfinite(pulse).all()) or float(pulse.sum()) <= 0:
            raise ReconstructionError(f"pulse kernel must be a non-empty finite 1-D array, got {tuple(pulse.shape)}")
        if not 0 <= pulse_origin < pulse.numel():
            raise ReconstructionError(f"pulse origin {pulse_origin} lies outside the kernel (0..{pulse.numel() - 1})")
        if not (isinstance(oversample, int) and 1 <= oversample <= 64):
            raise ReconstructionError(f"time oversampling {oversample} must be an integer in [1, 64]")
        self.sensor, self.terms, self.oversample = sensor, terms, oversample
        self.n_bins = sensor.n_bins
        k = pulse.numel()
        self.pad_lo = -(-(k - 1 - pulse_origin) // oversample) + 1  # whole bins
        self.pad_hi = -(-pulse_origin // oversample) + 1
        self.n_fine = (self.n_bins + self.pad_lo + self.pad_hi) * oversample
        self._conv_pad = (k - 1 - pulse_origin, pulse_origin)
        self.register_buffer("kernel", (pulse / pulse.sum()).flip(0).reshape(1, 1, -1).clone())
        self.register_buffer("gain", torch.tensor([z.gain for z in sensor.zones], dtype=pulse.dtype))
        self.power = sensor.signal_scale * math.pi
        self.crosstalk = sensor.crosstalk if terms.crosstalk else 0.0

    # ---- rendering to rates ----------------------------------------------------------------------------------------
    def bin(self, ranges_m: torch.Tensor, radiance: torch.Tensor, hist_id: torch.Tensor, n_hist: int) -> torch.Tensor:
        """Scatter returns into histograms on the fine axis with linear interpolation.

        ranges_m (N,) one-way metres; radiance (N,) weighted returns; hist_id (N,) long in [0, n_hist).
        Returns (n_hist, n_fine) transients (differentiable in radiance and ranges); arrivals off the axis drop out.
        """
        s, os_ = self.sensor, self.oversample
        u = (s.zero_bin + self.pad_lo + ranges_m / s.bin_width_m) * os_ - 0.5
        u = torch.nan_to_num(u, nan=-2.0, posinf=-2.0, neginf=-2.0).clamp(-2.0, self.n_fine + 1.0)
        j = torch.floor(u.detach())
        f = u - j
        j = j.long()
        out = torch.zeros(n_hist * self.n_fine, dtype=radiance.dtype, device=radiance.device)
        base = hist_id.long() * self.n_fine
        for idx, w in ((j, 1.0 - f), (j + 1, f)):
            ok = (idx >= 0) & (idx < self.n_fine)
            out = out.index_add(0, (base + idx.clamp(0, self.n_fine - 1))[ok], (radiance * w)[ok])
        return out.reshape(n_hist, self.n_fine)

    def rates(self, transient: torch.Tensor, background: torch.Tensor | float) -> torch.Tensor:
        """Photon rates per bin per cycle.

        transient: (V, Z, n_fine) from `bin`, or (V, Z, B) per bin (each bin's returns spread evenly over it, zero
        outside the window); background: (V, Z) or a scalar, photons per bin per cycle. Returns lam (V, Z, B),
        everywhere >= RATE_FLOOR.
        """
        v, z, n = transient.shape
        os_ = self.oversample
        if n == self.n_bins:
            transient = (transient / os_).repeat_interleave(os_, dim=-1)
            transient = F.pad(transient, (self.pad_lo * os_, self.pad_hi * os_))
        elif n != self.n_fine:
            raise ReconstructionError(f"transient has {n} bins; expected {self.n_bins} (per bin) or {self.n_fine} "
                                      f"(fine axis)")
        if z != len(self.gain):
            raise ReconstructionError(f"transient has {z} zones; the sensor model has {len(self.gain)}")
        fine = F.pad(transient.reshape(v * z, 1, -1), self._conv_pad)
        fine = F.conv1d(fine, self.kernel.to(transient.dtype))
        sig = fine.reshape(v, z, -1, os_).sum(-1)[..., self.pad_lo: self.pad_lo + self.n_bins]
        sig = self.power * self.gain.to(sig.dtype)[None, :, None] * sig.clamp_min(0.0)
        if self.crosstalk:
            sig = sig + self.crosstalk * sig.sum(dim=1, keepdim=True)
        bg = torch.as_tensor(background, dtype=sig.dtype, device=sig.device)
        bg = bg[..., None] if bg.ndim == 2 else bg
        return (sig + bg).clamp_min(RATE_FLOOR)

    # ---- rates to detections and likelihoods ---------------------------------------------------------------------
    def detections(self, lam: torch.Tensor) -> torch.Tensor:
        """Expected detections per cycle (V, Z, B): first-photon probabilities when pile-up is on, else lam;
        blurred by the sensor's timing jitter."""
        if self.terms.pileup:
            p = -torch.expm1(-lam) * torch.exp(-_before(lam))
        else:
            p = lam
        return self._jitter(p)

    def expected_counts(self, lam: torch.Tensor, cycles: torch.Tensor) -> torch.Tensor:
        """Expected counts (V, Z, B) over cycles (V,) laser cycles."""
        return self.detections(lam) * cycles[:, None, None]

    def nll(self, lam: torch.Tensor, counts: torch.Tensor, cycles: torch.Tensor,
            valid: torch.Tensor | None = None) -> torch.Tensor:
        """Negative log-likelihood of counts (V, Z, B) over cycles (V,), as a deviance (0 for a perfect fit),
        summed over valid bins and averaged over the histograms that hold a valid bin.

        Multinomial over bins plus a 'no photon' outcome when pile-up is on (log p_b = log(1 - e^-lam_b) -
        sum_{j<b} lam_j, computed with log1p/expm1 and a float64 cumulative sum), Poisson otherwise. Finite for any
        rates >= 0, however small or large. A histogram without a valid bin (a dropped frame, which scene_data
        leaves out) adds nothing, not even its 'no photon' term: read as N cycles without a photon, it would tell
        the fit that its zone's field of view is empty.

        The value is evaluated in float64 when a view sums over EXACT_ABOVE_CYCLES cycles: a float32 deviance is a
        difference of terms of c log(c/N), which rounding swamps once a view sums ~1e8 cycles (it even turned
        negative at 4e9). The gradient stays that of the computation in `lam`'s own dtype, so a fit steps as it
        did."""
        lam = lam.clamp_min(RATE_FLOOR)
        valid = torch.ones_like(counts, dtype=torch.bool) if valid is None else valid
        held = valid.any(-1)
        total = self._deviance(lam, counts.to(lam.dtype), cycles.to(lam.dtype), valid, held)
        if total.dtype != torch.float64 and float(cycles.max()) > EXACT_ABOVE_CYCLES:
            with torch.no_grad():
                exact = self._deviance(lam.detach().double(), counts.double(), cycles.double(), valid, held)
            total = total + (exact - total.detach()).to(total.dtype)  # adds nothing to the gradient
        # The mean over the histograms held (exactly the plain mean when every histogram is held).
        return total.mean() * (held.numel() / held.sum().clamp_min(1))

    def _deviance(self, lam: torch.Tensor, c: torch.Tensor, cycles: torch.Tensor, valid: torch.Tensor,
                  held: torch.Tensor) -> torch.Tensor:
        """Deviance (V, Z) of each histogram (`nll`'s terms), 0 where `held` is False; lam >= RATE_FLOOR."""
        n = cycles[:, None, None]
        if self.terms.pileup:
            if self.sensor.jitter_bins > 0:
                # The smallest normal number, not a denormal one: under flush_denormals (the fast preset on the
                # CPU) a denormal floor is 0, and log(0) made the loss nan behind a saturating return.
                logp = torch.log(self.detections(lam).clamp_min(torch.finfo(lam.dtype).tiny))
            else:
                logp = _log_hit(lam) - _before(lam)
            terms = torch.where(valid, torch.xlogy(c, c / n) - c * logp, torch.zeros_like(c))
            # More counts than cycles: scene_data leaves out the histograms over CYCLES_MARGIN x their cycles
            # (protocol.plausibility); one below that (where a model's cycles are an estimate, as the TMF8820's)
            # reads as "no cycle without a photon".
            miss_c = (n[..., 0] - c.sum(-1)).clamp_min(0.0)
            log_miss = -lam.sum(-1, dtype=torch.float64).to(lam.dtype)
            miss = torch.xlogy(miss_c, miss_c / n[..., 0]) - miss_c * log_miss
            return terms.sum(-1) + torch.where(held, miss, torch.zeros_like(miss))
        mu = self._jitter(lam) * n
        return torch.where(valid, mu - c + torch.xlogy(c, c) - c * torch.log(mu), torch.zeros_like(c)).sum(-1)

    def _jitter(self, p: torch.Tensor) -> torch.Tensor:
        sigma = self.sensor.jitter_bins
        if sigma < 1e-3:
            return p
        half = int(math.ceil(5 * sigma))
        x = torch.arange(-half, half + 1, dtype=p.dtype, device=p.device)
        k = torch.exp(-0.5 * (x / sigma) ** 2)
        k = (k / k.sum()).reshape(1, 1, -1)
        v, z, b = p.shape
        return F.conv1d(F.pad(p.reshape(v * z, 1, b), (half, half)), k).reshape(v, z, b)


def _before(lam: torch.Tensor) -> torch.Tensor:
    """sum_{j<b} lam_j along the last axis, accumulated in float64 (long histograms), >= 0.

    `cumsum - lam` subtracts each rate from a sum that holds it: next to a huge rate (1e14) that cancels the smaller
    ones before it, and the expected counts exceeded the cycles. Where the running sum passes SHIFTED_SUM_ABOVE the
    shifted sum (as protocol.pileup._rate_before) is taken instead; below it the two agree to 1e-10, and
    `cumsum - lam` (rounded alike in value and gradient) keeps fits stepping exactly as they always have."""
    csum = torch.cumsum(lam.double(), dim=-1)
    plain = (csum - lam.double()).clamp_min(0.0).to(lam.dtype)
    shifted = F.pad(csum[..., :-1], (1, 0)).to(lam.dtype)  # the running sum one bin back: no cancellation
    return torch.where(csum.detach() > SHIFTED_SUM_ABOVE, shifted, plain)


def _log_hit(lam: torch.Tensor) -> torch.Tensor:
    """log(1 - exp(-lam)), accurate for tiny and huge lam."""
    # Each branch sees only its own range, so the unused one never produces inf (whose gradient would poison where).
    big, small = lam.clamp_min(0.6931), lam.clamp(max=0.6931)
    return torch.where(lam > 0.6931, torch.log1p(-torch.exp(-big)), torch.log(-torch.expm1(-small)))
