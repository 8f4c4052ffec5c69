"""Errors raised by the reconstruction code (one-line messages, as everywhere in the project)."""

from spadscan.protocol.errors import SpadscanError


class ReconstructionError(SpadscanError):
    """A reconstruction cannot run or cannot produce a result (bad settings, an empty surface, a diverged fit)."""
