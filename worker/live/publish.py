"""Publishing a live reconstruction's state into `<capture>/recon/live/`: mesh.ply, preview.png, status.json.

Each file is written under a hidden temporary name and renamed into place (a reader sees a whole file, the old one or
the new one), the status last, so that a status is never older than the mesh beside it. Between two publications of
the mesh the live job rewrites the status alone (the fit's views and steps move on); its `chamfer_mm` stays that of
the mesh beside it. The folder is the live job's own: it is not a job result (those are `<capture>/recon/<job>/`,
published whole by the worker).
"""

from __future__ import annotations

import os
import secrets
import shutil
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import LIVE_DIR, STATUS, LiveStatus, read_status, write_status

from ..outputs import export_mesh
from ..report import offscreen, pictures

MESH = "mesh.ply"
PREVIEW = "preview.png"


def live_folder(capture: Path) -> Path:
    """`<capture>/recon/live/`, created."""
    folder = Path(capture) / "recon" / LIVE_DIR
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def take_live_folder(folder: Path, job, first: LiveStatus) -> str | None:
    """Take `folder` (`<scan>/recon/live/`) for live job `job`: None when it is the job's (its status names the job,
    or no job, or cannot be read, or there was none: `first` is then written there, created so that of two jobs
    starting at once exactly one takes it); else the id of the live job that holds it.

    The folder's path is the scan's one live reconstruction that `spadscan ctl status` and the dashboard read, so
    it is one job's for good: the first live job's that took it (its retries and its --redo have its id). A second
    live job of the scan (another preset, a hashed id) writing there would delete the first's mesh, and its end
    would say 'done' over the first's status with its own result; a lab reading the page expects the job it saw
    following the scan to be the one it reports on. That second job runs as an ordinary job instead. Two queues on
    one root give a scan's live job one id in each: the owner token (`Job.owner`, which `first` carries) tells the
    one that took the folder from the other, which is told the holder's id (its own). A folder with no status yet
    is the job's that claimed it first (`claim_live_folder`), where one did."""
    path = Path(folder) / STATUS
    for _ in range(2):
        found, holder = _named(path, job)
        if found:
            return holder
        claimed = _claim_mark(Path(folder).parent, job)
        if claimed is not None:
            return claimed
        spare = Path(folder) / f".claim-{secrets.token_hex(4)}"  # hidden: a reader never takes it for the status
        try:
            spare.mkdir()
            written = write_status(spare, first)
            try:
                os.link(written, path)  # fails where status.json appeared meanwhile: exactly one job takes the folder
                return None
            except FileExistsError:
                pass  # another job took it first: read whose it is
            except OSError:  # a file system without hard links: taken without the guard
                os.replace(written, path)
                return None
        finally:
            shutil.rmtree(spare, ignore_errors=True)
    return None


CLAIM = ".live-claim"
"""In `<scan>/recon/`: which live job claimed the scan's live folder before it had a status (`claim_live_folder`)."""


def claim_live_folder(scan: Path, job) -> str | None:
    """At the claim of live job `job` in the queue: None when `<scan>/recon/live/` is the job's or free (then it is
    marked the job's, in `<scan>/recon/.live-claim`, before the job's process starts), else the id of the live job
    that holds it. Two queues' workers claim a scan's live job at its first chunk, within a poll of each other,
    seconds before either job's process can take the folder (`take_live_folder`): the mark, made by one hard link,
    gives it to exactly one of them at the claim, and the other's job is left in the queue (`Queue.live_claim`)
    instead of holding a worker for the whole scan. The live folder itself is not made here (it is the job's to
    make)."""
    found, holder = _named(Path(scan) / "recon" / LIVE_DIR / STATUS, job)
    return holder if found else _claim_mark(Path(scan) / "recon", job)


def live_holder(scan: Path, job) -> str | None:
    """`claim_live_folder` without claiming: None when `<scan>/recon/live/` is `job`'s or free, else the id of the
    live job that holds it (by its status, else by the mark of its claim)."""
    for path in (Path(scan) / "recon" / LIVE_DIR / STATUS, Path(scan) / "recon" / CLAIM):
        found, holder = _named(path, job)
        if found:
            return holder
    return None


def _named(path: Path, job) -> tuple[bool, str | None]:
    """What the live status or claim mark `path` says of live job `job`: (False, None) where there is none; (True,
    None) where it is the job's, names no job, or is damaged (the job's own write replaces it, and a damaged mark
    is no claim to honour); else (True, the id of the other live job it names)."""
    from .done import holds

    try:
        status = read_status(path)
    except SpadscanError:
        return path.is_file(), None
    return True, (None if holds(status, job) else status.job)


def _claim_mark(recon: Path, job) -> str | None:
    """None when `recon`/.live-claim names `job` (or no job, or cannot be read), or names none yet and is made
    naming it now (by one hard link: of two claims at once exactly one makes it); else the id of the job it names."""
    path = recon / CLAIM
    mine = LiveStatus(views_used=0, views_published=0, steps=0, state="waiting", job=job.id,
                      owner=getattr(job, "owner", ""))
    for _ in range(2):
        found, marked = _named(path, job)
        if found:
            return marked
        spare = recon / f".claim-{secrets.token_hex(4)}"
        try:
            spare.mkdir(parents=True)
            try:
                os.link(write_status(spare, mine), path)
                return None
            except FileExistsError:
                pass  # another job's claim came first: read whose it is
            except OSError:  # a file system without hard links: claimed without the guard
                return None
        except OSError:  # recon/ cannot be written: the job's process says so
            return None
        finally:
            shutil.rmtree(spare, ignore_errors=True)
    return None


def clear_leftovers(folder: Path) -> None:
    """Remove temporary files a killed live job left in its folder (every temporary name starts with a dot)."""
    for path in Path(folder).glob(".*"):
        if path.is_file():
            path.unlink(missing_ok=True)


def clear_earlier(folder: Path) -> None:
    """Remove what an earlier attempt of the job left in its folder (its worker was stopped, or its process crashed,
    and the job is run again from the start): the temporary files (`clear_leftovers`), and the mesh and preview of
    the fit it abandoned, which beside this attempt's status would read as this attempt's."""
    clear_leftovers(folder)
    for name in (MESH, PREVIEW):
        (Path(folder) / name).unlink(missing_ok=True)


def publish_mesh(folder: Path, mesh, gt_mesh=None, preview: bool = True) -> str | None:
    """Write the live mesh (and, with `preview`, its preview picture beside the ground truth when known). Returns
    None, or where the preview could not be drawn the one-line warning a run's report gives ("no preview.png: <why>",
    `draw_preview`), for the live status to say."""
    folder = Path(folder)
    export_mesh(mesh, folder / MESH)
    return draw_preview(folder, mesh, gt_mesh) if preview else None


def draw_preview(folder: Path, mesh, gt_mesh=None) -> str | None:
    """Draw `folder`/preview.png of `mesh`; None when drawn, else why not ("no preview.png: <why>", one line, as a
    run's report says it: the published file named, not the temporary one, and nothing on stderr at every
    publication: the live job logs it once)."""
    tmp = folder / f".{PREVIEW}.{secrets.token_hex(4)}.png"  # pyvista picks the format from the extension
    try:
        pictures.draw_preview(mesh, tmp, gt=gt_mesh)
        os.replace(tmp, folder / PREVIEW)
    except offscreen.OffscreenUnavailable as exc:
        return pictures.no_preview_warning(exc, PREVIEW)
    finally:
        tmp.unlink(missing_ok=True)
    return None


def publish_status(folder: Path, status: LiveStatus) -> Path:
    """Write status.json (last, after the files it describes)."""
    return write_status(folder, status)


__all__ = ["MESH", "PREVIEW", "CLAIM", "live_folder", "take_live_folder", "claim_live_folder", "live_holder",
           "clear_leftovers", "clear_earlier", "publish_mesh", "draw_preview", "publish_status"]
