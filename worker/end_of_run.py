"""How a reconstruction ended, honestly: did it converge, and what makes its result doubtful (report.json's
"converged" and "warnings", one line each).

Nine checks, each on plain numbers the run recorded (docs/end_of_run.md derives the thresholds):

- **Stopped early.** A run that ended on its time budget or step count while its data term was still falling:
  the windowed data term of the last fifth of the run against the fifth before it. Any other run that did not
  converge says that it did not (UNCONVERGED), a live job's short final polish aside.
- **Starved.** A CPU run whose threads waited for cores over half its training (Linux's scheduler statistics,
  `cpu_wait.py`; where those cannot be read, its process had under half a core: its CPU seconds against its wall
  seconds): it trained that many times slower than alone.
- **Far from the noise.** The measured counts against the fitted model's expected counts, histogram by histogram.
  On a simulated capture, whose model is exact, a histogram is misfit when its Poisson deviance exceeds what photon
  noise alone gives (`noise_deviance`) by more than MISFIT_Z standard deviations of that noise and the model is off
  by more than MISFIT_RELATIVE where its photons are; a good fit leaves a few such histograms, a wrong surface many.
  (The deviance summed over every bin against the noise, `FitNoise.ratio`, cannot judge a bright capture: there a
  good fit's 1-2 mm errors are significant too.) On a real capture the sensor's own departures from any model of it
  outweigh the noise everywhere, so the test there is the model's error per bin relative to its expected counts over
  all the histograms (`FitNoise.relative_misfit`), against what a good fit of a real capture leaves. Where most
  histograms are saturated (`protocol.pileup.saturated_histograms`: the first return stopped nearly every laser
  cycle, pile-up), the line names that as the cause, with what to do, and a saturated capture whose fit passes says
  so on its own line: its histograms hold each view's nearest surface and nothing behind it.
- **Seen by too few views.** The share of the mesh's surface (undersides left out) that fewer than three views saw
  (`coverage.py`): there the shape is the prior's guess, however well the fit explains the measurements.
- **Returns the mesh lacks.** Many first returns come from where the mesh has no surface: nothing of it in their
  zone's field of view as near as the return (`lost_returns.py`). A part that stands out of the object lost whole (a
  thin rod that carving cut away) leaves a mesh that the other checks pass: one piece, well seen, its fit within the
  noise where the lost part's few photons were.
- **In pieces.** The mesh falls apart into more than one piece of note (`pieces.py`): a thin part broke where the
  fit could not hold it, or surface stands apart where there is none. Neither need show in the fit's misfit. With a
  ground truth of as many pieces (two objects), there is nothing to say.
- **Specks.** Pieces too small to count hold together a share of the surface no good fit leaves (`pieces.py`): the
  fit shaped noise.
- **Tunnels.** With a ground truth, the mesh has more tunnels through it than the truth has, beyond the pinholes a
  good fit leaves (`pieces.py`): thin walls broke open into holes, which the Chamfer figure hardly shows.
- **Too little signal.** Many histograms of the zone aimed at the object hold no return at carving's level
  (`signal_check.py`): each carved its view empty, and the fit explains what was left. The other checks pass such a
  result: in so faint a capture any surface is within the noise, and coverage and pieces are measured on the wrong
  mesh itself. A run whose carving thresholds were set lower is judged at their default level too: lowered, noise
  clears them in every view, and the capture is as faint as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.special import gammaln, xlogy

from spadscan.protocol.pileup import mostly_saturated, saturated_histograms

from .ambient_light import ambient_warning
from .cpu_wait import counted_helpers, lost_seconds
from .pieces import SPECKS_LIMIT
from .signal_check import signal_warning

STILL_FALLING = 0.01
"""Relative drop of the windowed data term over the last fifth of a run above which it was still improving."""
OVERRUN_SHARE = 0.1
OVERRUN_FLOOR_S = 10.0
"""A run that overran its time budget says so beyond the tolerance `--budget-s` promises: OVERRUN_SHARE of the
budget or OVERRUN_FLOOR_S seconds, whichever is larger (the start and the end of a run take seconds however short
its budget)."""
LEAST_PACE = 0.01
"""The least share of its pace alone that a run's threads' waits are taken to say (`pace_share`): summed waits that
overlap can reach the whole wall time, and beyond 100x slower the figure says only that the run was starved."""
STARVED_SHARE = 0.5
"""Share of its training's wall time that a CPU run must have gone at its own pace, not waiting for cores that other
processes held (`pace_share`); where that is not measured, CPU cores' worth its process must have had on average (CPU
seconds / wall seconds, `cpu_share`): below it, warn."""
REAL_SENSOR_MISFIT = 0.3
"""Relative misfit (`FitNoise.relative_misfit`) that a real sensor's own departures from its model leave on good fits
of the public dataset's real pyramid, bright or dim (docs/end_of_run.md gives the measurements)."""
RELATIVE_MISFIT_LIMIT = 0.6
"""Relative misfit above which the fit does not explain a measured capture: twice REAL_SENSOR_MISFIT."""
SIMULATED_GOOD_MISFIT = 0.1
"""Relative misfit under which good fits of simulated captures stay (0.03-0.10 over every split; docs/end_of_run.md):
above RELATIVE_MISFIT_LIMIT one is grossly wrong however few histograms were checked."""
MISFIT_Z = 5.0
"""Standard deviations of a histogram's photon-noise deviance by which its deviance must exceed that noise to count
as misfit: chance alone gives one such histogram in millions."""
MISFIT_RELATIVE = 0.15
"""Relative error where its photons are (the histogram's own relative misfit) that a misfit histogram must exceed as
well: in a bright capture a good fit's millimetre errors are significant against the noise, but small."""
MISFIT_SHARE_SIMULATED = 0.1
"""Share of the checked histograms of a simulated capture that may be misfit before the run says so: twice the largest
share a good fit of the tuning split leaves (the demo goblet's default 120 s run, 4.2 %; docs/end_of_run.md)."""
MISFIT_MIN_HISTOGRAMS = 3
"""Fewest misfit histograms that make a pattern: a capture of few views checks few histograms, and one histogram
at a sharp edge that a smooth field rounds off is not a wrong surface."""
COVERAGE_LIMIT = 0.12
"""Share of the surface seen by too few views (`coverage.Coverage.share_few`) above which the result says so: between
the largest share that a good fit of a tuning capture leaves (11.4 %: the tuning lamp scanned from 0.35 m, 1.5 mm;
the real pyramid within its 5 mm goal 10.4 %) and the smallest that one over 2 mm leaves (13.1 %: the tall egg at
3.0 mm); docs/end_of_run.md lists them."""
EXTRA_TUNNELS = 2
"""Tunnels beyond its ground truth's that a mesh may have before the result says so: a good fit opens one or two
pinholes through a thin wall (the demo goblet's best fits 2, the 256-view goblet 1, the cat 1), a broken wall opens
more (the demo goblet's notched fits 5-30, the vase at 1.96 mm 3, the big goblet 10; docs/end_of_run.md)."""
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
    histograms: int = 0
    """Histograms checked (those with a valid bin that expects photons)."""
    misfit_histograms: int = 0
    """Of them, those whose deviance exceeds their noise by over MISFIT_Z standard deviations and whose own relative
    misfit is over MISFIT_RELATIVE."""
    excess_z: float = 0.0
    """The deviance beyond the photon noise and the renders' share, summed over every bin checked, in standard
    deviations of the two: a relative misfit that chance alone gives (a dim capture's few photons) stays under
    MISFIT_Z here."""
    saturated_histograms: int = 0
    """Of the histograms checked, those whose first return is saturated (`saturated_histograms`)."""

    @property
    def ratio(self) -> float:
        """The deviance less the renders' share, against the photon noise: about 1 for a fit down to the noise."""
        if self.noise_per_bin <= 0:
            return math.inf
        return (self.deviance_per_bin - self.render_per_bin) / self.noise_per_bin

    @property
    def misfit_share(self) -> float:
        """Share of the checked histograms that are misfit (0 when none was checked)."""
        return self.misfit_histograms / self.histograms if self.histograms else 0.0

    @property
    def saturated(self) -> bool:
        """Whether the checked histograms are mostly saturated (pile-up: `protocol.pileup.mostly_saturated`)."""
        return mostly_saturated(self.saturated_histograms, self.histograms)

    def to_dict(self) -> dict:
        return {"deviance_per_bin": self.deviance_per_bin, "noise_per_bin": self.noise_per_bin,
                "render_per_bin": self.render_per_bin, "ratio": self.ratio, "relative_misfit": self.relative_misfit,
                "histograms": self.histograms, "misfit_histograms": self.misfit_histograms,
                "misfit_share": self.misfit_share, "excess_z": self.excess_z,
                "saturated_histograms": self.saturated_histograms, "bins": self.bins,
                "views": list(self.views)}


def noise_deviance(mu: np.ndarray) -> np.ndarray:
    """Expected Poisson half-deviance E[mu - c + c log(c / mu)] of one bin whose count c ~ Poisson(mu), per bin.

    E[mu - c] = 0, so it is E[c log c] - mu log mu. Below EXACT_BELOW counts the expectation is summed over the
    distribution (it falls to 0 with mu: a bin that expects no photon and gets none fits perfectly); above, the
    expansion 1/2 + 1/(12 mu) + 1/(12 mu^2) + 19/(120 mu^3) (error under 1e-6). Large counts give 1/2: half a
    chi-square with one degree of freedom."""
    return noise_moments(mu)[0]


def noise_moments(mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) of the Poisson half-deviance of one bin whose count c ~ Poisson(mu), per bin: the mean as
    `noise_deviance` says; the variance summed over the distribution below EXACT_BELOW counts, above it 1/2 (half a
    chi-square with one degree of freedom; its next term is of order 1/mu)."""
    mu = np.maximum(np.asarray(mu, np.float64), 0.0)
    mean, var = np.empty_like(mu), np.full_like(mu, 0.5)
    big = mu >= EXACT_BELOW
    x = 1.0 / mu[big]
    mean[big] = 0.5 + x / 12.0 + x * x / 12.0 + 19.0 * x ** 3 / 120.0
    small = mu[~big]
    if small.size:
        k = np.arange(int(EXACT_BELOW + 12 * math.sqrt(EXACT_BELOW) + 20), dtype=np.float64)
        m = np.maximum(small, 1e-300)[:, None]  # mu = 0 (no photon expected): mean and variance 0
        with np.errstate(divide="ignore"):
            p = np.exp(xlogy(k, m) - m - gammaln(k + 1))
            d = m - k + xlogy(k, k) - xlogy(k, m)
        first = (p * d).sum(axis=1)
        mean[~big] = (p * xlogy(k, k)).sum(axis=1) - xlogy(small, small)
        var[~big] = (p * d * d).sum(axis=1) - first * first
    return np.maximum(mean, 0.0), np.maximum(var, 0.0)


def fit_noise(measured: np.ndarray, expected: np.ndarray, valid: np.ndarray | None = None,
              views=(), expected_var: np.ndarray | None = None) -> FitNoise | None:
    """Compare measured counts with the model's expected counts (same shape, e.g. (V, Z, B): the last axis is a
    histogram's bins) over the `valid` bins; None when there is no valid bin. `expected_var` (same shape, counts^2):
    the variance of `expected` itself where it is an estimate (the mean of a few renders of randomly sampled rays).
    An error e in mu adds e^2 / (2 mu) to a bin's expected deviance (its second-order term; the first averages out),
    so that much is counted with the photon noise: on a bright capture the renderer's own sampling noise would
    otherwise read as a misfit. Each histogram is judged too (`FitNoise.misfit_histograms`)."""
    c = np.asarray(measured, np.float64)
    mu = np.maximum(np.asarray(expected, np.float64), 1e-12)
    var = np.zeros(c.shape) if expected_var is None else np.asarray(expected_var, np.float64)
    ok = np.isfinite(c) & np.isfinite(mu) & np.isfinite(var) & (np.ones(c.shape, bool) if valid is None else
                                                                np.asarray(valid, bool))
    if not ok.any():
        return None
    # Bins left out keep their place (the histograms are judged whole) with a neutral mu and no weight.
    c, mu, var = np.where(ok, c, 0.0), np.where(ok, mu, 1.0), np.where(ok, np.maximum(var, 0.0), 0.0)
    dev = np.where(ok, mu - c + xlogy(c, c / mu), 0.0)
    render = np.where(ok, var / (2.0 * mu), 0.0)
    noise, noise_var = (np.where(ok, a, 0.0) for a in noise_moments(mu))
    mu = np.where(ok, mu, 0.0)
    excess, expected = float(dev.sum() - noise.sum() - render.sum()), float(mu.sum())
    relative = math.sqrt(2.0 * max(excess, 0.0) / expected) if expected > 0 else 0.0
    checked, misfit = misfit_histograms(dev, noise, noise_var, render, mu)
    sd = math.sqrt(float(noise_var.sum() + (2.0 * render * render).sum()))
    n = int(ok.sum())
    flat = lambda a: a.reshape(-1, a.shape[-1])  # noqa: E731
    judged = flat(mu).sum(axis=1) > 0  # the histograms `misfit_histograms` checks
    saturated = int((saturated_histograms(np.maximum(flat(c), 0.0), flat(ok)) & judged).sum())
    return FitNoise(float(dev.sum() / n), float(noise.sum() / n), n, [int(v) for v in views], relative,
                    float(render.sum() / n), checked, misfit, excess / sd if sd > 0 else 0.0, saturated)


def misfit_histograms(dev, noise, noise_var, render, mu) -> tuple[int, int]:
    """(histograms checked, histograms misfit) from per-bin arrays of one shape whose last axis is the bins (0 where
    a bin is not valid): a histogram's excess deviance over its photon noise and the renders' share, in standard
    deviations of the two (a render share r varies as 2 r^2: r times a chi-square with one degree of freedom), over
    MISFIT_Z, and its own relative misfit over MISFIT_RELATIVE. Histograms that expect no photon are not checked."""
    flat = lambda a: a.reshape(-1, a.shape[-1]).sum(axis=1)  # noqa: E731
    d, n, r, m = flat(dev), flat(noise), flat(render), flat(mu)
    sd = np.sqrt(flat(noise_var) + flat(2.0 * render * render))
    excess = d - n - r
    checked = (m > 0) & (sd > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(checked, excess / np.where(checked, sd, 1.0), 0.0)
        relative = np.where(checked, np.sqrt(2.0 * np.maximum(excess, 0.0) / np.where(checked, m, 1.0)), 0.0)
    return int(checked.sum()), int((checked & (z > MISFIT_Z) & (relative > MISFIT_RELATIVE)).sum())


def late_drop(data_terms) -> float | None:
    """Relative drop of the mean data term from the second-last fifth of the run to the last fifth (0.02: it fell by
    2 %); None for runs shorter than MIN_TREND_STEPS or without a finite, positive data term."""
    d = np.asarray([x for x in data_terms if x is not None], np.float64)
    if len(d) < MIN_TREND_STEPS or not np.all(np.isfinite(d)):
        return None
    n = len(d) // 5
    before, last = float(d[-2 * n:-n].mean()), float(d[-n:].mean())
    return (before - last) / before if before > 0 else None


def too_short(data_terms) -> bool:
    """Whether a run's data terms are too few to tell a trend (MIN_TREND_STEPS): not whether `late_drop` could
    read them (a run of thousands of steps with a term that is not finite is no short one)."""
    return sum(x is not None for x in data_terms) < MIN_TREND_STEPS


def late_drop_error(data_terms) -> float:
    """The standard error of `late_drop` from the steps' scatter within the two fifths (0 where it is None)."""
    d = np.asarray([x for x in data_terms if x is not None], np.float64)
    if len(d) < MIN_TREND_STEPS or not np.all(np.isfinite(d)):
        return 0.0
    n = len(d) // 5
    before, last = d[-2 * n:-n], d[-n:]
    if before.mean() <= 0:
        return 0.0
    return float(np.sqrt((before.var(ddof=1) + last.var(ddof=1)) / n) / before.mean())


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
    scene_notes: list[str] = field(default_factory=list)
    """What the capture's set-up found that limits the result (a scene bound that cuts the object): warnings too."""
    coverage: object | None = None
    """The mesh's coverage by the views (a `coverage.Coverage`), or None where it was not measured."""
    pieces: object | None = None
    """The mesh's connected pieces (a `pieces.Pieces`), or None where they were not counted."""
    budget_s: float | None = None
    """The whole run's time budget (seconds), or None without one."""
    elapsed_s: float | None = None
    """Seconds from the process's start to the checks (what the budget counts)."""
    continued: bool = False
    """The run went on from another fit's field (a live job's final run): too few steps to judge a trend is then a
    short polish, not a rough early state."""
    polish: bool = False
    """The run is a live job's final polish: it went on from the live fit for the step count the live job chose
    itself (a few seconds' steps at the live fit's rate, `live.job.final_job`), not one the user asked for."""
    training_s: float | None = None
    """Wall seconds of training, checkpoint evaluations included (what its share of the budget counts)."""
    training_budget_s: float | None = None
    """The seconds the budget left training, or None without a budget."""
    preset: str | None = None
    """The preset that ran, or None where not known (`faster_ways`)."""
    cuda_seen: bool | None = None
    """Whether torch saw a CUDA device on the machine that ran, or None where not known (`faster_ways`)."""
    signal: object | None = None
    """How many histograms of the zone aimed at the object hold a return at carving's level (a
    `signal_check.Signal`), or None where not judged."""
    truth_pieces: int | None = None
    """Pieces of note of the ground truth (`pieces.mesh_pieces` of it), or None without one."""
    truth_tunnels: int | None = None
    """Tunnels through the ground truth (`pieces.Pieces.tunnels` of it), or None without one (or one not closed)."""
    thread_times: dict | None = None
    """Training's threads' seconds on a CPU and waiting for one (`cpu_wait.ThreadWaits.summary`: the stepping
    thread's and the helpers'), or None where not measured."""
    machine_jobs: int | None = None
    """Job processes the other workers on this machine may run at once, as the worker that started the run counted
    them (`cpu_wait.MACHINE_JOBS_ENV`), or None where no worker said (a run of its own): cores the run's threads
    waited for may have been theirs (`busy_warning`)."""
    lost: object | None = None
    """The first returns the mesh does not account for (a `lost_returns.LostReturns`), or None where not judged."""
    threads_fixed: bool = False
    """The run kept the CPU threads it was given (`--threads`, a user's OMP_NUM_THREADS: `threads.threads_fixed`),
    not the worker's share of the cores, which counts `machine_jobs`."""
    thin_sheets_emptied: int | None = None
    """Nodes the fast preset's thin-sheets part emptied near the table (its summary's `emptied_nodes`), or None where
    it did not run."""
    dark: dict | None = None
    """The fast preset's dark-restart part's summary with the fitted `albedo` beside it, where the part started the
    fit again for a dark object; else None."""
    ambient: object | None = None
    """How much of the laser cycles ambient light stopped before the object's returns (an `ambient_light.Ambient`),
    or None where not judged."""


def converged(facts: RunFacts) -> bool:
    """The model's own test where it has one; else (the paper preset) whether the data term had stopped falling:
    under STILL_FALLING over the last fifth of at least MIN_TREND_STEPS steps, by two standard errors. A step's data
    term is that of a few random views, which differ several-fold: their scatter alone made a fit still falling
    over the whole capture read as settled in three runs of five."""
    if facts.stopped_by == "converged":
        return True
    if facts.model_converged is not None:
        return bool(facts.model_converged)
    drop = late_drop(facts.data_terms)
    return drop is not None and drop + 2.0 * late_drop_error(facts.data_terms) < STILL_FALLING


def cpu_share(facts: RunFacts) -> float | None:
    """CPU cores' worth the process had while training (CPU seconds / wall seconds), or None where not measured."""
    if not facts.cpu_seconds or not facts.wall_seconds or facts.wall_seconds <= 0:
        return None
    return facts.cpu_seconds / facts.wall_seconds


def lost_share(facts: RunFacts) -> float | None:
    """Share of training's wall seconds the run lost to other processes, its threads waiting for cores they held
    (`cpu_wait.lost_seconds`), or None where not measured (no scheduler statistics, a GPU run)."""
    if facts.thread_times is None or not facts.wall_seconds:
        return None
    lost = lost_seconds(facts.thread_times, facts.wall_seconds)
    return None if lost is None else lost / facts.wall_seconds


def pace_share(facts: RunFacts) -> tuple[float, bool] | None:
    """(the share of its pace alone that the run kept while training, whether it was measured by its threads' waits
    (`lost_share`) rather than by its CPU time (`cpu_share`, where the waits are not known)), or None where neither
    is known. Its inverse is how many times slower it trained than alone."""
    lost = lost_share(facts)
    if lost is not None:
        return max(1.0 - lost, LEAST_PACE), True
    share = cpu_share(facts)
    return None if share is None else (share, False)


def cpu_wait(facts: RunFacts) -> dict | None:
    """report.json's figures on what the run lost to other processes (None where its threads' waits were not
    measured): seconds lost and their share of training, the pace kept, the steps' slowdown, the threads' times."""
    lost = lost_share(facts)
    if lost is None:
        return None
    pace, _ = pace_share(facts)
    return {"lost_s": lost * facts.wall_seconds, "lost_share": lost, "pace_share": pace, "slowdown": 1.0 / pace,
            "threads": facts.thread_times}


def busy_warning(facts: RunFacts) -> str | None:
    """The line saying that a CPU run's threads waited for cores most of its training and it trained that many times
    slower than alone, or None. Only a run that a time budget stopped lost steps to a busy machine: one that
    converged, or made the steps it was asked for, has the result it would have had alone (later). The waits do not
    say who held the cores: other processes, or the run's own threads where it has more than the cores free to it
    (then `--threads 1` is advised too). Where other workers on this host run job processes (`machine_jobs`), they
    are named among those processes, and the advice is fewer job processes there: a share of the cores that counts
    them is still too little when the host's job processes outnumber its cores, and stopping other work would not
    stop them."""
    pace = pace_share(facts)
    if facts.stopped_by != "budget" or facts.device != "cpu" or pace is None or not pace[0] < STARVED_SHARE:
        return None
    share, by_waits = pace
    slower = f"trained about {1 / max(share, 1e-3):.0f}x slower than it would alone ({facts.steps} steps)"
    siblings = _sibling_jobs(facts)
    if not by_waits:
        beside = f" (beside {siblings})" if siblings else ""
        return (f"the machine was busy: this run had {share:.2f} of a CPU core on average{beside} and {slower}; "
                f"{_busy_advice(facts, own=False)}")
    cpu = cpu_share(facts)
    # Threads that spin while a partner waits for its core burn CPU time: the run's CPU time then reads as a core.
    spun = ("" if cpu is None or cpu < STARVED_SHARE else
            f" (its CPU time, {cpu:.2f} of a core, hides this: its threads spun while they waited)")
    own = counted_helpers(facts.thread_times, facts.wall_seconds) > 0
    who = ("other processes held them" + (f", among them {siblings}" if siblings else "")
           + (", or the run has more threads than cores free to it" if own else ""))
    return (f"the machine was busy: this run's threads waited for CPU cores for {100 * lost_share(facts):.0f} % of "
            f"its training ({who}){spun}; it {slower}; {_busy_advice(facts, own)}")


def _sibling_jobs(facts: RunFacts) -> str:
    """The other workers' job processes on this host (`RunFacts.machine_jobs`) as the busy line names them, and
    whether the run's threads counted them; '' where there are none or no worker said."""
    if not _beside_siblings(facts):
        return ""
    counted = ("beside which this run kept the threads it was given" if facts.threads_fixed
               else "whose share of the cores this run's threads already count")
    return f"up to {facts.machine_jobs} job process(es) of other workers on this host, {counted}"


def _busy_advice(facts: RunFacts, own: bool) -> str:
    """What the busy line advises: stopping other work, or, beside other workers' job processes (`machine_jobs`),
    fewer job processes on the host; `--threads 1` too where the run's own threads count (`own`)."""
    first = ("run fewer job processes on this host (fewer workers, or a smaller --processes)"
             if _beside_siblings(facts) else "stop other work")
    return first + (", run it with `--threads 1`," if own else "") + " or give it a larger time budget"


def _beside_siblings(facts: RunFacts) -> bool:
    """Whether the worker that started the run said other workers' job processes share this host with it."""
    return isinstance(facts.machine_jobs, int) and facts.machine_jobs > 0


INTERRUPTED = "the run's training was stopped by Ctrl-C"
"""How the line of a run whose training the user ended early begins."""
UNCONVERGED = "the run did not converge: its mesh may still be changing"
"""How the line of a run that did not converge and whose other lines say nothing of it begins
(`unconverged_warning`, `unconverged_line`)."""
ENDED_BY = {"budget": ("time budget", "--budget-s"), "steps": ("step count", "--steps")}
"""What ended a run that stopped before it converged, by its `stopped_by`: the limit in words and the flag that
gives it longer (the worker's, reconstruct's and the demo's alike)."""


def unconverged_line(stopped_by: str) -> str:
    """UNCONVERGED with what ended the run and the flag that gives it longer, where its `stopped_by` says (its time
    budget or its step count): one line, as report.json, the page, --status, the demo and the dashboard all show it."""
    if stopped_by not in ENDED_BY:
        return UNCONVERGED
    limit, flag = ENDED_BY[stopped_by]
    return f"{UNCONVERGED} (it ended on its {limit}: a larger {flag} gives it longer)"


def overrun_tolerance_s(budget_s: float) -> float:
    """Seconds a run may take beyond its time budget before it says so (`--budget-s`: within 10 % or 10 s)."""
    return max(OVERRUN_SHARE * budget_s, OVERRUN_FLOOR_S)


def _seconds(value: float) -> str:
    """Seconds to two figures under ten, whole above: a training share of 0.01 s (a set-up that used the budget)
    reads as that, not as 0."""
    return f"{value:.0f}" if value >= 9.5 else f"{value:.2g}"


def overrun_warning(facts: RunFacts) -> str | None:
    """The line saying that the run took longer than its time budget and its tolerance (overrun_tolerance_s), or
    None. Training stops within its share of the budget, so what overran is the start (the interpreter, the imports,
    the set-up) or the end (the mesh, the pictures, the metrics), which the budget estimates from the machine as it
    was at the start: on a machine that other work slowed down later, they take longer."""
    if (facts.budget_s is None or facts.elapsed_s is None
            or facts.elapsed_s <= facts.budget_s + overrun_tolerance_s(facts.budget_s)):
        return None
    took = f"the run took {facts.elapsed_s:.1f} s of a {facts.budget_s:g} s time budget"
    over_training = (0.0 if facts.training_s is None or facts.training_budget_s is None
                     else facts.training_s - facts.training_budget_s)
    if over_training > 0.5 * (facts.elapsed_s - facts.budget_s):
        # Training overran its share, not the start or the end: the trainer takes at least one step, however long
        # (the paper preset's on a CPU: over a minute).
        per_step = facts.training_s / max(facts.steps, 1)
        faster = faster_ways(facts.preset, facts.device, facts.cuda_seen)
        return (f"{took}: training took {facts.training_s:.0f} s of the {_seconds(facts.training_budget_s)} s the "
                f"budget left it, {per_step:.0f} s a step over {facts.steps} step(s) on {facts.device}, and a run "
                f"takes at least one; give it {either(['a time budget of many steps', *faster])}")
    had = _contention_said(facts)
    return (f"{took}: its start and its end (the "
            f"mesh, the pictures, the metrics) took longer than the budget left them{had}; give it a larger time "
            f"budget or stop other work")


def _contention_said(facts: RunFacts) -> str:
    """What a CPU run's training lost to a busy machine, for the overrun's line: the share its threads waited for
    cores (`lost_share`), else the CPU core's worth its process had (`cpu_share`); '' where neither is known."""
    if facts.device != "cpu":
        return ""
    lost = lost_share(facts)
    if lost is not None:
        return f" (its threads waited for CPU cores for {100 * lost:.0f} % of its training)"
    share = cpu_share(facts)
    return "" if share is None else f" (it had {share:.2f} of a CPU core while training)"


FASTER_PRESET = {"paper": "fast"}
"""Preset -> the preset whose steps run faster, where there is one (the fast preset's grid step takes milliseconds on
a CPU, the paper preset's MLP step seconds to minutes): the fast preset has none to be pointed at."""


def faster_ways(preset: str | None, device: str, cuda_seen: bool | None) -> list[str]:
    """What would make a run's steps faster, as phrases for its advice, only those that apply: a GPU for a run that
    was not on one (`--device cuda` where torch sees a CUDA device; else it takes another machine), and a faster
    preset where there is one (FASTER_PRESET). None (a run's facts that do not say): named as they may apply."""
    ways = []
    if device != "cuda":
        ways.append("a machine with a GPU" if cuda_seen is False else "a faster device (--device cuda)")
    faster = FASTER_PRESET.get(preset) if preset is not None else "fast"
    if faster is not None:
        ways.append(f"the {faster} preset (--preset {faster})")
    return ways


def either(options: list[str]) -> str:
    """'a', 'a or b', 'a, b or c'."""
    return options[0] if len(options) == 1 else f"{', '.join(options[:-1])} or {options[-1]}"


def misfit_warning(fit: FitNoise, measured: bool) -> str | None:
    """The line saying that the fit does not explain the measurements, or None when it does: on a measured capture
    by its relative misfit (RELATIVE_MISFIT_LIMIT), on a simulated one by the same when it is gross, else by its
    share of misfit histograms (MISFIT_SHARE_SIMULATED, and at least MISFIT_MIN_HISTOGRAMS of them). Of a saturated
    capture (`FitNoise.saturated`) it names pile-up as the cause (`saturation_cause`), not the time axis, the poses
    or the surface: the builtin sphere at power 100 (64 views, 300 steps) was off by 61 % with its time axis and
    poses exact."""
    if measured and fit.relative_misfit > RELATIVE_MISFIT_LIMIT:
        cause = (saturation_cause(fit) if _saturated(fit) else
                 "a wrong sensor model or calibration, an object that moved during the scan, or a fit gone wrong")
        return (f"the fit does not explain the measurements: the model is off by {100 * fit.relative_misfit:.0f} % "
                f"per bin where the photons are (a good fit of a real capture: about "
                f"{100 * REAL_SENSOR_MISFIT:.0f} %); {cause}")
    if not measured and fit.relative_misfit > RELATIVE_MISFIT_LIMIT and fit.excess_z > MISFIT_Z:
        # Gross, whatever the count: a capture of one or two views, or a short run's check of 4 histograms, has too
        # few histograms for MISFIT_MIN_HISTOGRAMS, and a good fit of a simulated capture is under 0.1 here; and
        # beyond chance: a dim capture's few photons alone can make the relative misfit that large.
        cause = (saturation_cause(fit) if _saturated(fit) else
                 "the capture is simulated, so its model is exact: its time axis (the sensor's bin_width_m, "
                 "zero_bin), its poses or the fit are wrong")
        return (f"the fit does not explain the measurements: the model is off by {100 * fit.relative_misfit:.0f} % "
                f"per bin where the photons are (a good fit of a simulated capture: under "
                f"{100 * SIMULATED_GOOD_MISFIT:.0f} %); {cause}")
    if not measured and fit.misfit_share > MISFIT_SHARE_SIMULATED and fit.misfit_histograms >= MISFIT_MIN_HISTOGRAMS:
        cause = (saturation_cause(fit) if _saturated(fit) else
                 "the capture is simulated, so its model is exact: part of the surface is likely wrong")
        return (f"the fit does not explain the measurements: {100 * fit.misfit_share:.0f} % of the histograms "
                f"checked ({fit.misfit_histograms} of {fit.histograms}) depart from the model beyond photon noise and "
                f"by over {100 * MISFIT_RELATIVE:.0f} % where their photons are (a good fit: under "
                f"{100 * MISFIT_SHARE_SIMULATED:.0f} %); {cause}")
    return None


def _saturated(fit) -> bool:
    """`FitNoise.saturated`, False for a figure that does not say (a reader's own record of the misfit alone)."""
    return bool(getattr(fit, "saturated", False))


PILEUP_ADVICE = "lower the laser power or the exposure, or move the sensor back"
"""What a saturated capture needs (`saturation_cause`)."""


def saturation_cause(fit: FitNoise, consequence: str = "") -> str:
    """Why a saturated capture (`FitNoise.saturated`) fits badly, then `consequence` (a clause, or none), then what
    to do about it."""
    return pile_up_line(fit.saturated_histograms, f"the {fit.histograms} checked", consequence)


def pile_up_line(saturated: int, of: str, consequence: str = "") -> str:
    """'the histograms are saturated (`saturated` of `of`): ...' with `consequence` (a clause, or none) and what to
    do: the line that names pile-up, in a run's warnings and in a live job's status (worker/live/job.py)."""
    return (f"the histograms are saturated ({saturated} of {of}): the first return stopped nearly every laser cycle "
            f"(pile-up), so they hold only the leading edge of each view's nearest surface and nothing behind "
            f"it{consequence}; {PILEUP_ADVICE}")


def saturation_warning(fit: FitNoise | None) -> str | None:
    """The line saying that the capture is saturated (`FitNoise.saturated`), or None: said alone where the fit
    explains what the histograms hold (`misfit_warning` names pile-up itself where it does not), since that is only
    each view's nearest surface and the shape behind it comes from the fit's smoothness."""
    if fit is None or not _saturated(fit):
        return None
    return saturation_cause(fit, ", and the shape behind it comes from the fit's smoothness, not from measurements")


def mostly_at(heights_m: tuple[float, float] | None) -> str:
    """', mostly at heights 0.12 to 0.30 m' for a (low, high) pair of heights in metres; '' for None."""
    return "" if heights_m is None else f", mostly at heights {heights_m[0]:.2f} to {heights_m[1]:.2f} m"


def coverage_warning(coverage, measured: bool = False) -> str | None:
    """The line saying that much of the surface was seen by too few views to be measured (a `coverage.Coverage`
    whose share_few is above COVERAGE_LIMIT), or None. On a `measured` capture it names a second cause: an object
    that moved during the scan leaves a fit that grows surface where no view looked (the real pyramid moved 3 cm
    between its scan's halves: 16 %, against 8-10 % unmoved)."""
    if coverage is None or not coverage.share_few > COVERAGE_LIMIT:
        return None
    return (f"{100 * coverage.share_few:.0f} % of the surface (undersides left out) was seen by fewer than "
            f"{coverage.few_views} views{mostly_at(coverage.few_heights_m)}: its shape there comes from the fit's "
            f"smoothness, not from measurements; scan it with views aimed at it (for a tall object, a higher target)"
            + ("; if the views did aim at it, the object may have moved during the scan" if measured else ""))


def specks_warning(pieces, settled: bool = True) -> str | None:
    """The line saying that the mesh's specks (a `pieces.Pieces`) hold more than SPECKS_LIMIT of its surface together,
    or None. Of a `settled` run (one that converged) it says that a longer run hardly changes them: a fit at the noise
    floor gave the same specks with three times its budget (docs/end_of_run.md). A run that stopped before it
    converged has no such measure behind it, and its line does not claim it."""
    if pieces is None or not pieces.specks_share > SPECKS_LIMIT:
        return None
    longer = "a longer run hardly changes it: " if settled else ""
    return (f"{pieces.specks} specks stand apart from the mesh, {100 * pieces.specks_share:.1f} % of its surface (a "
            f"good fit: under {100 * SPECKS_LIMIT:.1f} %): the fit shaped noise, and the surface is likely spiky too; "
            f"an object small against the sensor's footprint, or a faint capture ({longer}scan closer, or with more "
            f"signal); look at preview.png")


DARK_ALBEDO = 0.6
"""A fitted albedo under which a restarted fit's object is called dark (the dark-restart part's `falling_below`)."""


def dark_warning(dark: dict | None) -> str | None:
    """The line saying that the object is dark, where the dark-restart part started its fit again (`RunFacts.dark`),
    or None: its returns are that many times fainter than a white object's, and its shape noisier; a dark torus (albedo
    0.15) came out at 3.9 mm where a white one came out at 0.9."""
    if not dark or dark.get("restarted_at_step") is None or not isinstance(dark.get("albedo"), (int, float)):
        return None
    albedo = float(dark["albedo"])
    if not albedo < DARK_ALBEDO:  # the restarted fit found it bright after all: nothing to say of its photons
        return None
    start = ", its albedo read from the counts" if dark.get("counts_albedo") is not None else ""
    return (f"the object is dark: its fitted albedo is {albedo:.2f} (a white one's about 1), so each view caught "
            f"about {1 / max(albedo, 1e-3):.0f}x fewer photons from it than from a white one, and its shape is "
            f"noisier, thin or small parts most (its fit started again from the hull at step "
            f"{dark['restarted_at_step']}{start}: docs/end_of_run.md); scan it nearer, with more frames per pose or "
            f"more laser power for a better one; look at preview.png")


def lost_warning(lost) -> str | None:
    """The line saying that many first returns come from where the mesh has no surface (a `lost_returns.LostReturns`
    that `says` so), or None: a part that stands out of the object is missing from the mesh (one that only other
    surface hides is not seen: lost_returns.py)."""
    if lost is None or not lost.says:
        return None
    return (f"{100 * lost.share:.1f} % of the first returns that can have come from the object ({lost.lost} of "
            f"{lost.returns}) come from where the mesh has no surface{mostly_at(lost.heights_m)}: their zones saw "
            f"something over {lost.tolerance_m * 1e3:.0f} mm nearer than any surface of the mesh or the table (a good "
            f"fit: at most {100 * lost.limit:.0f} %); a part that stands out of the object is missing, a thin one most "
            f"likely, lost where some views missed its faint return (scan it nearer or with more laser power), or "
            f"something else stood in the views; look at preview.png")


def pieces_warning(pieces, truth_pieces: int | None = None, thin_sheets_emptied: int | None = None) -> str | None:
    """The line saying that the mesh is in more than one piece of note (a `pieces.Pieces`), or None. With the ground
    truth's own count of pieces (`truth_pieces`), only more pieces than it has are worth a line: two objects scanned
    together are two pieces when their fit is perfect. `thin_sheets_emptied`: the nodes the thin-sheets part emptied
    near a table (RunFacts), named as a likely cause where there are any: it empties every sheet thinner than about
    two voxels there, a thin upright part of the object too (a 1 cm disc standing on edge: 5.6 mm in 2 pieces, 1.2
    with the part off)."""
    if pieces is None or pieces.count < 2 or (truth_pieces is not None and pieces.count <= truth_pieces):
        return None
    thin = ""
    if thin_sheets_emptied:
        thin = (f"; on the table the thin-sheets part emptied {thin_sheets_emptied} nodes of sheets thinner than "
                f"about two voxels, a thin upright part standing there among them perhaps (--set "
                f"parts.thin_sheets.enabled=false keeps them)")
    return (f"the mesh is in {pieces.count} pieces, {100 * pieces.share_apart:.0f} % of its surface apart from the "
            f"largest: if the object is one piece, a thin part of it broke off or a lump stands where there is "
            f"nothing{thin}; look at preview.png")


def tunnels_warning(pieces, truth_tunnels: int | None) -> str | None:
    """The line saying that the mesh has more than EXTRA_TUNNELS tunnels beyond its ground truth's (a `pieces.Pieces`
    against `truth_tunnels`), or None; without a ground truth nothing is said: a capture does not tell how many
    handles its object has."""
    if pieces is None or pieces.tunnels is None or truth_tunnels is None:
        return None
    if pieces.tunnels <= truth_tunnels + EXTRA_TUNNELS:
        return None
    return (f"the mesh has {pieces.tunnels} tunnels through it where its ground truth has {truth_tunnels}: thin walls "
            f"or parts broke open into holes that the Chamfer figure hardly shows (a longer run closes some, more "
            f"views of the thin parts more); look at preview.png")


def warnings(facts: RunFacts) -> list[str]:
    """One line per reason to doubt the result (empty when there is none)."""
    out = []
    if facts.stopped_by in ("budget", "steps") and not converged(facts):
        drop = late_drop(facts.data_terms)
        limit, flag = ENDED_BY[facts.stopped_by]
        if drop is None:
            if not facts.continued and too_short(facts.data_terms):
                out.append(f"the run stopped on its {limit} after only {facts.steps} step(s), before its fit could "
                           f"settle: the mesh is a rough early state (a larger {flag} gives a better one)")
        elif drop >= STILL_FALLING:
            out.append(f"the run stopped on its {limit} well before convergence: its data term was still falling "
                       f"({100 * drop:.1f} % over the last fifth of its {facts.steps} steps; a larger {flag} gives "
                       f"a better mesh)")
    if facts.stopped_by == "interrupted" and not converged(facts):
        out.append(f"{INTERRUPTED} after {facts.steps} step(s), before it converged: the mesh is the fit as it "
                   f"stood (a run left to its end gives a better one)")
    unsettled = unconverged_warning(facts, said=bool(out))
    if unsettled:
        out.append(unsettled)
    busy = busy_warning(facts)
    if busy:
        out.append(busy)
    over = overrun_warning(facts)
    if over:
        out.append(over)
    faint = signal_warning(facts.signal)  # first of the result's doubts: it explains those that follow
    if faint:
        out.append(faint)
    dark = dark_warning(facts.dark)  # as faint returns do, it explains a shape's doubts
    if dark:
        out.append(dark)
    bright = ambient_warning(facts.ambient)  # so does a background that buries the returns
    if bright:
        out.append(bright)
    # The doubts about the shape: of a rough early state, the fit's shortness says them first (a 1-step mesh of a
    # good capture read as "the time axis or the poses are wrong" and "scan it with views aimed at it"). The specks
    # line says that a longer run hardly changes them only of a run that converged: of one stopped early that would
    # contradict the lines that say to run it longer.
    early = early_note(facts)
    misfit = misfit_warning(facts.fit, facts.measured) if facts.fit is not None else None
    shape = [(misfit if misfit is not None else saturation_warning(facts.fit), early),
             (coverage_warning(facts.coverage, facts.measured), early),
             (lost_warning(facts.lost), early),
             (pieces_warning(facts.pieces, facts.truth_pieces, facts.thin_sheets_emptied), early),
             (specks_warning(facts.pieces, settled=converged(facts)), early),
             (tunnels_warning(facts.pieces, facts.truth_tunnels), early)]
    out += [line + note for line, note in shape if line]
    out += facts.scene_notes + facts.budget_notes
    return out


def unconverged_warning(facts: RunFacts, said: bool) -> str | None:
    """UNCONVERGED for a run that did not converge where no line says so yet (`said`: one of "stopped early" or
    Ctrl-C does): its data term had nearly stopped falling but the plateau test had not said so, or its trend could
    not be read. None for a run that converged, and for a live job's final polish (`polish`: it went on from the live
    fit for the step count the live job chose and ended on it, a few dozen steps, too few for the plateau test; the
    trend test says whether its data term still fell). A final run for the steps the user asked for is judged as
    any run. One of report.json's warnings, as every reader counts them (docs/end_of_run.md): `unconverged_line`."""
    polish = facts.polish and facts.stopped_by == "steps"
    return None if said or polish or converged(facts) else unconverged_line(facts.stopped_by)


def early_note(facts: RunFacts) -> str:
    """What the shape's doubts of a run stopped before its fit could settle (too few steps to tell a trend: its
    budget, its step count or Ctrl-C) add: that the shortness alone may explain them. '' for any other run."""
    if (facts.stopped_by not in ("budget", "steps", "interrupted") or facts.continued or converged(facts)
            or not too_short(facts.data_terms)):
        return ""
    return f" (the fit stopped after only {facts.steps} step(s): that alone may explain this; run it longer first)"


__all__ = ["INTERRUPTED", "UNCONVERGED", "ENDED_BY", "unconverged_line", "unconverged_warning",
           "FitNoise", "RunFacts", "noise_deviance", "fit_noise", "late_drop", "late_drop_error",
           "converged", "cpu_share", "lost_share", "pace_share", "cpu_wait", "busy_warning", "warnings",
           "overrun_warning", "misfit_warning", "saturation_warning", "pile_up_line", "coverage_warning",
           "lost_warning", "pieces_warning", "specks_warning", "tunnels_warning", "EXTRA_TUNNELS", "COVERAGE_LIMIT",
           "STILL_FALLING", "STARVED_SHARE", "LEAST_PACE", "OVERRUN_SHARE", "OVERRUN_FLOOR_S", "overrun_tolerance_s",
           "RELATIVE_MISFIT_LIMIT", "MISFIT_SHARE_SIMULATED",
           "MISFIT_Z", "MISFIT_RELATIVE", "MISFIT_MIN_HISTOGRAMS",
           "noise_moments", "misfit_histograms"]
