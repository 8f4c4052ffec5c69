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


def test_a_look_that_overlaps_a_start_does_not_refuse_it(tmp_path, monkeypatch):
    """`daemon --check` takes a shared lock for a moment; a daemon that starts in that moment waits it out, and a
    refusal never names a holder that has let go (the file is emptied on release)."""
    import fcntl
    import threading

    import spadscan.daemon.root_lock as root_lock

    with RootLock(tmp_path):
        pass
    assert (tmp_path / LOCK_NAME).read_text() == ""
    fd = os.open(tmp_path / LOCK_NAME, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_SH)
    threading.Timer(0.2, os.close, (fd,)).start()  # the look ends while the start is retrying
    with RootLock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == f"{os.getpid()}\n"
    monkeypatch.setattr(root_lock, "LOCK_TRIES", 2)
    with RootLock(tmp_path):
        with pytest.raises(ConfigError, match=r"in use by another daemon \(pid"):
            RootLock(tmp_path).acquire()


def test_a_lock_file_another_user_made_still_locks(tmp_path, monkeypatch):
    """A lock file this user cannot write (left by a daemon once run with sudo) is locked read-only."""
    import spadscan.daemon.root_lock as root_lock

    (tmp_path / LOCK_NAME).write_text("")
    real_open = os.open

    def no_write(path, flags, *mode):
        if flags & os.O_RDWR:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *mode)

    monkeypatch.setattr(root_lock.os, "open", no_write)
    with RootLock(tmp_path):
        with pytest.raises(ConfigError, match="in use by another daemon"):
            check_root_free(tmp_path)
    check_root_free(tmp_path)


@pytest.mark.parametrize("how", ["moved", "removed", "lock deleted"])
def test_a_root_moved_or_its_lock_deleted_is_locked_again(tmp_path, how, monkeypatch):
    """A lock on a file no longer at the root guards nothing: `keep` takes the file there now, and a second daemon
    is refused again; where the root is as it was, it does nothing."""
    import shutil

    import spadscan.daemon.root_lock as root_lock

    monkeypatch.setattr(root_lock, "LOCK_TRIES", 2)
    root = tmp_path / "caps"
    root.mkdir()
    with RootLock(root) as lock:
        assert lock.keep() is False
        if how == "moved":
            root.rename(tmp_path / "caps-archive")
        elif how == "removed":
            shutil.rmtree(root)
        else:
            (root / LOCK_NAME).unlink()
        root.mkdir(exist_ok=True)  # the daemon makes the root again for its next scan
        intruder = RootLock(root)
        intruder.acquire()  # without `keep`, a second daemon is let in
        intruder.release()
        assert lock.keep() is True
        with pytest.raises(ConfigError, match=r"in use by another daemon \(pid"):
            RootLock(root).acquire()
        assert lock.keep() is False


def test_keep_refuses_where_another_daemon_took_the_new_lock(tmp_path, monkeypatch):
    import spadscan.daemon.root_lock as root_lock

    monkeypatch.setattr(root_lock, "LOCK_TRIES", 2)
    root = tmp_path / "caps"
    root.mkdir()
    with RootLock(root) as lock:
        (root / LOCK_NAME).unlink()
        with RootLock(root):
            with pytest.raises(ConfigError, match=r"in use by another daemon \(pid"):
                lock.keep()
        assert lock.keep() is True  # the other let go: taken


def test_a_lock_that_cannot_be_looked_at_is_kept(tmp_path, monkeypatch):
    """A lost mount or a permission makes the look fail, not the lock go: `keep` refuses and holds what it held, so
    that no second daemon is let in by this one letting go."""
    import spadscan.daemon.root_lock as root_lock

    monkeypatch.setattr(root_lock, "LOCK_TRIES", 2)
    root = tmp_path / "caps"
    root.mkdir()
    with RootLock(root) as lock:
        real_stat = os.stat

        def failing(path, *args, **kwargs):
            if os.fspath(path) == os.fspath(root / LOCK_NAME):
                raise OSError(5, "Input/output error")
            return real_stat(path, *args, **kwargs)

        monkeypatch.setattr(root_lock.os, "stat", failing)
        with pytest.raises(ConfigError, match="cannot check the lock of captures root"):
            lock.keep()
        monkeypatch.setattr(root_lock.os, "stat", real_stat)
        with pytest.raises(ConfigError, match=r"in use by another daemon"):
            RootLock(root).acquire()
        (root / LOCK_NAME).unlink()
        with RootLock(root):  # another daemon holds the new file: the old lock is kept, not let go
            with pytest.raises(ConfigError):
                lock.keep()
            assert lock._fd is not None
