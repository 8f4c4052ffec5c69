"""Ambient light that stops the laser cycles before they reach the object: a bright room, a lamp or sunlight on the
scene.

A first-photon sensor stops each laser cycle at its first photon, so an ambient rate of b photons per bin per cycle
leaves exp(-b r) of the cycles live at bin r (Coates; protocol/pileup.py). The fit models that exactly, but what it
fits gets worse twice over: the object's returns come from the cycles still live when they arrive, so they are
fainter, and they stand on a background b photons per bin higher, whose photon noise buries the fainter of them.
No other check sees it: every return still clears carving's level, no histogram is saturated by its return, and the
fit explains the histograms to their (larger) noise. The simulated duck (lcspc-sim, 256 views) came out 0.74 mm at
the sensor's own ambient light, which stops 8 % of the cycles before its returns, and AMBIENT_EVIDENCE lists what
more light did to it.

The background is the fit's own (`SceneData.background`): a measured capture's read from the bins before any return,
a simulated one's from its sensor model. A sensor without pile-up (`pileup` false) counts every photon: no cycle is
stopped, and nothing is judged here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STOPPED_LIMIT = 0.4
"""Share of the laser cycles that ambient light stops before the object's returns (the median view's) above which the
result says so: between the duck's 29 % (1.55 mm) and 49 % (2.05 mm; AMBIENT_EVIDENCE); every benchmark capture stays
under 12 % (lcspc-sim from 0.7 m), the TMF8820's 128-bin histograms (the real pyramid, the simulated table scenes)
at 0.1 % (docs/end_of_run.md, "Too much ambient light")."""
MAX_FAINTER = 1000
"""The most times fainter a return is said to be by its number; beyond, 'over 1,000x' (light that stops every cycle
would make it infinitely so)."""
AMBIENT_EVIDENCE = "0.74 mm at 8 % of its cycles stopped, 1.55 at 29 %, 2.05 at 49 %, 4.81 at 64 %"
"""What the simulated duck (lcspc-sim, 256 views, 3,000 steps) came out at as ambient light stopped more of its
cycles before its returns: said in the warning, so that the share reads as a consequence."""


@dataclass
class Ambient:
    """How much of the laser's cycles ambient light stopped before the object's returns."""

    background: float
    """Median ambient rate over the histograms with data, photons per bin per cycle."""
    background_photons: float
    """Median photons per bin that rate puts in a histogram (the rate times its cycles)."""
    return_bin: float
    """Median bin of the first returns (as carving finds them: reconstruct's `_return_ranges`)."""
    stopped_share: float
    """Share of the cycles that the ambient light stopped before that bin: 1 - exp(-background * return_bin)."""
    returns: int
    """Histograms with a first return (of which `return_bin` is the median)."""

    def to_dict(self) -> dict:
        return {"background_per_bin_per_cycle": self.background, "background_photons_per_bin":
                self.background_photons, "return_bin": self.return_bin, "stopped_share": self.stopped_share,
                "returns": self.returns, "limit": STOPPED_LIMIT}


def capture_ambient(background: np.ndarray, cycles: np.ndarray, return_bins: np.ndarray, pileup: bool,
                    usable: np.ndarray | None = None) -> Ambient | None:
    """The ambient light of a capture: `background` (V, Z) photons per bin per cycle of each histogram, `cycles` (V,)
    each view's laser cycles, `return_bins` (n,) the bins of the histograms' first returns, `usable` (V, Z) bool
    (None: all) the histograms that hold data. None for a sensor without pile-up (`pileup` false: no cycle stops),
    or where no histogram holds data or none a first return."""
    background = np.asarray(background, np.float64)
    return_bins = np.asarray(return_bins, np.float64).reshape(-1)
    held = np.ones(background.shape, bool) if usable is None else np.asarray(usable, bool).reshape(background.shape)
    return_bins = return_bins[np.isfinite(return_bins)]
    if not pileup or not held.any() or not len(return_bins):
        return None
    rate = float(np.median(background[held]))
    per_view = np.broadcast_to(np.asarray(cycles, np.float64).reshape(-1, 1), background.shape)
    photons = float(np.median((background * per_view)[held]))
    at = max(float(np.median(return_bins)), 0.0)
    stopped = -math.expm1(-max(rate, 0.0) * at)  # exact for the faint light of most captures
    return Ambient(background=rate, background_photons=photons, return_bin=at, stopped_share=stopped,
                   returns=len(return_bins))


def ambient_warning(ambient: Ambient | None) -> str | None:
    """The line saying that ambient light stopped more than STOPPED_LIMIT of the laser cycles before the object's
    returns, or None."""
    if ambient is None or not ambient.stopped_share > STOPPED_LIMIT:
        return None
    live = 1.0 - ambient.stopped_share
    fainter = f"{1 / live:.1f}x" if live * MAX_FAINTER > 1.0 else f"over {MAX_FAINTER:,}x"  # light that stops all
    return (f"too much ambient light: it stopped {100 * ambient.stopped_share:.0f} % of the laser cycles before the "
            f"object's returns (median bin {ambient.return_bin:.0f}; a good capture: under {100 * STOPPED_LIMIT:.0f} "
            f"%), so each return is {fainter} fainter and stands on {ambient.background_photons:.3g} photons "
            f"per bin of background, whose noise blurs its shape (a simulated duck: {AMBIENT_EVIDENCE}); darken the "
            f"room or shade the scene, or scan closer, where the returns arrive before the light stops the cycles")


__all__ = ["Ambient", "capture_ambient", "ambient_warning", "STOPPED_LIMIT"]
