"""A scan's capture folder as the runner keeps it: its writer's progress and end, the measurements of a pose, the
pause it records, and what stands in the way of reopening it."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from spadscan.protocol.capture_format import MANIFEST, Measurement, one_line, read_json
from spadscan.protocol.capture_writer import INTERRUPTED, PAUSE, Stock
from spadscan.protocol.disk_full import FULL_ERRNOS
from spadscan.protocol.errors import CaptureError

from .describe import describe, write_advice
from .devices import Frame
from .scan_job import ScanJob
from .scan_plan import sensor_from_tcp

log = logging.getLogger("spadscan.daemon")


def count_as_held(job: ScanJob) -> None:
    """Set the progress of a scan whose writes have ended (stopped, aborted) to what its capture holds: counted from
    its folder as a resume counts it (`counted_on_disk`, as `ctl status` of a paused scan is), for the writer's own
    count misses a chunk moved out by hand (during a pause); the writer's count where only a resume can count (a
    chunk changed since the daemon read it). A publish that landed as the scan was stopped is counted either way."""
    if job.writer is not None:
        job.record_progress(job.writer)
    stock, _ = counted_on_disk(job)
    if stock is not None:
        job.record_stock(stock)


def counted_on_disk(job: ScanJob) -> tuple[Stock | None, str | None]:
    """`ScanJob.stock_on_disk`: (the scan's progress as its resume will count it from its folder, None) or (None, why
    only the resume can count), a folder that cannot be counted included: what `ctl status` of a paused scan and the
    stop note say."""
    try:
        return job.stock_on_disk()
    except (CaptureError, OSError) as exc:
        return None, f"{one_line(exc)} (`spadscan ctl resume` says the same)"


def lost_chunks(job: ScanJob) -> bool:
    """Whether chunks the scan published are gone from its folder (moved out or deleted while it ran), checked before
    it is called complete ("complete" promises every pose): their poses are then owed again, as a resume finds them
    (`CaptureWriter.take_stock`), and the scan's progress says so."""
    gone = job.writer.take_stock()
    if not gone:
        return False
    job.record_progress(job.writer)
    again = [str(pose) for pose in job.owed]
    if job.next_pose < job.n_poses:  # the last chunks gone: the scan goes on from the first pose they held
        last = job.n_poses - 1
        again.append(str(last) if job.next_pose == last else f"{job.next_pose}..{last}")
    log.warning("scan %s: %s gone from its folder (moved out or deleted while the scan ran): taking pose(s) %s "
                "again before the scan is complete", job.name, ", ".join(gone), ", ".join(again))
    return True


def close_writer(job: ScanJob) -> None:
    """Drop the scan's writer, its writer lock released now (not whenever the writer is collected): a descriptor
    held past a pause or the scan's end would keep another process (the next daemon) off the capture."""
    if job.writer is not None:
        job.writer.close()
    job.writer = None


def finish_capture(job: ScanJob) -> None:
    """Mark the capture complete; an adaptive scan's manifest also counts its poses by why they were taken."""
    if job.chooser is None:
        job.writer.finish("complete")
        return
    job.writer.flush()
    job.writer.set_state("complete", None, view_choices=dict(sorted(job.view_counts.items())))


def end_early(job: ScanJob) -> None:
    """End an adaptive scan at its published poses (job.ended_early says why): schedule.npy and planned_poses cut to
    them first, so that the capture is complete as it stands (every planned pose published), then the state."""
    n = job.writer.next_pose_index
    job.writer.replace_schedule(job.sensor_poses[:n])
    job.writer.flush()
    job.writer.set_state("complete", job.ended_early, view_choices=dict(sorted(job.view_counts.items())))


def pose_measurements(job: ScanJob, i: int, frames: list[Frame], arm, choice: dict | None = None,
                  numbers: tuple[int, ...] | None = None) -> list[Measurement]:
    """One measurement per frame at the arm's actual pose (raw counts, never summed); `choice`: why an adaptive scan
    took the pose (its `view_choice`); `numbers`: the frames' numbers at the pose (default 0, 1, ...: a retake's are
    the ones missing)."""
    tcp = np.asarray(arm.tcp_pose, dtype=np.float64)
    sensor_pose = sensor_from_tcp(tcp, job.hand_eye)
    common = {"tcp_pose": tcp.tolist(), "joints": np.asarray(arm.joints, float).tolist(),
              "arm_timestamp_s": float(arm.timestamp_s)}
    out = []
    for k, f in enumerate(frames):
        meta = {"t_start": float(f.t_start), "t_end": float(f.t_end), "temperature_c": f.temperature_c,
                "depths_mm": f.depths_mm, "confidences": f.confidences, **common}
        if f.extra:
            meta["extra"] = f.extra
        if choice is not None:
            meta["view_choice"] = choice
        out.append(Measurement(f.hists, sensor_pose, i, k if numbers is None else numbers[k], f.reference, meta))
    return out


def folder_gone(path: Path) -> bool:
    """Whether a scan's folder is gone: its manifest (which nothing but the operator removes) is missing. A look that
    fails otherwise (a failing disk, a permission) is not taken for gone: the disk's advice then stands."""
    try:
        os.stat(path / MANIFEST)
    except (FileNotFoundError, NotADirectoryError):
        return True
    except OSError:
        return False
    return False


def gone_or_ended(path: Path) -> bool:
    """Whether the scan folder `path` holds no manifest any more (moved out by hand), or one that says it ended."""
    try:
        return read_json(path / MANIFEST).get("state") != "running"
    except CaptureError:
        return not (path / MANIFEST).exists()


def reopen_problem(job: ScanJob, exc: BaseException) -> str:
    """Why the capture of `job` cannot be reopened, with what the operator can do."""
    if not job.path.is_dir():
        return f"its folder {job.path} is gone; `spadscan ctl abort` ends the scan"
    if not isinstance(exc, OSError):  # the capture itself is in the way (a damaged chunk)
        return f"cannot reopen the capture: {exc}; `spadscan ctl abort` ends the scan"
    what = describe(exc, "reopening it")
    return f"cannot reopen the capture: {what}; {reopen_fix(exc)}"


def reopen_fix(exc: OSError) -> str:
    """What the operator does about a capture that write error `exc` keeps from being reopened."""
    return "make room, then `spadscan ctl resume`" if exc.errno in FULL_ERRNOS else write_advice(exc)


def remove_partial(path: Path) -> None:
    """Remove a scan folder that CaptureWriter.create left half-made (removing needs no free space)."""
    shutil.rmtree(path, ignore_errors=True)


def pause_said(job: ScanJob) -> str | None:
    """What the capture records of a pause: why the scan was paused in the first place (`ScanJob.paused_for`), else
    its reason. A block is recorded with it, so that the dashboard says why the scan waits as `ctl status` does; the
    next daemon leaves it out of the pause it takes over (`pause_before_block`) and checks the rig afresh."""
    return job.reason if job.blocked else job.paused_for or job.reason


def pause_kind(job: ScanJob) -> str:
    """The kind of pause the capture records (scan.json's `paused.kind`): INTERRUPTED while the scan waits only
    because a takeover found it interrupted (`ScanJob.interrupted`), else PAUSE."""
    return INTERRUPTED if job.interrupted else PAUSE


def paused_record(path: Path) -> dict | None:
    """The pause the capture's scan had when its daemon stopped (scan.json's `paused`), or None."""
    paused = read_json(path / MANIFEST).get("paused")
    return paused if isinstance(paused, dict) else None


def paused_reason(record: dict | None) -> str | None:
    """Why a `paused` record (`paused_record`) says the scan was paused, or None without one."""
    return None if record is None else str(record.get("reason") or "paused")
