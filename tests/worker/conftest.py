"""Fixtures shared by the worker's tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def one_thread():
    """One torch thread: the test machine's cores are shared, and oversubscribed threads only spin."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
