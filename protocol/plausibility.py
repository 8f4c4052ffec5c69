"""Histograms no sensor could produce: refused before a reconstruction or a baseline fits them, or warned about.

A reconstruction fits whatever counts it is given. A capture whose every bin holds 2**32-1 (a corrupt file, a
converter that wrote -1 as unsigned) used to reconstruct with exit status 0, every loss term exactly 0 (saturated
bins are left out of the fit, so nothing was left to fit) and a meaningless mesh. These histograms (one zone of one
measurement) are implausible:

- saturated: every bin at the counter's limit (the sensor model's max_count, at most the uint32 maximum 2**32-1);
- over the counter: a bin above max_count, which the sensor's counter cannot hold (above 2**24-1 for the TMF8820's
  24-bit counters);
- all zero: not one count, where every real sensor sees ambient light and dark counts in every bin;
- all equal: every bin the same non-zero count, which photon noise never gives;
- over its cycles: for a sensor that stops at its first photon in each laser cycle (the sensor model's `pileup`),
  more counts in all than CYCLES_MARGIN x its laser cycles (`cycles`), where at most one count a cycle is possible
  (one bin raised to 50,000 in a 5,000-cycle histogram pulled a fit's albedo down and spoiled its fit of the other
  histograms); more than the cycles themselves (SIMULATED_CYCLES_MARGIN) for histograms this project's simulator
  drew (`cycles_margin`). The bins clipped at the counter's limit are left out of the sum (they are warned about as
  clipped).

The bins a sensor model ignores (the TMF8820's bin 0) are left out of these tests. A capture whose histograms are
all implausible is refused (CaptureError); one where only some are gets a one-line warning, as does one with bins
clipped at the counter's limit in otherwise plausible histograms (those bins carry no information). The real
TMF8820 captures of LCSPCData (ambient ~120 counts a bin, peaks below 10**6, at most 1.73 million counts in all of
the 4 million cycles the model gives a frame) and simulated captures (at most 0.96 of their cycles) pass.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import CaptureError

UINT32_MAX = 2**32 - 1

KINDS = ("over the counter", "saturated", "all zero", "all equal", "over its cycles")
"""Implausible kinds, in the order a histogram is classified (one kind each)."""

CYCLES_MARGIN = 1.5
"""A first-photon histogram is implausible above this many counts per laser cycle of the sensor model. Not 1: a
model's cycles can be an estimate (the TMF8820's 4 million are known to +-0.7 million per frame, so a bright real
frame could hold more counts than 4 million); a simulated one never exceeds 1, and a corrupt count far exceeds 1.5."""

SIMULATED_CYCLES_MARGIN = 1.0
"""The bound for histograms drawn by this project's simulator (`spadscan simulate`, the daemon's simulated sensor):
it draws a first-photon histogram as one multinomial outcome per cycle, so its counts never exceed its cycles, which
it knows exactly. A simulated capture scaled to 1.45 x its cycles passed the 1.5 margin unremarked."""


def cycles_margin(simulated: bool) -> float:
    """The margin of the "over its cycles" kind for a capture's histograms: SIMULATED_CYCLES_MARGIN for those this
    project's simulator drew (`capture_format.drawn_by_simulator`), else CYCLES_MARGIN (estimated cycles)."""
    return SIMULATED_CYCLES_MARGIN if simulated else CYCLES_MARGIN


@dataclass(frozen=True)
class CountSurvey:
    """What `survey_counts` found in a set of histograms."""

    histograms: int
    """Histograms looked at (measurements x zones)."""
    limit: int
    """The counter's limit: the sensor model's max_count (at most 2**32-1)."""
    implausible: dict[str, int] = field(default_factory=dict)
    """Histograms of each implausible kind (KINDS), kinds with none left out."""
    clipped: int = 0
    """Otherwise plausible histograms with some bins at the counter's limit."""
    cycles: int | None = None
    """The laser cycles of a first-photon sensor's histogram (the kind "over its cycles"), or None: no such test."""
    margin: float = CYCLES_MARGIN
    """Counts per cycle above which a histogram is "over its cycles" (`cycles_margin`)."""

    @property
    def n_implausible(self) -> int:
        return sum(self.implausible.values())

    def refusal(self, where: str) -> str | None:
        """The one-line reason to refuse the capture (every histogram implausible), or None."""
        if self.histograms == 0 or self.n_implausible < self.histograms:
            return None
        found = [kind for kind, n in self.implausible.items() if n]
        if len(found) == 1:
            what = f"all {self.histograms:,} histograms {self._phrases()[found[0]][0]}"
        else:
            what = f"of its {self.histograms:,} histograms, {self._listed()}"
        return f"{where}: no sensor could have produced these counts: {what}; refusing to fit them"

    def warning(self, where: str) -> str | None:
        """A one-line warning when only some histograms are implausible or clipped, or None."""
        if self.refusal(where) is not None:
            return None
        parts = []
        if self.n_implausible:
            parts.append(f"{self.n_implausible:,} of {self.histograms:,} histograms no sensor could have produced "
                         f"({self._listed()}), left out")
        if self.clipped:
            parts.append(f"{self.clipped:,} of {self.histograms:,} histograms with bins clipped at the counter's "
                         f"limit {self.limit:,}")
        return f"{where}: {'; '.join(parts)}" if parts else None

    def _phrases(self) -> dict[str, tuple[str, str]]:
        """Each kind as (what 'all N histograms' do, how a count of them is labelled)."""
        limit = f"the {_bits(self.limit)} counter's limit {self.limit:,}"
        cycles = f"their {self.cycles or 0:,} laser cycles"
        cycles = cycles if self.margin == 1 else f"{self.margin:g} x {cycles}"
        return {
            "over the counter": (f"hold counts above {limit}", f"with counts above {limit}"),
            "saturated": (f"are saturated (every bin at {limit})", f"saturated (every bin at {limit})"),
            "all zero": ("are all zero", "all zero"),
            "all equal": ("have every bin equal", "with every bin equal"),
            "over its cycles": (f"hold more counts than {cycles} (a sensor that stops at its first photon counts "
                                f"at most one a cycle)", f"with more counts than {cycles}"),
        }

    def _listed(self) -> str:
        """'3 all zero, 2 with every bin equal': the implausible kinds found, with their counts."""
        phrases = self._phrases()
        return ", ".join(f"{n:,} {phrases[kind][1]}" for kind, n in self.implausible.items() if n)


def first_photon_cycles(sensor) -> int | None:
    """The laser cycles that bound a histogram's counts for a SensorModel that stops at its first photon in each
    cycle (`pileup`), else None (a sensor that counts every photon has no such bound): the `cycles` of the checks
    below."""
    return int(sensor.cycles) if sensor.pileup else None


def survey_counts(hists: np.ndarray, max_count: int = UINT32_MAX, ignore_bins=(), cycles: int | None = None,
                  margin: float = CYCLES_MARGIN) -> CountSurvey:
    """Classify histograms (..., bins) of whole counts: see the module's docstring. `max_count`: the sensor's
    largest count; `ignore_bins`: bins left out of the tests (kept when they are all the bins there are);
    `cycles`: the laser cycles of one histogram of a first-photon sensor (`first_photon_cycles`), None for none;
    `margin`: counts per cycle allowed (`cycles_margin`)."""
    kind, limit, clipped = _classify(hists, max_count, ignore_bins, cycles, margin)
    found = {k: int((kind == i).sum()) for i, k in enumerate(KINDS) if (kind == i).any()}
    return CountSurvey(kind.size, limit, found, int(clipped.sum()), None if cycles is None else int(cycles),
                       float(margin))


def implausible(hists: np.ndarray, max_count: int = UINT32_MAX, ignore_bins=(), cycles: int | None = None,
                margin: float = CYCLES_MARGIN) -> np.ndarray:
    """Whether each histogram (..., bins) is one no sensor could have produced (any of KINDS): the mask (...) of
    those a reconstruction must leave out. An all-zero histogram read as "no return" would prove its zone's whole
    field of view empty and carve the object away. `cycles` and `margin` as in `survey_counts`."""
    hists = np.asarray(hists)
    return (_classify(hists, max_count, ignore_bins, cycles, margin)[0] >= 0).reshape(hists.shape[:-1])


def _classify(hists: np.ndarray, max_count: int, ignore_bins, cycles: int | None = None,
              margin: float = CYCLES_MARGIN) -> tuple[np.ndarray, int, np.ndarray]:
    """(the index in KINDS of each histogram's first kind, -1 for none; the count limit; which of the plausible
    ones have a bin clipped at the limit), over the histograms (..., bins) flattened."""
    hists = np.asarray(hists)
    if hists.ndim < 1 or hists.dtype.kind not in "iu":
        raise ValueError(f"histograms must be an integer array (..., bins), got {hists.dtype} {hists.shape}")
    limit = int(min(max_count, UINT32_MAX))
    keep = [b for b in range(hists.shape[-1]) if b not in set(ignore_bins)] or list(range(hists.shape[-1]))
    h = hists.reshape(-1, hists.shape[-1])[:, keep]
    kind = np.full(h.shape[0], -1)
    if h.shape[0] == 0 or h.shape[1] == 0:
        return kind, limit, np.zeros(h.shape[0], bool)
    hi, lo = h.max(axis=1), h.min(axis=1)
    tests = {"over the counter": hi > limit, "saturated": lo >= limit, "all zero": hi == 0, "all equal": hi == lo,
             "over its cycles": _over_cycles(h, limit, cycles, margin)}
    for i, name in reversed(list(enumerate(KINDS))):  # the first kind in KINDS wins
        kind[tests[name]] = i
    return kind, limit, (h >= limit).any(axis=1) & (kind < 0)


def _over_cycles(h: np.ndarray, limit: int, cycles: int | None, margin: float = CYCLES_MARGIN) -> np.ndarray:
    """Which histograms (n, bins) hold more counts than `margin` x `cycles` (none when `cycles` is None). Bins
    at the counter's limit are left out of the sum: a histogram with some is told as clipped (its other bins are
    fitted), or, with all, as saturated."""
    if cycles is None:
        return np.zeros(h.shape[0], bool)
    total = np.where(h < limit, h, 0).sum(axis=1, dtype=np.float64)
    return total > margin * float(cycles)


def check_counts(hists: np.ndarray, max_count: int, ignore_bins, where: str, cycles: int | None = None,
                 margin: float = CYCLES_MARGIN) -> str | None:
    """Refuse (CaptureError, one line naming `where`) histograms no sensor could have produced; return a one-line
    warning when only some are (or some bins are clipped), else None. `cycles` and `margin` as in `survey_counts`."""
    survey = survey_counts(hists, max_count, ignore_bins, cycles, margin)
    reason = survey.refusal(where)
    if reason is not None:
        raise CaptureError(reason)
    return survey.warning(where)


def _bits(limit: int) -> str:
    """'24-bit' for a limit of 2**24-1; 'sensor's' for one that is not a power of two less one."""
    bits = limit.bit_length()
    return f"{bits}-bit" if limit == 2**bits - 1 else "sensor's"
