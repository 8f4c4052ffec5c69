"""One daemon per captures root: an advisory lock (flock) on `<captures>/.spadscan-daemon.lock`, held for the daemon's
life.

Two daemons on one captures root would both take over the same interrupted scan and write the same folder; the
control socket cannot guard against that, since two configs may name different sockets. The kernel drops a flock
when its holder dies, so a crash or a power cut never leaves a stale lock to clear by hand. The lock file itself is
never removed: unlinking it while another daemon waits to open it would let two daemons lock two different files.
It holds the holder's pid, only to name it in the refusal.
"""

from __future__ import annotations

import errno
import fcntl
import os
import time
from pathlib import Path

from spadscan.protocol.errors import ConfigError

LOCK_NAME = ".spadscan-daemon.lock"
"""Hidden: the worker and the daemon's own scan search skip names that start with a dot."""

LOCK_TRIES = 20
LOCK_RETRY_S = 0.05
"""A held lock is tried again for about a second before it is refused: `spadscan daemon --check` takes the lock for
a moment to look, and a daemon starting in that moment must not take the look for another daemon."""


class RootLock:
    """`with RootLock(root):` holds the captures root for this process; raises ConfigError when another holds it."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.path = self.root / LOCK_NAME
        self._fd: int | None = None
        self._writable = False

    def acquire(self) -> None:
        fd, writable = _open_lock_file(self.path, self.root)
        try:
            _lock_retrying(fd, self.root)
            if writable:  # the pid only names the holder in a refusal: a read-only lock file still locks
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
        except BaseException:
            os.close(fd)
            raise
        self._fd, self._writable = fd, writable

    def keep(self) -> bool:
        """Hold the lock of the file now at `path`, taking it again where that is not the file locked (the root was
        moved or removed, or its lock file deleted, while this process held it: a lock on a file no longer there
        guards nothing, and a second daemon would be let in). True when it was taken again; ConfigError when another
        daemon holds the file there now, or the file cannot be looked at (the lock held is then kept)."""
        if self._fd is not None:
            try:
                there = os.stat(self.path)
            except (FileNotFoundError, NotADirectoryError):
                there = None
            except OSError as exc:  # a lost mount, a permission: not a sign that the lock is gone
                raise ConfigError(f"cannot check the lock of captures root {self.root}: {exc.strerror or exc} "
                                  f"({self.path})") from None
            held = os.fstat(self._fd)
            if there is not None and (there.st_dev, there.st_ino) == (held.st_dev, held.st_ino):
                return False
        old = self._fd
        self._fd = None
        try:
            self.acquire()  # a new file: no conflict with the one still held
        except BaseException:
            self._fd = old  # kept: a refusal or an error lets no second daemon in by this one letting go
            raise
        if old is not None:
            os.close(old)  # its file is elsewhere now, or gone: its pid is nobody's to read
        return True

    def release(self) -> None:
        if self._fd is not None:
            if self._writable:
                try:
                    os.ftruncate(self._fd, 0)  # so that a later refusal never names this pid
                except OSError:
                    pass
            os.close(self._fd)  # closing the only descriptor drops the flock
            self._fd = None

    def __enter__(self) -> "RootLock":
        if self._fd is None:
            self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def check_root_free(root: Path) -> None:
    """Raise the refusal RootLock would raise, creating and holding nothing (for `spadscan daemon --check`)."""
    path = Path(root) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return  # a daemon that holds the root has this file open
    except OSError as exc:
        raise ConfigError(f"cannot read the lock of captures root {root}: {exc.strerror or exc} ({path})") from None
    try:
        _lock(fd, fcntl.LOCK_SH, root)  # refused while a daemon holds its exclusive lock
    finally:
        os.close(fd)


def _open_lock_file(path: Path, root: Path) -> tuple[int, bool]:
    """(descriptor, writable) of the lock file, created if missing; read-only when another user made it (a daemon
    once run with sudo): flock needs no write access."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644), True
    except PermissionError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot lock captures root {root}: {exc.strerror or exc} ({path})") from None
    try:
        return os.open(path, os.O_RDONLY | os.O_CLOEXEC), False
    except OSError as exc:
        raise ConfigError(f"cannot lock captures root {root}: {exc.strerror or exc} ({path})") from None


def _lock_retrying(fd: int, root: Path) -> None:
    """An exclusive lock on `fd`, tried LOCK_TRIES times LOCK_RETRY_S apart; the last refusal is raised."""
    for attempt in range(LOCK_TRIES):
        try:
            _lock(fd, fcntl.LOCK_EX, root)
            return
        except ConfigError:
            if attempt == LOCK_TRIES - 1:
                raise
            time.sleep(LOCK_RETRY_S)


def _lock(fd: int, kind: int, root: Path) -> None:
    try:
        fcntl.flock(fd, kind | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
            raise ConfigError(f"cannot lock captures root {root}: {exc.strerror or exc}") from None
        raise ConfigError(f"captures root {root} is in use by another daemon{_holder(fd)}; stop that daemon, or "
                          f"give this rig another `captures` folder") from None


def _holder(fd: int) -> str:
    """' (pid N)' from the lock file, or '' while its holder has not written it yet."""
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return ""
    return f" (pid {text})" if text.isdigit() else ""
