"""Whether the views a live fit reads are saturated by pile-up, said in the live status while the scan runs: the
operator can lower the power or move the sensor back before the whole scan is taken that way."""

from __future__ import annotations

import numpy as np

from spadscan.protocol.pileup import SATURATED_SHARE, saturated_histograms

from ..end_of_run import pile_up_line


def live_saturation_warning(counts, valid=None) -> str | None:
    """The live status's line for a capture most of whose histograms so far (`counts` (V, Z, B) detections, `valid`
    (V, Z, B) bool bins to read, default all) are saturated (`protocol.pileup.saturated_histograms`), or None.
    Histograms without a detection are not counted."""
    c = np.maximum(np.asarray(counts, np.float64), 0.0)
    some = c.sum(axis=-1) > 0
    saturated = int((saturated_histograms(c, valid) & some).sum())
    if not some.any() or saturated <= SATURATED_SHARE * int(some.sum()):
        return None
    return pile_up_line(saturated, f"the {int(some.sum())} read so far",
                        ", and the fit can only guess the shape behind it")


__all__ = ["live_saturation_warning"]
