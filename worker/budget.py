"""A time budget that bounds a whole reconstruction, from its start to its report.

`--budget-s` (and the config key `default_budget_s`) is the wall time of the whole run: loading the capture and
building the model, training, extracting the mesh, the metrics and the pictures share it. The run keeps back what
the stages after training are expected to take (`EndCosts`, timed on this machine once the model is built) and
trains for the rest; when training ends, the mesh resolution and the number of metric points are chosen to fit what
is left (coarser or fewer than the config's when time is short; the report says so), and the metrics stop at a
deadline however far their forecast falls short (metrics.mesh_metrics). The contract, tested: the run
ends within 10 % or 10 s of its budget, whichever is larger.

Seconds are wall seconds (time.perf_counter) throughout.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable

FIXED_S = 8.0
"""Seconds kept back for what does not scale with the mesh or the points: the preview, error-versus-time, fit and
coverage pictures, report.html, the 3D view. Measured on the 2-core machine under a load of 11: 5-7 s (the off-screen
renderer's start alone 2 s) before the coverage picture, which takes 1.8-2.4 s more on the idle machine (its drawing).
That was 9 s with the count of the views that see each sample point of the mesh (the coverage check) in it, about a
second then; the count is now timed by a probe on the views the report counts (`EndCosts.coverage_s`), since a
capture's views made it grow (20 s at 10,000 views when every view was counted). With 8 s and the count in it, the
demo's final run on the idle machine cut its metrics to 270,000 points (its pictures took 9.7 s). The returns held
against the mesh (`lost_returns`, 0.1-0.3 s idle, on at most 256 views whatever the capture's size) are in it too."""
COVERAGE_S = 1.0
"""Seconds of the coverage count before a probe is timed (a 256-view capture's on the idle machine)."""
COMPLETION_SHARE = 0.1
"""What a view beyond those the coverage counts for every point costs, as a share of one of those, at least: it is
counted only for the points those see fewer than three times (coverage.spread_counts), and the probe's own counts say
what share of the points that is (`EndCosts.time_coverage`). Measured at 10,000 views (one thread, a loaded 2-core
machine): 0.03 of one on a well seen sphere, 0.05 on a poor fit with a quarter of its surface seen by few views; but
0.56 on a flat plate seen from close by narrow views, where every point is seen by few of the spread views."""
COVERAGE_DEFAULT_VIEWS = 256
"""The views COVERAGE_S is a figure for: before a probe, the count's default grows with the views it reads."""
COVERAGE_PICTURE_S = 2.5
"""The coverage picture is drawn only when this much is left of the budget beyond what the metrics and the normals
picture still need: a short budget goes to the mesh and its figures first (the idle machine's 1.8-2.4 s)."""
NORMALS_PICTURE_S = 3.0
"""And for the normal-error picture, drawn when there is a ground truth (3 s under that load)."""
MESH_S_PER_CELL = 1e-7
"""Marching-cubes seconds per grid cell before a probe is timed (the fast preset: 1.6 s at 256 cells a side)."""
METRICS_S_PER_POINT = 5e-5
"""Metric seconds per sample point and mesh before a probe is timed (300,000 points: 7-15 s, more when much of a
mesh lies far from the other; the per-vertex normal error samples the ground truth once more)."""
MAX_END_SHARE = 0.5
"""The stages after training keep back at most this share of what is left of the budget once the model is built:
beyond it they are made cheaper (a coarser mesh, fewer points), so that training keeps the other half."""
MIN_MESH_RESOLUTION = 32
"""Coarsest final mesh, cells along the longest side."""
MESH_STEPS = 8
"""A mesh too fine for the time left steps down by 1/MESH_STEPS of its resolution at a time (256: 224, 192, ...).
Halving lost half the resolution for a moment's shortfall: training keeps back what the end is estimated to take,
and ending a fraction of a second late put a 120 s run's mesh at 128 cells, 14.7 s then left unused."""
MIN_METRIC_POINTS = 5_000
"""Fewest metric sample points per mesh."""
PROBE_RESOLUTIONS = (32, 64)
"""Mesh resolutions of the probes that time extraction on this machine and this model."""
PROBE_POINTS = 5_000
"""Sample points of the probe that times the metrics on this machine."""
SAFETY = 1.5
"""Margin on extrapolated times (a probe's overheads do not all scale, and far surfaces slow the metrics)."""
PROBE_REPEAT_UNDER_S = 1.0
"""A probe that took less than this is timed once more and the faster of the two kept. A probe takes milliseconds
and is extrapolated 8 to 512 times (a 64-cell mesh to 256 cells, 5,000 metric points to 300,000), so a burst of
another process's work during it, or a first call's one-time work, multiplied into tens of seconds kept back for
nothing: on the loaded 2-core machine a 64-cell probe of the mug took 0.22 s once where repeats took 0.04-0.05 s,
and the run kept 21 s back for a 256-cell mesh that took 1.0 s. A longer probe is timed once: a moment's load
weighs less against it, and the paper preset's render of two views alone takes a minute on 2 cores."""


def process_started() -> float:
    """When this process started, as a time.perf_counter reading (Linux: from /proc, so that the interpreter's
    start and the imports count against a budget too); elsewhere, now."""
    now = time.perf_counter()
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        age = uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22 of stat: start, ticks after boot
    except (OSError, ValueError, IndexError):
        return now
    return now - age if 0 <= age < 3600 else now


@dataclass
class RunClock:
    """The whole run's budget: `budget_s` seconds from `start` (a `clock()` reading); None: unbounded."""

    budget_s: float | None
    start: float
    clock: Callable[[], float] = time.perf_counter

    def elapsed(self) -> float:
        return self.clock() - self.start

    def left(self) -> float:
        """Seconds left of the budget (may be negative); inf without one."""
        return math.inf if self.budget_s is None else self.budget_s - self.elapsed()


@dataclass
class EndCosts:
    """What the stages after training are expected to take: seconds per marching-cubes cell, per metric point and
    mesh, and the fixed part (pictures, report). Probes replace the defaults with timings on this machine."""

    mesh_s_per_cell: float = MESH_S_PER_CELL
    mesh_fixed_s: float = 0.0
    """Seconds of an extraction that do not grow with the cells (the model's own set-up of its grid)."""
    metrics_s_per_point: float = METRICS_S_PER_POINT
    """Metric seconds per sample point and mesh, taken as in proportion to the points: where their time grows
    faster (a poor mesh far from the ground truth), the final metrics' deadline holds them (metrics.mesh_metrics)."""
    fixed_s: float = FIXED_S
    fit_check_s: float = 0.0
    """Seconds of the fit check (the views it renders against the photon noise), once a probe has timed a render;
    its 32 views rendered 4 times take a second or more on 2 cores, which FIXED_S does not hold."""
    view_render_s: float = 0.0
    """Seconds of one view's render, once a probe has timed one (0: not timed)."""
    coverage_s: float = COVERAGE_S
    """Seconds of the count of the views that see each sample point of the final mesh (the report's coverage)."""
    probed: list[str] = field(default_factory=list)

    def pictures_s(self) -> float:
        """The stages after the mesh that do not scale with it or with the points: the pictures, the fit check, the
        coverage count."""
        return self.fixed_s + SAFETY * (self.fit_check_s + self.coverage_s)

    def mesh_s(self, resolution: int) -> float:
        return SAFETY * (self.mesh_fixed_s + self.mesh_s_per_cell * resolution ** 3)

    def metrics_s(self, points: int) -> float:
        """Metrics of one final mesh: both directions, and the per-vertex normal error against as many points."""
        return SAFETY * self.metrics_s_per_point * 2 * max(points, 0)

    def time_mesh(self, timings: dict[int, float]) -> None:
        """Mesh extractions took `timings` {resolution: seconds}: with two or more, a fixed part and a part that
        grows with the cells (least squares, neither negative); with one, all of it grows with the cells."""
        r = sorted(timings)
        x = [float(k) ** 3 for k in r]
        t = [max(float(timings[k]), 0.0) for k in r]
        if len(r) >= 2:
            mx, mt = sum(x) / len(x), sum(t) / len(t)
            var = sum((a - mx) ** 2 for a in x)
            per_cell = max(sum((a - mx) * (b - mt) for a, b in zip(x, t)) / var, 0.0) if var > 0 else 0.0
            fixed = max(mt - per_cell * mx, 0.0)
        else:
            per_cell, fixed = t[0] / x[0], 0.0
        self.mesh_s_per_cell, self.mesh_fixed_s = per_cell, fixed
        self.probed.append("mesh " + ", ".join(f"{k}: {v:.2f} s" for k, v in zip(r, t)))

    def time_metrics(self, points: int, seconds: float) -> None:
        """Metrics of one mesh against the ground truth on `points` points took `seconds`."""
        self.metrics_s_per_point = max(float(seconds), 0.0) / (2 * points)
        self.probed.append(f"metrics {points}: {seconds:.2f} s")

    def time_fit_check(self, seconds: float, views_rendered: int, renders_needed: int) -> None:
        """Rendering `views_rendered` views took `seconds`: the fit check renders `renders_needed` views."""
        self.view_render_s = max(seconds, 0.0) / max(views_rendered, 1)
        self.fit_check_s = self.view_render_s * renders_needed
        self.probed.append(f"fit check {renders_needed} view renders: {self.fit_check_s:.2f} s")

    def coverage_views(self, spread_views: int, other_views: int) -> None:
        """Before a probe times it (or where none can: no surface yet), the coverage count's default for a report
        that counts `spread_views` views for every point and `other_views` more for the few points: COVERAGE_S is a
        figure for COVERAGE_DEFAULT_VIEWS views, so it is scaled by the views, the others at COMPLETION_SHARE."""
        per_view = COVERAGE_S / COVERAGE_DEFAULT_VIEWS
        self.coverage_s = per_view * (max(spread_views, 0) + COMPLETION_SHARE * max(other_views, 0))

    def time_coverage(self, seconds: float, views_timed: int, spread_views: int, other_views: int,
                      few_share: float | None = None) -> None:
        """Counting `views_timed` views for every sample point took `seconds`: the report counts `spread_views`
        views so, and `other_views` more only for the points those see fewer than three times: `few_share` of the
        points (0 to 1, the probe's estimate; None: unknown), each other view costing that share of a spread view,
        and never less than COMPLETION_SHARE."""
        per_view = max(float(seconds), 0.0) / max(views_timed, 1)
        share = COMPLETION_SHARE
        if few_share is not None and math.isfinite(few_share):
            share = min(max(float(few_share), COMPLETION_SHARE), 1.0)
        self.coverage_s = per_view * (spread_views + share * other_views)
        self.probed.append(f"coverage {spread_views} + {other_views} views at {share:.2f}: {self.coverage_s:.2f} s")

    def end_s(self, resolution: int, points: int | None, checkpoint: tuple[int, int] | None = None) -> float:
        """Seconds the stages after training take at `resolution` and `points` (None: no ground truth), plus the
        last checkpoint's evaluation (`checkpoint` = its mesh resolution and points) where there is one."""
        total = self.pictures_s() + self.mesh_s(resolution)
        if points:
            total += self.metrics_s(points)
        if checkpoint is not None:
            total += self.checkpoint_s(*checkpoint)
        return total

    def checkpoint_s(self, resolution: int, points: int) -> float:
        """Seconds of one checkpoint's evaluation: a mesh at `resolution` scored on `points` points (both ways)."""
        return self.mesh_s(resolution) + self.metrics_s(points)


def probe_seconds(run: Callable[[], object], clock: Callable[[], float]) -> tuple[float, object]:
    """(wall seconds, result) of `run()`, a probe of an end stage: the faster of two calls where the first took
    under PROBE_REPEAT_UNDER_S (the result is the last call's)."""
    t0 = clock()
    result = run()
    seconds = clock() - t0
    if seconds < PROBE_REPEAT_UNDER_S:
        t0 = clock()
        result = run()
        seconds = min(seconds, clock() - t0)
    return seconds, result


def training_budget(clock: RunClock, end_s: float) -> float | None:
    """Seconds left for training once `end_s` is kept back (at most MAX_END_SHARE of what is left); None without a
    budget. Never below a hundredth of a second (a run makes at least one step)."""
    if clock.budget_s is None:
        return None
    left = clock.left()
    keep = min(end_s, MAX_END_SHARE * max(left, 0.0))
    return max(0.01, left - keep)


def mesh_resolution_within(costs: EndCosts, want: int, seconds: float) -> int:
    """The finest resolution up to `want` whose extraction fits in `seconds` (stepping down from `want` by an
    eighth of it, `MESH_STEPS`; at least MIN_MESH_RESOLUTION; `want` itself when it fits)."""
    want = int(want)
    step = max(1, want // MESH_STEPS)
    r = want
    while r > MIN_MESH_RESOLUTION and costs.mesh_s(r) > seconds:
        r = max(MIN_MESH_RESOLUTION, r - step)
    return min(r, want)


def coverage_picture_within(costs: EndCosts, seconds: float, scored: bool) -> bool:
    """Whether the coverage picture (COVERAGE_PICTURE_S) fits in `seconds` and leaves, on a run scored against a
    ground truth, what must still follow it: the metrics on MIN_METRIC_POINTS and the normals picture. The picture
    goes before the metrics are cut any further."""
    still_needed = costs.metrics_s(MIN_METRIC_POINTS) + NORMALS_PICTURE_S if scored else 0.0
    return seconds - still_needed >= COVERAGE_PICTURE_S


def fit_views_within(costs: EndCosts, want: int, renders: int, seconds: float, least: int) -> int:
    """The most fit-check views up to `want`, each rendered `renders` times, that fit in `seconds` (at least `least`,
    the views the fit picture shows; `want` where no render was timed)."""
    per_view = SAFETY * costs.view_render_s * max(renders, 1)
    if per_view <= 0 or per_view * want <= seconds:
        return int(want)
    return int(min(want, max(least, int(max(seconds, 0.0) / per_view))))


def metric_points_within(costs: EndCosts, want: int, seconds: float) -> int:
    """The most metric points up to `want` that fit in `seconds` (at least MIN_METRIC_POINTS, rounded down to a
    thousand when cut)."""
    if costs.metrics_s(want) <= seconds:
        return int(want)
    unit = max(costs.metrics_s(1), 1e-15)
    fit = int(max(seconds, 0.0) / unit * (1 + 1e-9))
    return int(min(want, max(MIN_METRIC_POINTS, fit // 1000 * 1000)))


__all__ = ["process_started", "RunClock", "EndCosts", "training_budget", "mesh_resolution_within",
           "fit_views_within", "metric_points_within", "coverage_picture_within", "MIN_MESH_RESOLUTION",
           "MIN_METRIC_POINTS", "PROBE_RESOLUTIONS", "PROBE_POINTS", "probe_seconds"]
