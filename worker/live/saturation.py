"""Whether the views a live fit reads are saturated by pile-up, said in the live status while the scan runs: the
operator can lower the power or move the sensor back before the whole scan is taken that way."""

from __future__ import annotations

import numpy as np

from spadscan.protocol.pileup import mostly_saturated, saturated_count

from ..end_of_run import pile_up_line


def live_saturation_warning(counts, valid=None) -> str | None:
    """The live status's line for a capture most of whose histograms so far (`counts` (V, Z, B) detections, `valid`
    (V, Z, B) bool bins to read, default all) are saturated (`protocol.pileup.mostly_saturated`), or None.
    Histograms without a detection are not counted."""
    saturated, judged = saturated_count(np.maximum(np.asarray(counts, np.float64), 0.0), valid)
    if not mostly_saturated(saturated, judged):
        return None
    return pile_up_line(saturated, f"the {judged} read so far",
                        ", and the fit can only guess the shape behind it")


__all__ = ["live_saturation_warning"]
