"""Signals for the commands that write one folder from start to end (simulate, import-lcspc, reconstruct) and the
dashboard."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Callable


@contextlib.contextmanager
def terminate_as_interrupt():
    """Within the block, SIGTERM (`kill`, a service stop, a time limit) ends the command as Ctrl-C does: the command's
    clean-up runs and the capture's manifest says it was interrupted. Python's default for SIGTERM is to die on the
    spot, which left a half-written capture saying 'running', as if still being written.

    Only the main thread can set a handler; elsewhere (a test calling a command from a thread) the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class TrainingStop:
    """`stop()` for a trainer: true once the user pressed Ctrl-C while it trained. A first Ctrl-C while training ends
    the training at its next step and keeps the run (the mesh and the report follow); a second one, or one before
    training began (nothing to keep yet), interrupts as Ctrl-C does. `say` gets the line that tells the user so."""

    def __init__(self, say: Callable[[str], None]):
        self.say = say
        self.training = False
        """Set at the trainer's first question: from then on a fit exists to keep."""
        self.asked = False

    def __call__(self) -> bool:
        self.training = True
        return self.asked

    def interrupt(self, signum, frame) -> None:
        if self.asked or not self.training:
            raise KeyboardInterrupt
        self.asked = True
        self.say("stopping: training ends at its next step (if it still runs) and the mesh and report follow "
                 "(Ctrl-C again aborts, keeping nothing)")


@contextlib.contextmanager
def first_interrupt_stops_training(say: Callable[[str], None]):
    """Within the block, Ctrl-C is `TrainingStop.interrupt` of the `TrainingStop` it yields (pass it to the trainer
    as `stop`). Outside the main thread no handler can be set, and where SIGINT is ignored none is wanted: the stop
    is never asked there."""
    stop = TrainingStop(say)
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # An ignored SIGINT stays ignored: a shell script's background jobs inherit it so, and a Ctrl-C meant for
        # the script must not end their training.
        yield stop
        return
    previous = signal.signal(signal.SIGINT, stop.interrupt)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)
