"""A hand run's result published into `--out` whole (`spadscan reconstruct`): written into a hidden scratch folder,
then renamed into place once it has finished, so that it never mixes its files into a result the worker published
there meanwhile (a job's `<scan>/recon/<job>/`), and a result found there is kept (or set aside with --overwrite)."""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import Callable, Iterator

from spadscan.protocol.errors import ConfigError

from .outputs import held_result, replacing_result

def move_aside(final: Path) -> Path | None:
    """Rename a results folder to `<name>.replaced-<UTC time>-<random>` beside it; returns the new path, or None
    when there is no such folder."""
    if not final.exists():
        return None
    aside = _beside(final, "replaced")
    os.rename(final, aside)
    return aside


def _beside(folder: Path, kind: str) -> Path:
    """A new name beside `folder`: `<name>.<kind>-<UTC time>-<4 hex digits>`."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return folder.with_name(f"{folder.name}.{kind}-{stamp}-{secrets.token_hex(2)}")


@contextlib.contextmanager
def result_beside(out, overwrite: bool, log: Callable[[str], None] | None = None) -> Iterator[Path]:
    """A run (`spadscan reconstruct`) that writes its result into the hidden scratch folder this yields,
    `.tmp-<name>-<8 hex digits>` (`scratch_for`), and has it published into `out` once it has finished
    (`publish_beside`); a run that ends without finishing (an error, Ctrl-C, SIGTERM through the command's
    `terminate_as_interrupt`) leaves `out` as it was and its scratch folder removed. `out` is what the worker publishes
    to when it is a job's `<scan>/recon/<job>/`: written into straight, a run of minutes would mix its files into a
    result the worker renamed into place meanwhile. Scratch folders an earlier run into `out` left (killed) are named
    first: nothing else would, hidden as they are. A publishing that fails says where the finished result is."""
    out = Path(os.path.abspath(out))
    if not out.name:
        raise ConfigError(f"--out {out}: a result needs a folder of its own, not the filesystem's root")
    log = log or (lambda line: None)
    for left in leftover_scratch(out):
        log(f"{left}: the scratch folder of an earlier run into this --out that never finished (killed, or still "
            f"running): remove it once no run writes into {out}")
    was = _identity(out)
    scratch, made = scratch_for(out, f".tmp-{out.name}-{secrets.token_hex(4)}")  # no claim token: no worker sweeps it
    try:
        yield scratch
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        for folder in made:  # the folders above a new --out that the run created: a failed run leaves none
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    try:
        publish_beside(scratch, out, overwrite, was, log)
    except BaseException as exc:
        if not scratch.is_dir():
            raise
        where = f"this run's finished result is whole in {scratch}; move its files into {out} by hand"
        if isinstance(exc, OSError):
            raise ConfigError(f"--out {out}: could not move the finished result in ({exc.strerror or exc}): "
                              f"{where}") from exc
        log(where)
        raise


def leftover_scratch(out: Path) -> list[Path]:
    """Scratch folders of `result_beside` runs into `out` (`.tmp-<name>-<8 hex digits>`, beside it or inside it) that
    are there now: a run that was killed leaves its own. (A worker's scratch folder ends in 16 hex digits.)"""
    name = re.compile(rf"\.tmp-{re.escape(out.name)}-[0-9a-f]{{8}}")
    found = []
    for folder in (out.parent, out):
        try:
            found += [entry for entry in folder.iterdir() if name.fullmatch(entry.name) and entry.is_dir()]
        except OSError:
            continue  # `out` does not exist yet
    return sorted(found)


def scratch_for(out: Path, name: str) -> tuple[Path, list[Path]]:
    """Create the run's scratch folder `name` for `out`; returns it and the folders above it that were created with
    it. Beside `out` when the finished result can be moved into `out` from there: always for a new `out` (one rename
    in one folder: `out` appears whole), and for an existing `out` when a trial rename says so. A rename across
    filesystems fails (`out` a mount point, or a link to a folder on another disk), as does any in a parent folder the
    user cannot write (`--out .` in a folder of their own inside someone else's): then inside `out`, which is writable
    whenever `out` is, on its filesystem. Beside is better where it works: a worker that renames a job's result into
    place, setting `out` aside, carries a scratch folder inside `out` away with it."""
    beside, inside = out.with_name(name), out / name
    if not out.is_dir():
        made = [folder for folder in beside.parents if not folder.exists()]
        try:
            beside.mkdir(parents=True)
        except OSError as exc:
            where = f": {exc.filename}" if exc.filename else ""
            raise ConfigError(f"--out {out}: cannot create it ({exc.strerror or exc}{where})") from exc
        return beside, made
    try:
        beside.mkdir()
    except OSError:
        pass  # a parent folder the user cannot write: inside, below
    else:
        try:
            os.rename(beside, inside)
        except OSError:
            beside.rmdir()
        else:
            with contextlib.suppress(OSError):
                os.rename(inside, beside)
                return beside, []
            return inside, []  # it could not be renamed back: inside it is, then
    try:
        inside.mkdir()
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot write into it ({exc.strerror or exc})") from exc
    return inside, []


def publish_beside(scratch: Path, out: Path, overwrite: bool, was: tuple[int, int] | None,
                   log: Callable[[str], None] | None = None) -> None:
    """Publish the finished result in `scratch` (beside `out` or inside it: `scratch_for`) to `out`, which was the
    folder `was` (`_identity`) when the run started. A new `out` appears whole, by one rename. A result found in `out`
    now (one that appeared while the run went: a worker published its job's result there, say) is never replaced in
    silence: without `overwrite` it is kept, this run's result renamed to `<out>.new-<UTC time>-<4 hex>` (`_keep_apart`)
    and the run refused, saying where; with it, a folder that is not the one the run started from is moved aside whole
    (as the worker's publishing does). Into the folder the run started from, the result's files are moved beside the
    user's own, a previous result (`overwrite`) replaced as `replacing_result` does."""
    log = log or (lambda line: None)
    if not out.exists():
        try:
            os.rename(scratch, out)
            return
        except OSError:
            if not out.exists():
                raise
            # it appeared between the look and the rename: one more folder to reckon with, below
    held = held_result(out)
    replaced = _identity(out) != was
    if held and (not overwrite or (replaced and scratch.parent == out)):
        # (a scratch folder inside a folder renamed into `out` meanwhile is this run's, made anew there; setting that
        # folder aside would carry it along)
        kept = _keep_apart(scratch, out)
        raise ConfigError(f"{out}: a result ({', '.join(held)}) appeared there while this run went (a worker "
                          f"publishing its job's result?): kept it; this run's result is in {kept}"
                          + ("" if overwrite else " (--overwrite would have moved the one found aside)"))
    if held and replaced:
        aside = move_aside(out)
        log(f"{out} was replaced while this run went (a worker publishing its job's result?): moved that result "
            f"aside to {aside}")  # said first: should the rename below fail, the message names both folders
        os.rename(scratch, out)
        return
    with replacing_result(out, log):
        _move_in(scratch, out)
    scratch.rmdir()


def _keep_apart(scratch: Path, out: Path) -> Path:
    """Rename the result in `scratch` to `<out>.new-<UTC time>-<4 hex>` beside `out`, or, where that cannot be (a
    parent folder the user cannot write, `out` a mount point), inside `out`; returns where it is."""
    kept = _beside(out, "new")
    try:
        os.rename(scratch, kept)
    except OSError:
        kept = out / kept.name
        os.rename(scratch, kept)
    return kept


def _move_in(scratch: Path, out: Path) -> None:
    """Move the files of `scratch` into `out`. A move that fails has those moved already go back: the result stays
    whole in `scratch`, and `replacing_result` does not take them for files a failed run wrote (it removes those)."""
    moved = []
    try:
        for entry in sorted(scratch.iterdir()):
            os.replace(entry, out / entry.name)
            moved.append(entry.name)
    except BaseException:
        for name in reversed(moved):
            os.replace(out / name, scratch / name)
        raise


def _identity(folder: Path) -> tuple[int, int] | None:
    """(device, inode) of `folder`, or None when there is none: a folder renamed into its place is another one."""
    try:
        st = folder.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino
