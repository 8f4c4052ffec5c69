"""The safety stops an arm reports, named as the pause reasons name them, and what the operator does to clear each
(firmware_notes/safety.md, "Stops"): they call for different things at the rig, so a reason must not mistake one
for another. A safety violation or fault (UR safety modes 8 and 9: the safety system itself stopped the arm) is not
unlocked like a protective stop: the arm's safety system must be restarted.

An arm that can tell which stop holds it (the UR arm, the sim arm) names it in `ArmState.safety_stop`; the runner
reads the name with `stop_name`, which also serves an arm that only sets `protective_stop`.
"""

from __future__ import annotations

from spadscan.daemon.arm.safety_hold import (EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP, SAFETY_FAULT,
                                             SAFETY_VIOLATION)
from spadscan.daemon.devices import ArmState

__all__ = ["EMERGENCY_STOP", "PROTECTIVE_STOP", "SAFEGUARD_STOP", "SAFETY_VIOLATION", "SAFETY_FAULT", "SAFETY_STOP",
           "TO_CLEAR", "stop_name", "clear_advice"]
SAFETY_STOP = "safety stop"
"""The name for an arm that says it is stopped for safety but not which stop it is."""
TO_CLEAR = {
    EMERGENCY_STOP: "release the emergency stop button and reset the arm on the teach pendant",
    PROTECTIVE_STOP: "fix the cause and unlock the protective stop on the teach pendant",
    SAFEGUARD_STOP: "reset the safeguard",
    SAFETY_VIOLATION: ("find the violated limit in the teach pendant's log, then restart the arm from the pendant (its "
                       "safety system must be restarted after a violation; the arm comes back powered off: power it "
                       "on and release the brakes)"),
    SAFETY_FAULT: ("find the cause in the teach pendant's log, then restart the arm from the pendant (its safety "
                   "system must be restarted after a fault; the arm comes back powered off: power it on and release "
                   "the brakes)"),
    SAFETY_STOP: "clear the stop on the teach pendant",
}
"""What the operator does before `spadscan ctl resume`, by stop."""


def stop_name(state: ArmState) -> str | None:
    """Which safety stop holds the arm in `state` (None: none); SAFETY_STOP for an arm that cannot tell which."""
    if state.safety_stop is not None:
        return state.safety_stop
    return SAFETY_STOP if state.protective_stop else None


def clear_advice(stop: str) -> str:
    """What to do about `stop` before resuming, as a clause: '<what to do>, then resume'."""
    return f"{TO_CLEAR.get(stop, TO_CLEAR[SAFETY_STOP])}, then resume"
