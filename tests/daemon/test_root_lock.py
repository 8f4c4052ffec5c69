"""The captures root's lock: one holder at a time, the holder's pid in the refusal, free again once released, and
a check that creates and holds nothing."""

from __future__ import annotations

import os

import pytest

from spadscan.daemon.root_lock import LOCK_NAME, RootLock, check_root_free
from spadscan.protocol.errors import ConfigError


def test_one_holder_at_a_time(tmp_path):
    with RootLock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == f"{os.getpid()}\n"
        for attempt in (lambda: RootLock(tmp_path).acquire(), lambda: check_root_free(tmp_path)):
            with pytest.raises(ConfigError) as info:
                attempt()
            assert str(info.value).startswith(f"captures root {tmp_path} is in use by another daemon "
                                              f"(pid {os.getpid()})")
    check_root_free(tmp_path)  # released: free again
    with RootLock(tmp_path):
        pass


def test_check_creates_nothing(tmp_path):
    check_root_free(tmp_path / "missing")
    check_root_free(tmp_path)
    assert not (tmp_path / LOCK_NAME).exists() and not (tmp_path / "missing").exists()


def test_an_unusable_root_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="cannot lock captures root .*missing"):
        RootLock(tmp_path / "missing").acquire()
