"""Floating-point settings for the optimisation, applied only while it runs."""

from __future__ import annotations

from contextlib import contextmanager

import torch


@contextmanager
def flush_denormals(device: torch.device):
    """Flush float denormals to zero inside the block on CPU, and restore the default after it.

    Once the opacity sharpness is large, float32 denormals slow CPU steps 5-10x. The flag is a processor-wide mode of
    the calling thread, and other numerical code is not written for it: with it left on, scipy's cKDTree (1.17)
    crashes with a segmentation fault in the metrics. So it is scoped to the optimiser's own work."""
    if device.type != "cpu":
        yield
        return
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)
