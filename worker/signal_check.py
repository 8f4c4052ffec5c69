"""Did the capture hold enough signal for the fit? A histogram in which no bin clears carving's level proves its zone's
whole field of view empty, so a capture where many views miss the object carves most of it away, and the fit then
explains the few returns left with a lump: a dim capture (too little laser power, too much ambient light, a dark or
small object) gives a wrong result that the other checks pass, since in so faint a capture any surface lies within
the photon noise, and coverage and pieces are measured on that wrong mesh itself.

Only the zone aimed at the object is judged: the scan points each view's boresight at its target, so that zone must
see the object, whereas a 9-zone sensor's outer zones look past a small object into empty space (no table behind it)
and see nothing however bright the capture. The share of the aimed zone's histograms with no return at carving's
level tells it (docs/end_of_run.md, "Too little signal", gives the measurements behind NO_RETURN_LIMIT).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .carving.returns import RESCAN, below_default_level, first_returns, weak_level
from .disk_room import names_said

NO_RETURN_LIMIT = 0.05
"""Share of the aimed zone's usable histograms with no return at carving's level above which the result says so.
Measured at that level on about 170 captures (docs/end_of_run.md): every good one (fits under 2 mm, the real pyramid,
the 9-zone sphere and demos without a table) has none; a torus at 0.2 of its laser power 18.8 % (29.5 mm), at 0.15
41.4 % (43 mm). At 0.3 of its power (1.6 %, 4 of 256, 25.7 mm) it stays under the limit: a limit that low would
turn on a handful of histograms, a few views that happen to miss."""
MIN_RETURN_PHOTONS = 3
"""A histogram of the aimed zone holding fewer photons than this in all its bins counts as holding no return,
whatever clears carving's level in it: where the background is nil (a simulation without ambient light) one stray
photon clears any level, and a capture of 15 photons over 16 views (8 of them empty) reconstructed to a 34 mm lump
with nothing said. Every benchmark capture holds over 1,000 photons in each of them."""


@dataclass
class Signal:
    """How many of the histograms of a capture's aimed zone hold a return at the level carving stops at."""

    histograms: int
    """Usable histograms judged: those of the zone(s) aimed at the object that the capture holds data in."""
    no_return: int
    """Of them, those in which no bin clears `threshold` (carving took their zone's whole field of view for empty),
    or that hold fewer than MIN_RETURN_PHOTONS photons in all."""
    threshold: float
    """Carving's level for a return (noise standard deviations of the matched-filtered background): the weak
    threshold off a table, the carving threshold on one."""
    zones: tuple[int, ...] = (0,)
    """The zones judged (0-based): those whose field of view holds the sensor's boresight."""
    n_zones: int = 1
    """How many zones the sensor has."""
    default_threshold: float | None = None
    """Carving's default level, where the run's thresholds were set below it (`--set`), else None."""
    default_no_return: int | None = None
    """Of the judged histograms, those with no return at `default_threshold` (None where it is None): a capture too
    faint by the default level stays faint when the level is lowered, and what then clears it is partly noise."""

    @property
    def share(self) -> float:
        """Share of the judged histograms with no return (0 when none was judged)."""
        return self.no_return / self.histograms if self.histograms else 0.0

    @property
    def default_share(self) -> float | None:
        """Share of the judged histograms with no return at carving's default level, or None where the run carved at
        that level or above."""
        if self.default_no_return is None:
            return None
        return self.default_no_return / self.histograms if self.histograms else 0.0

    def to_dict(self) -> dict:
        return {"histograms": self.histograms, "no_return": self.no_return, "share": self.share,
                "threshold": self.threshold, "zones": list(self.zones), "n_zones": self.n_zones,
                "limit": NO_RETURN_LIMIT, "default_threshold": self.default_threshold,
                "default_no_return": self.default_no_return, "default_share": self.default_share}


def aimed_zones(sensor) -> tuple[int, ...]:
    """The zones whose field of view holds the boresight (+z), where the scan aims each view at its target (several
    where zones meet on it); when none does, the one whose centre lies nearest it."""
    boresight = np.array([0.0, 0.0, 1.0])
    held = tuple(i for i, zone in enumerate(sensor.zones) if bool(zone.holds(boresight)))
    if held:
        return held
    return (int(np.argmax([_centre(zone)[2] for zone in sensor.zones])),)


def _centre(zone) -> np.ndarray:
    """Unit direction (sensor frame) of a zone's centre: a cone's axis, a rectangle's middle."""
    if zone.kind == "rect":
        d = np.array([0.5 * sum(zone.tan_x), 0.5 * sum(zone.tan_y), 1.0])
    else:
        d = np.asarray(zone.axis, float)
    return d / np.linalg.norm(d)


def capture_signal(counts: np.ndarray, sensor, threshold: float, usable: np.ndarray | None = None,
                   weak_threshold: float | None = None,
                   defaults: tuple[float, float | None] | None = None) -> Signal:
    """The returns of `counts` (V, zones, bins), one histogram per view and zone as carving reads them (frames summed),
    in the aimed zone(s), at carving's level (`returns.weak_level` of `threshold` and `weak_threshold`, as carving is
    given them) with its 'leading' filter; `usable` (V, zones) bool, None for all: histograms without data are not
    judged. `defaults`: the default (threshold, weak threshold) as carving would be given them, or None; where the
    run's put carving's level below theirs (`returns.below_default_level`, the rule the carving error advises by
    too), the histograms are judged at the default level as well."""
    level = weak_level(threshold, weak_threshold)
    zones = aimed_zones(sensor)
    judged = None if usable is None else np.asarray(usable, bool)[:, zones]
    enough = np.asarray(counts)[:, zones].sum(-1) >= MIN_RETURN_PHOTONS  # whatever the level

    def no_return(at: float) -> tuple[int, int]:
        found = first_returns(counts, sensor, at, "leading", usable=usable).detected[:, zones] & enough
        held = np.ones(found.shape, bool) if judged is None else judged
        return int(held.sum()), int((held & ~found).sum())

    histograms, missed = no_return(level)
    lowered = defaults is not None and below_default_level(threshold, weak_threshold, *defaults)
    default_level = weak_level(*defaults) if lowered else None
    return Signal(histograms=histograms, no_return=missed, threshold=float(level), zones=zones,
                  n_zones=len(sensor.zones), default_threshold=float(default_level) if lowered else None,
                  default_no_return=no_return(default_level)[1] if lowered else None)


def signal_warning(signal: Signal | None) -> str | None:
    """The line saying that too many of the aimed zone's histograms hold no return at carving's level, or at its
    default level where the run's thresholds were set lower (`lowered_warning`), or None."""
    if signal is None:
        return None
    if not signal.share > NO_RETURN_LIMIT:
        return lowered_warning(signal)
    return (f"too little signal: {100 * signal.share:.0f} % of the histograms ({signal.no_return} of "
            f"{signal.histograms}){_where(signal)} hold no return above carving's level ({signal.threshold:g} noise "
            f"standard deviations; a good capture: none) or hold fewer than {MIN_RETURN_PHOTONS} photons, and each "
            f"such view says nothing of the object or carved its whole field of view empty, so much of the object may "
            f"be missing; too little laser power, too much ambient light, a dark or small "
            f"object, or views aimed past it: {RESCAN} ({_lower_or_lowered(signal)})")


def _lower_or_lowered(signal: Signal) -> str:
    """The aside of the too-little-signal line: lower thresholds to try, or, where the run's put carving's level below
    the default one already (`capture_signal`), what the default level finds (lower still, noise passes for returns)."""
    if signal.default_share is None:
        return ("`spadscan reconstruct` with field.carve_threshold and field.carve_weak_threshold set lower by --set, "
                "the second at most the first, keeps more but fits noise")
    return (f"its thresholds are set below their defaults already: at the default level "
            f"({signal.default_threshold:g}) {100 * signal.default_share:.0f} % hold none; lower still, noise passes "
            f"for returns")


def lowered_warning(signal: Signal) -> str | None:
    """The line saying that the capture is too faint by carving's default level although the run, its thresholds set
    lower, found returns in enough histograms: at the lowered level photon noise clears the threshold too, so the
    hull and the fit hold noise (a dim torus refitted at 3 and 2 noise standard deviations: no view empty, 41-100
    mm; a 6 mm wand: 24.7 mm); None where the run carved at the default level or the capture clears it."""
    share = signal.default_share
    if share is None or not share > NO_RETURN_LIMIT:
        return None
    return (f"faint returns: {100 * share:.0f} % of the histograms ({signal.default_no_return} of "
            f"{signal.histograms}){_where(signal)} hold no return above carving's default level "
            f"({signal.default_threshold:g} noise standard deviations; a good capture: none); this run carved at "
            f"{signal.threshold:g}, its thresholds set lower with --set, where photon noise passes for returns too, "
            f"so the mesh may be partly noise (stray blobs in preview.png), and lower thresholds will not help: "
            f"{RESCAN} (a thin, small or dark object: more frames per pose)")


def _where(signal: Signal) -> str:
    """Which zone(s) were judged, for a sensor of several: '' for one zone."""
    if signal.n_zones <= 1:
        return ""
    names = [str(z + 1) for z in signal.zones]  # counted from 1, as the sensor's channels are
    listed = names_said(names, last_and=True, most=None)
    return (f" of zone {listed} of {signal.n_zones}, the one aimed at the object," if len(names) == 1 else
            f" of zones {listed} of {signal.n_zones}, those aimed at the object,")


__all__ = ["Signal", "aimed_zones", "capture_signal", "lowered_warning", "signal_warning", "NO_RETURN_LIMIT"]
