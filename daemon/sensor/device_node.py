"""What a device node (a serial port, an I2C bus) must be for this user to use it, judged without opening it: opening
a serial port toggles DTR, which resets the Arduino behind a bridge, so `--check` looks and never opens.

    node_problem("/dev/ttyACM0", "dialout", "tty")   None, or why the daemon could not use it
    access_fix("/dev/ttyACM0", "dialout")           the usual fix of a refused open, for the error that reports it
"""

from __future__ import annotations

import errno
import getpass
import grp
import os
import pwd
import stat
from pathlib import Path

SERIAL_GROUP = "dialout"
"""The group that owns serial ports on most distributions (Debian, Ubuntu, Fedora)."""
I2C_GROUP = "i2c"
"""The group that owns /dev/i2c-N where a udev rule gives the buses to users (Raspberry Pi OS, Debian's i2c-tools)."""

SYS_CHAR = Path("/sys/dev/char")
"""The kernel's index of character devices by major:minor; each entry's `subsystem` link names its class."""


def node_problem(path: str, group: str, kind: str, *, access=os.access, sys_char: Path = SYS_CHAR) -> str | None:
    """Why `path` (present) is not a device node this user can read and write, in words that follow the path; None
    when nothing seen without opening it stands in the way. `group` owns such nodes on most distributions (the
    fix of a refused permission), `kind` is the kernel class they belong to ('tty', 'i2c-dev')."""
    try:
        st = os.stat(path)
    except OSError as exc:
        return f"cannot be looked at ({exc.strerror})"
    if not stat.S_ISCHR(st.st_mode):
        what = "a folder" if stat.S_ISDIR(st.st_mode) else "a regular file" if stat.S_ISREG(st.st_mode) else \
            "a special file"
        return f"{what}, not a character device as {_KIND_WORDS.get(kind, kind)} is; check the path"
    found = _device_class(st.st_rdev, sys_char)
    if found is not None and found != kind:
        return (f"a character device of class '{found}', not {_KIND_WORDS.get(kind, kind)} (class '{kind}'); "
                f"check the path")
    if not access(path, os.R_OK | os.W_OK):
        return f"this user may not read and write it ({_mode_words(st)}): {access_fix(path, group, st)}"
    return None


def access_fix(path: str, group: str, st: os.stat_result | None = None) -> str:
    """The usual fix of a device node this user may not open: join the group that may (the node's own group when
    that group may read and write it, else `group`), then log in again (a new group counts from the next login)."""
    if st is None:
        try:
            st = os.stat(path)
        except OSError:
            st = None
    if st is not None and st.st_gid != 0 and st.st_mode & 0o060 == 0o060:
        group = _group_name(st.st_gid) or group
    user = _user()
    return f"add {user} to the '{group}' group (sudo usermod -aG {group} {user}), then log out and in again"


def with_access_fix(text: str, exc: BaseException, path: str, group: str) -> str:
    """`text` (a refused open's line), with `access_fix` after it when `exc` is a refused permission."""
    return f"{text}; {access_fix(path, group)}" if is_access_refused(exc) else text


def is_access_refused(exc: BaseException) -> bool:
    """Whether `exc`, or an error it was raised from or during, is a refused permission (EACCES, EPERM)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.EACCES, errno.EPERM):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


_KIND_WORDS = {"tty": "a serial port", "i2c-dev": "an I2C bus"}


def _device_class(rdev: int, sys_char: Path) -> str | None:
    """The kernel class of the character device `rdev`; None where the kernel does not say (a pty, no /sys)."""
    try:
        return os.path.basename(os.readlink(sys_char / f"{os.major(rdev)}:{os.minor(rdev)}" / "subsystem"))
    except OSError:
        return None


def _mode_words(st: os.stat_result) -> str:
    owner = _user_name(st.st_uid) or str(st.st_uid)
    group = _group_name(st.st_gid) or str(st.st_gid)
    return f"{stat.filemode(st.st_mode)} {owner}:{group}"


def _group_name(gid: int) -> str | None:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return None


def _user_name(uid: int) -> str | None:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return None


def _user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "the user"
