"""How a reconstruction ended, honestly: did it converge, and what makes its result doubtful (report.json's
"converged" and "warnings", one line each).

Four checks, each on plain numbers the run recorded (docs/end_of_run.md derives the thresholds):

- **Stopped early.** A run that ended on its time budget or step count while its data term was still falling:
  the windowed data term of the last fifth of the run against the fifth before it.
- **Starved.** A CPU run whose process got much less than one core (its CPU seconds against its wall seconds):
  other processes took the cores, and it made that many times fewer steps than it would have alone.
- **Far from the noise.** The measured counts against the fitted model's expected counts. On a simulated capture,
  whose model is exact, the Poisson deviance per bin divided by the deviance that photon noise alone gives on
  average for those expected counts (`noise_deviance`): about 1 when the model explains the data down to the noise.
  On a real capture the sensor's own departures from any model of it outweigh the noise by a factor that grows with
  the photons, so the test there is scale-free: the model's error per bin relative to its expected counts
  (`FitNoise.relative_misfit`), against what a good fit of a real capture leaves.
- **Seen by too few views.** The share of the mesh's surface (undersides left out) that fewer than three views saw
  (`coverage.py`): there the shape is the prior's guess, however well the fit explains the measurements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.special import gammaln, xlogy

STILL_FALLING = 0.01
"""Relative drop of the windowed data term over the last fifth of a run above which it was still improving."""
STARVED_SHARE = 0.5
"""CPU cores' worth a CPU run's process must have had on average (CPU seconds / wall seconds): below it, warn."""
REAL_SENSOR_MISFIT = 0.3
"""Relative misfit (`FitNoise.relative_misfit`) that a real sensor's own departures from its model leave on good fits
of the public dataset's real pyramid, bright or dim (docs/end_of_run.md gives the measurements)."""
RELATIVE_MISFIT_LIMIT = 0.6
"""Relative misfit above which the fit does not explain a measured capture: twice REAL_SENSOR_MISFIT."""
NOISE_RATIO_SIMULATED = 1.1
"""The same on a simulated capture, whose sensor model is the simulator's: a fit that found the surface leaves photon
noise alone there (1.01-1.03 on the tuning split's scenes), so 10 % more misfit means part of the surface is wrong."""
COVERAGE_LIMIT = 0.2
"""Share of the surface seen by too few views (`coverage.Coverage.share_few`) above which the result says so: twice
the largest share a good fit of the tuning split leaves (10 %: the real pyramid, around its base on the table)."""
MIN_TREND_STEPS = 50
"""Fewest steps for the trend test: a shorter run is judged by its stop alone."""
EXACT_BELOW = 30.0
"""Expected counts below which the noise deviance is summed over the Poisson distribution (above: its expansion)."""


@dataclass
class FitNoise:
    """The fit's data term against the photon noise, over `bins` valid bins of the views checked."""

    deviance_per_bin: float
    """Mean Poisson half-deviance per bin, mu - c + c log(c / mu), of the measured counts c (0 for a perfect fit)."""
    noise_per_bin: float
    """Its mean expectation if the counts were Poisson draws of the fitted expected counts mu (`noise_deviance`)."""
    bins: int
    views: list[int] = field(default_factory=list)
    relative_misfit: float = 0.0
    """The model's error per bin beyond the photon noise, relative to its expected counts: sqrt(2 sum(d - E[d]) /
    sum mu), d the half-deviance of a bin. For a model off by a relative error e in each bin, d - E[d] is about
    mu e^2 / 2, so this is the photon-weighted RMS of e (0.1: the model is 10 % off where the photons are). Unlike
    the deviance ratio it does not grow with the photon count: a real sensor's own departures from its model give
    the same figure in a bright capture as in a dim one."""
    render_per_bin: float = 0.0
    """The mean deviance per bin that the expected counts' own error adds (they are the mean of a few renders of
    sampled rays: `fit_noise`'s `expected_var`); part of `deviance_per_bin`, none of the model's misfit."""

    @property
    def ratio(self) -> float:
        """The deviance less the renders' share, against the photon noise: about 1 for a fit down to the noise."""
        if self.noise_per_bin <= 0:
            return math.inf
        return (self.deviance_per_bin - self.render_per_bin) / self.noise_per_bin

    def to_dict(self) -> dict:
        return {"deviance_per_bin": self.deviance_per_bin, "noise_per_bin": self.noise_per_bin,
                "render_per_bin": self.render_per_bin, "ratio": self.ratio, "relative_misfit": self.relative_misfit,
                "bins": self.bins, "views": list(self.views)}


def noise_deviance(mu: np.ndarray) -> np.ndarray:
    """Expected Poisson half-deviance E[mu - c + c log(c / mu)] of one bin whose count c ~ Poisson(mu), per bin.

    E[mu - c] = 0, so it is E[c log c] - mu log mu. Below EXACT_BELOW counts the expectation is summed over the
    distribution (it falls to 0 with mu: a bin that expects no photon and gets none fits perfectly); above, the
    expansion 1/2 + 1/(12 mu) + 1/(12 mu^2) + 19/(120 mu^3) (error under 1e-6). Large counts give 1/2: half a
    chi-square with one degree of freedom."""
    mu = np.maximum(np.asarray(mu, np.float64), 0.0)
    out = np.empty_like(mu)
    big = mu >= EXACT_BELOW
    x = 1.0 / mu[big]
    out[big] = 0.5 + x / 12.0 + x * x / 12.0 + 19.0 * x ** 3 / 120.0
    small = mu[~big]
    if small.size:
        k = np.arange(int(EXACT_BELOW + 12 * math.sqrt(EXACT_BELOW) + 20), dtype=np.float64)
        m = small[:, None]
        with np.errstate(divide="ignore"):
            logp = xlogy(k, m) - m - gammaln(k + 1)
        e_clogc = (np.exp(logp) * xlogy(k, k)).sum(axis=1)
        out[~big] = e_clogc - xlogy(small, small)
    return np.maximum(out, 0.0)


def fit_noise(measured: np.ndarray, expected: np.ndarray, valid: np.ndarray | None = None,
              views=(), expected_var: np.ndarray | None = None) -> FitNoise | None:
    """Compare measured counts with the model's expected counts (same shape, e.g. (V, Z, B)) over the `valid` bins;
    None when there is no valid bin. `expected_var` (same shape, counts^2): the variance of `expected` itself where it
    is an estimate (the mean of a few renders of randomly sampled rays). An error e in mu adds e^2 / (2 mu) to a bin's
    expected deviance (its second-order term; the first averages out), so that much is counted with the photon
    noise: on a bright capture the renderer's own sampling noise would otherwise read as a misfit."""
    c = np.asarray(measured, np.float64)
    mu = np.maximum(np.asarray(expected, np.float64), 1e-12)
    var = np.zeros(c.shape) if expected_var is None else np.asarray(expected_var, np.float64)
    ok = np.isfinite(c) & np.isfinite(mu) & np.isfinite(var) & (np.ones(c.shape, bool) if valid is None else
                                                                np.asarray(valid, bool))
    if not ok.any():
        return None
    c, mu, var = c[ok], mu[ok], np.maximum(var[ok], 0.0)
    dev = mu - c + xlogy(c, c / mu)
    noise, render = noise_deviance(mu), var / (2.0 * mu)
    excess, expected = float(dev.sum() - noise.sum() - render.sum()), float(mu.sum())
    relative = math.sqrt(2.0 * max(excess, 0.0) / expected) if expected > 0 else 0.0
    return FitNoise(float(dev.mean()), float(noise.mean()), int(ok.sum()), [int(v) for v in views], relative,
                    float(render.mean()))


def late_drop(data_terms) -> float | None:
    """Relative drop of the mean data term from the second-last fifth of the run to the last fifth (0.02: it fell by
    2 %); None for runs shorter than MIN_TREND_STEPS or without a finite, positive data term."""
    d = np.asarray([x for x in data_terms if x is not None], np.float64)
    if len(d) < MIN_TREND_STEPS or not np.all(np.isfinite(d)):
        return None
    n = len(d) // 5
    before, last = float(d[-2 * n:-n].mean()), float(d[-n:].mean())
    return (before - last) / before if before > 0 else None


@dataclass
class RunFacts:
    """What the checks read, as the run recorded it."""

    stopped_by: str
    """'budget', 'steps' or 'converged'."""
    steps: int
    model_converged: bool | None
    """The model's own convergence test at the last step (the fast preset's plateau), or None when it has none."""
    data_terms: list[float]
    """The data term of every step."""
    device: str = "cpu"
    cpu_seconds: float | None = None
    """Process CPU seconds spent while training (all threads)."""
    wall_seconds: float | None = None
    """Wall seconds of the same stretch."""
    fit: FitNoise | None = None
    measured: bool = True
    """A real sensor's capture (else a simulated one: the fit is held to the photon noise more tightly)."""
    budget_notes: list[str] = field(default_factory=list)
    """What a short time budget cut (a coarser mesh, fewer metric points): said as warnings too."""
    coverage: object | None = None
    """The mesh's coverage by the views (a `coverage.Coverage`), or None where it was not measured."""
    continued: bool = False
    """The run went on from another fit's field (a live job's final run): too few steps to judge a trend is then a
    short polish, not a rough early state."""


def converged(facts: RunFacts) -> bool:
    """The model's own test where it has one; else (the paper preset) whether the data term had stopped falling
    (under STILL_FALLING over the last fifth of at least MIN_TREND_STEPS steps)."""
    if facts.stopped_by == "converged":
        return True
    if facts.model_converged is not None:
        return bool(facts.model_converged)
    drop = late_drop(facts.data_terms)
    return drop is not None and drop < STILL_FALLING


def cpu_share(facts: RunFacts) -> float | None:
    """CPU cores' worth the process had while training (CPU seconds / wall seconds), or None where not measured."""
    if not facts.cpu_seconds or not facts.wall_seconds or facts.wall_seconds <= 0:
        return None
    return facts.cpu_seconds / facts.wall_seconds


def misfit_warning(fit: FitNoise, measured: bool) -> str | None:
    """The line saying that the fit does not explain the measurements, or None when it does: on a measured capture
    by its relative misfit (RELATIVE_MISFIT_LIMIT), on a simulated one by its deviance against the photon noise
    (NOISE_RATIO_SIMULATED)."""
    if measured and fit.relative_misfit > RELATIVE_MISFIT_LIMIT:
        return (f"the fit does not explain the measurements: the model is off by {100 * fit.relative_misfit:.0f} % "
                f"per bin where the photons are (a good fit of a real capture: about "
                f"{100 * REAL_SENSOR_MISFIT:.0f} %); a wrong sensor model or calibration, an object that "
                f"moved during the scan, or a fit gone wrong")
    if not measured and fit.ratio > NOISE_RATIO_SIMULATED:
        rendered = (f", less {fit.render_per_bin:.3g} from the check's own renders" if fit.render_per_bin > 0
                    else "")
        return (f"the fit does not explain the measurements: their deviance from the model is {fit.ratio:.2f}x what "
                f"photon noise gives ({fit.deviance_per_bin:.3g}{rendered}, against {fit.noise_per_bin:.3g} per bin); "
                f"the capture is simulated, so its model is exact: part of the surface is likely wrong")
    return None


def coverage_warning(coverage) -> str | None:
    """The line saying that much of the surface was seen by too few views to be measured (a `coverage.Coverage`
    whose share_few is above COVERAGE_LIMIT), or None."""
    if coverage is None or not coverage.share_few > COVERAGE_LIMIT:
        return None
    where = ""
    if coverage.few_heights_m is not None:
        lo, hi = coverage.few_heights_m
        where = f", mostly at heights {lo:.2f} to {hi:.2f} m"
    return (f"{100 * coverage.share_few:.0f} % of the surface (undersides left out) was seen by fewer than "
            f"{coverage.few_views} views{where}: its shape there comes from the fit's smoothness, not from "
            f"measurements; scan it with views aimed at it (for a tall object, a higher target)")


def warnings(facts: RunFacts) -> list[str]:
    """One line per reason to doubt the result (empty when there is none)."""
    out = []
    if facts.stopped_by in ("budget", "steps") and not converged(facts):
        drop = late_drop(facts.data_terms)
        limit = "time budget" if facts.stopped_by == "budget" else "step count"
        flag = "--budget-s" if facts.stopped_by == "budget" else "--steps"
        if drop is None:
            if not facts.continued:
                out.append(f"the run stopped on its {limit} after only {facts.steps} step(s), before its fit could "
                           f"settle: the mesh is a rough early state (a larger {flag} gives a better one)")
        elif drop >= STILL_FALLING:
            out.append(f"the run stopped on its {limit} well before convergence: its data term was still falling "
                       f"({100 * drop:.1f} % over the last fifth of its {facts.steps} steps; a larger {flag} gives "
                       f"a better mesh)")
    share = cpu_share(facts)
    # Only a run that a time budget stopped lost steps to a busy machine: one that converged, or made the steps it
    # was asked for, has the result it would have had alone (later).
    if facts.stopped_by == "budget" and facts.device == "cpu" and share is not None and share < STARVED_SHARE:
        out.append(f"the machine was busy: this run had {share:.2f} of a CPU core on average and made about "
                   f"{1 / max(share, 1e-3):.0f}x fewer steps ({facts.steps}) than it would alone; stop other work "
                   f"or give it a larger time budget")
    misfit = misfit_warning(facts.fit, facts.measured) if facts.fit is not None else None
    if misfit:
        out.append(misfit)
    seen = coverage_warning(facts.coverage)
    if seen:
        out.append(seen)
    out += facts.budget_notes
    return out


__all__ = ["FitNoise", "RunFacts", "noise_deviance", "fit_noise", "late_drop", "converged", "cpu_share",
           "warnings", "misfit_warning", "coverage_warning", "COVERAGE_LIMIT", "STILL_FALLING", "STARVED_SHARE",
           "RELATIVE_MISFIT_LIMIT", "NOISE_RATIO_SIMULATED"]
