"""Which safety stop holds a UR arm, from what the RTDE receive interface reports (RTDE guide): the one predicate the
daemon (`ur._Reading.stop`) and its ur_rtde process (`rtde_child`) both use. While a stop holds the arm its control
script takes no command: ur_rtde gives up at once under a protective or emergency stop (it checks those two in its
waits) but waits for an answer that does not come under a safeguard stop (3 s for "ready", up to 300 s for "done"),
so the ur_rtde process must never send one where the daemon found the arm held; two tests of "held" could disagree.

Standard library only: the ur_rtde process imports it.
"""

from __future__ import annotations

EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP = "emergency stop", "protective stop", "safeguard stop"
SAFETY_VIOLATION, SAFETY_FAULT = "safety violation", "safety fault"
SAFETY_MODES = {1: "normal", 2: "reduced", 3: "protective stop", 4: "recovery", 5: "safeguard stop",
                6: "system emergency stop", 7: "robot emergency stop", 8: "violation", 9: "fault",
                12: "automatic mode safeguard stop", 13: "system three position enabling stop"}
"""UR safety modes by number (RTDE guide)."""
SAFEGUARD_MODES = frozenset({5, 12, 13})
"""Safety modes in which the arm is held by a safeguard (RTDE guide): treated like a protective stop."""
MODE_VIOLATION, MODE_FAULT = 8, 9
"""Safety modes in which the safety system itself stopped the arm (RTDE guide): it must be restarted."""
BIT_SAFEGUARD_STOPPED = 1 << 4
"""safety_status_bits: 'is safeguard stopped' (bit 2 protective, bit 7 emergency: ur_rtde reads those itself)."""
BIT_VIOLATION, BIT_FAULT = 1 << 8, 1 << 9
"""safety_status_bits: 'is violation', 'is fault' (RTDE guide)."""


def safety_fault(safety_mode: int, safety_bits: int) -> str | None:
    """SAFETY_FAULT or SAFETY_VIOLATION when the safety system itself stopped the arm, else None."""
    if safety_mode == MODE_FAULT or safety_bits & BIT_FAULT:
        return SAFETY_FAULT
    if safety_mode == MODE_VIOLATION or safety_bits & BIT_VIOLATION:
        return SAFETY_VIOLATION
    return None


def holding_stop(protective: bool, emergency: bool, safety_mode: int, safety_bits: int) -> str | None:
    """The safety stop that holds the arm, None when none does: a safety fault or violation first (only a restart of
    the arm clears it), then an emergency stop, as it outranks the others when several show, then a protective and a
    safeguard stop. `protective` and `emergency` as ur_rtde's isProtectiveStopped / isEmergencyStopped read them;
    `safety_mode` and `safety_bits` as getSafetyMode / getSafetyStatusBits."""
    fault = safety_fault(safety_mode, safety_bits)
    if fault is not None:
        return fault
    if emergency:
        return EMERGENCY_STOP
    if protective:
        return PROTECTIVE_STOP
    if safety_bits & BIT_SAFEGUARD_STOPPED or safety_mode in SAFEGUARD_MODES:
        return SAFEGUARD_STOP
    return None


ROBOT_MODE_RUNNING = 7
"""UR's robot mode of an arm powered on with its brakes released, ready to run a program (RTDE robot_mode, ur_rtde's
getRobotMode)."""
ROBOT_MODES = {-1: "without a controller", 0: "disconnected", 1: "confirming its safety configuration", 2: "booting",
               3: "powered off", 4: "powering on", 5: "powered on with its brakes on", 6: "in backdrive",
               8: "updating its firmware"}
"""UR's other robot modes (RTDE guide; ur_rtde's getRobotMode), as the arm's state: none runs a program."""


def not_ready(robot_mode: int) -> str | None:
    """Why an arm in `robot_mode` runs no program and what the operator does, as a clause ('the arm is powered off
    (robot mode 3): ...'), or None when it is running. An arm restarted after a safety violation or fault comes back
    powered off: the control script uploaded then does not start, and ur_rtde's connection gives up on it."""
    if robot_mode == ROBOT_MODE_RUNNING:
        return None
    state = ROBOT_MODES.get(robot_mode, "not ready")
    return (f"the arm is {state} (robot mode {robot_mode}): power it on and release the brakes on the teach pendant, "
            f"then resume")
