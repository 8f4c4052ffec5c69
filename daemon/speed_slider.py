"""An arm's speed slider as the runner reads it: the pace of a move's time limit and `status`'s speed keys."""

from __future__ import annotations

import time

from .describe import SLIDER_FULL, slider_note

SLIDER_OLD_S = 5.0  # a speed slider read longer ago than this is shown with its age (`speed_note`)


def speed_slider(arm) -> float | None:
    """The speed slider of an arm whose controller has one (UR), as last read, else None."""
    reading = slider_reading(arm)
    return None if reading is None else reading[0]


def slider_reading(arm) -> tuple[float, float | None] | None:
    """(speed slider, time.monotonic() it was read or None where the arm does not say) of an arm whose controller has
    one (UR), as last read, else None; through the wrapper that tracks a sim sensor's arm pose (`rig.TrackedArm`: its
    `inner` arm)."""
    while arm is not None:
        slider = getattr(arm, "speed_slider", None)
        if slider is not None:
            return float(slider), getattr(arm, "speed_slider_at", None)
        arm = getattr(arm, "inner", None)
    return None


def slider_status(arm) -> dict:
    """Status's speed slider keys, for an arm whose slider is below 100 %: `speed_scaling` (the fraction),
    `speed_note` (what it means; its age too when older than SLIDER_OLD_S) and `speed_scaling_age_s` (seconds since
    it was read, where the arm says); none otherwise."""
    reading = slider_reading(arm)
    if reading is None or reading[0] >= SLIDER_FULL:
        return {}
    slider, at = reading
    age = None if at is None else max(0.0, time.monotonic() - at)
    out = {"speed_scaling": round(slider, 3),
           "speed_note": slider_note(slider, age if age is not None and age > SLIDER_OLD_S else None)}
    if age is not None:
        out["speed_scaling_age_s"] = round(age, 1)
    return out
