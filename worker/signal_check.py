"""Did the capture hold enough signal for the fit? A histogram whose return does not clear the carving threshold
proves its whole cone empty, so a capture where many views miss the object carves most of it away, and the fit then
explains the few returns left with a lump: a dim capture (too little laser power, too much ambient light, a dark or
small object) gives a wrong result that the other checks pass, since in so faint a capture any surface lies within
the photon noise, and coverage and pieces are measured on that wrong mesh itself.

The share of histograms with no return at the carving threshold tells it (docs/end_of_run.md, "Too little signal",
gives the measurements behind NO_RETURN_LIMIT).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .carving.returns import first_returns

NO_RETURN_LIMIT = 0.03
"""Share of the usable histograms with no return at the carving threshold above which the result says so: five times
the largest share among the captures of 20 good fits (0.6 %: 9-zone captures, a few zones at the edge of the object;
single-zone and the real pyramid 0 %), a third of the smallest share among bad ones (the torus at 0.3 of its power,
9.4 %: 25.7 mm; at 0.15, 62.5 %: 43 mm; docs/end_of_run.md)."""


@dataclass
class Signal:
    """How many of a capture's histograms hold a return that carving takes as one."""

    histograms: int
    """Usable histograms judged (those the capture holds data in)."""
    no_return: int
    """Of them, those in which no bin clears `threshold`: carving takes their whole cone for empty."""
    threshold: float
    """The carving threshold (standard deviations of the matched-filtered background noise)."""

    @property
    def share(self) -> float:
        """Share of the judged histograms with no return (0 when none was judged)."""
        return self.no_return / self.histograms if self.histograms else 0.0

    def to_dict(self) -> dict:
        return {"histograms": self.histograms, "no_return": self.no_return, "share": self.share,
                "threshold": self.threshold, "limit": NO_RETURN_LIMIT}


def capture_signal(counts: np.ndarray, sensor, threshold: float, usable: np.ndarray | None = None) -> Signal:
    """The returns of `counts` (V, zones, bins), one histogram per view and zone as carving reads them (frames summed),
    at `threshold` with carving's own 'leading' filter; `usable` (V, zones) bool, None for all: histograms without data
    are not judged."""
    found = first_returns(counts, sensor, threshold, "leading", usable=usable).detected
    judged = np.ones(found.shape, bool) if usable is None else np.asarray(usable, bool)
    return Signal(histograms=int(judged.sum()), no_return=int((judged & ~found).sum()), threshold=float(threshold))


def signal_warning(signal: Signal | None) -> str | None:
    """The line saying that too many histograms hold no return at the carving threshold, or None."""
    if signal is None or not signal.share > NO_RETURN_LIMIT:
        return None
    return (f"too little signal: {100 * signal.share:.0f} % of the histograms ({signal.no_return} of "
            f"{signal.histograms}) hold no return above the carving threshold ({signal.threshold:g} noise standard "
            f"deviations; a good capture: under {100 * NO_RETURN_LIMIT:.0f} %), and each of them carved its whole view "
            f"empty, so much of the object may be missing; too little laser power, too much ambient light, or a dark "
            f"or small object: scan again with more power, longer exposure or less ambient light (a lower "
            f"--set field.carve_threshold keeps more but fits noise)")


__all__ = ["Signal", "capture_signal", "signal_warning", "NO_RETURN_LIMIT"]
