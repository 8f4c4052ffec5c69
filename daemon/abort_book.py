"""Aborts a capture could not record yet (a full or read-only disk), kept until they land.

An acknowledged abort must never be undone by a restart: one that scan.json cannot take is kept in
`abort-pending.json` in the scan folder where an empty file still fits (no daemon takes such a scan over, and the next
one records it), in memory in any case, and written again every ABORT_RETRY_S, at each control request and at
shutdown. The daemon's last_error tells the operator where each one stands, truthfully: it is replaced when the
abort's standing changes and cleared when the abort lands, but only while it still tells of that abort. A scan whose
folder is gone (the operator deleted it by hand) has nothing to record: its abort is done, never kept.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from pathlib import Path

from spadscan.protocol.capture_writer import CaptureWriter, drop_temporary, mark_aborted
from spadscan.protocol.errors import CaptureError

from .describe import describe
from .scan_job import ABORT_PENDING, clear_abort_pending, note_abort_pending

log = logging.getLogger("spadscan.daemon")
ABORT_RETRY_S = 5.0  # how often an abort the disk could not take is written again (room may come back at any time)
FOLDER_GONE = "its folder is gone: nothing to record"
"""What an abort of a scan whose folder was removed (by hand, mid-scan) says: done, as there is no capture to mark."""

IO = Callable[..., Awaitable]
"""Runs a function on the capture writer's thread (writes never interleave with a scan's publishing)."""
Replace = Callable[[str | None, str | None], bool]
"""replace(old, new): set the daemon's last_error to `new` if `old` is None or last_error is still `old`; True if
set."""


class AbortBook:
    """The aborts not yet in their scan.json, by scan name; each {"path", "reason", "error", "marker" (whether
    abort-pending.json keeps it), "said" (the last_error that told of it)}."""

    def __init__(self, io: IO, replace_error: Replace, auto_resume: bool):
        self._io, self._replace, self._auto_resume = io, replace_error, auto_resume
        self.unrecorded: dict[str, dict] = {}
        self.folder_gone: set[str] = set()
        """The scans whose abort found their folder gone (nothing recorded, nothing kept)."""
        self._retrying: asyncio.Task | None = None

    async def record(self, name: str, path: Path, reason: str, writer: CaptureWriter | None) -> None:
        """Record scan `name`'s abort in its capture (through `writer` when one is open); one the disk cannot take is
        kept and written again until it lands."""
        self.folder_gone.discard(name)  # (a name freed by a folder removed by hand may be taken again)
        error = await self._io(_write_abort, path, reason, writer)
        if error is FOLDER_GONE:
            self._gone(name)
        elif error is None:
            self._landed(name)
        else:
            await self._keep(name, path, reason, error)

    async def retry(self) -> None:
        """Write again each abort its capture could not record yet; abort-pending.json is tried again too (made, or
        given the record it lacks)."""
        for name, held in list(self.unrecorded.items()):
            error = await self._io(_write_abort, held["path"], held["reason"], None)
            if error is FOLDER_GONE:  # deleted by hand since: no capture is left to undo the abort
                self._gone(name)
                continue
            if error is None:
                self._landed(name)
                continue
            was = (held["error"], held["marker"])
            held["error"] = error
            # Again even when the file is there: one made empty on a full disk gets its record once there is room
            # for it (the reason then survives a restart in the file itself).
            held["marker"] = await self._io(note_abort_pending, held["path"], held["reason"])
            if (held["error"], held["marker"]) != was:
                self._said_again(name, held)

    async def close(self) -> None:
        """At shutdown: the retries stop, a last try is made (room may have come back), and each abort still not
        recorded is logged with what it means for the next daemon."""
        if self._retrying is not None:
            self._retrying.cancel()
            await asyncio.gather(self._retrying, return_exceptions=True)
            self._retrying = None
        await self.retry()
        for name, held in self.unrecorded.items():
            log.error("scan %s: the daemon stops with the scan's abort not recorded: %s", name,
                      _unrecorded_note(held, self._auto_resume, stopping=True))

    def said(self, name: str) -> str:
        """Where the unrecorded abort of scan `name` stands, in one line (as last_error tells it)."""
        return self._said(name, self.unrecorded[name])

    def status(self) -> dict:
        """What `status` shows of each abort not recorded yet."""
        return {name: {"reason": held["reason"], "error": held["error"], "kept_on_disk": held["marker"]}
                for name, held in self.unrecorded.items()}

    async def _keep(self, name: str, path: Path, reason: str, error: str) -> None:
        held = self.unrecorded.setdefault(name, {"path": path, "reason": reason, "marker": False})
        held["error"] = error
        held["marker"] = await self._io(note_abort_pending, path, reason)
        held["said"] = self._said(name, held)
        self._replace(None, held["said"])
        log.warning("%s", held["said"])
        if self._retrying is None or self._retrying.done():
            self._retrying = asyncio.create_task(self._retry_loop(), name="abort retries")

    def _said(self, name: str, held: dict) -> str:
        return f"scan {name!r} is aborted, but {_unrecorded_note(held, self._auto_resume)}"

    def _landed(self, name: str) -> None:
        held = self.unrecorded.pop(name, None)
        if held is not None:
            log.info("scan %s: its abort is recorded in its capture now", name)
            if held.get("said") is not None:
                self._replace(held["said"], None)

    def _gone(self, name: str) -> None:
        """Scan `name`'s folder is gone: its abort is done (no capture is left to record it in, nor to take over), and
        a last_error that told of it goes."""
        self.folder_gone.add(name)
        log.info("scan %s aborted: %s", name, FOLDER_GONE)
        held = self.unrecorded.pop(name, None)
        if held is not None and held.get("said") is not None:
            self._replace(held["said"], None)

    def _said_again(self, name: str, held: dict) -> None:
        """An unrecorded abort's standing changed (abort-pending.json made at last, another error): last_error, if it
        still tells of that abort, says where it stands now (a restart no longer scans on, say), not what it was."""
        said = self._said(name, held)
        if said != held["said"] and self._replace(held["said"], said):
            held["said"] = said
            log.warning("%s", said)

    async def _retry_loop(self) -> None:
        while self.unrecorded:
            await asyncio.sleep(ABORT_RETRY_S)
            await self.retry()


def _write_abort(path: Path, reason: str, writer: CaptureWriter | None) -> str | None:
    """Record an abort in the capture at `path` (on the writer thread): through its open writer (its last pose
    published first), else, or when that fails, in the manifest alone, after the temporary files no writer will
    finish are dropped (their room may be what the manifest needs). Returns None, FOLDER_GONE when the capture's
    folder no longer exists, or why it could not be recorded. A recorded abort's abort-pending.json goes."""
    if not path.is_dir():  # removed by hand: a write would only fail (and be kept, retried, blamed on the disk)
        return FOLDER_GONE
    if writer is not None:
        try:
            writer.finish("aborted", reason)
            clear_abort_pending(path)
            return None
        except (OSError, CaptureError):
            pass  # the manifest alone, below
    with contextlib.suppress(OSError):
        drop_temporary(path)
    try:
        mark_aborted(path, reason)
    except OSError as exc:
        return describe(exc, "recording it")
    except CaptureError as exc:
        return str(exc)
    clear_abort_pending(path)
    return None


def _unrecorded_note(held: dict, auto_resume: bool, stopping: bool = False) -> str:
    """What an abort not yet in scan.json means, for the operator: why, what keeps it, what happens next."""
    if held["marker"]:
        kept = (f"{ABORT_PENDING} in the scan folder keeps it: no daemon takes the scan over, and the next one "
                f"records it")
    else:
        scans_on = " and scans on by itself (auto_resume)" if auto_resume else ""
        kept = (f"nothing on disk keeps it (not even {ABORT_PENDING}): a daemon started on this captures root takes "
                f"the scan over as interrupted{scans_on}")
        if not stopping:
            kept += "; make room or make the disk writable before stopping this daemon"
    again = "" if stopping else f"; written again every {ABORT_RETRY_S:g} s, at each request and at shutdown"
    return f"its scan.json does not say so yet ({held['error']}); {kept}{again}"
