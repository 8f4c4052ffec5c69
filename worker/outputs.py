"""Result folders (`--out`) of `spadscan reconstruct` and `spadscan baseline`: never a previous result lost by
accident, never a half-written mesh left where a good one was."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path
from typing import Callable, Iterator

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.mesh_io import BUILTIN_PREFIX

from .report.view3d import VIEW3D

RESULT_FILES = ("mesh.ply", "report.json")
"""Files whose presence means a folder holds a result."""
ASIDE_DIR = ".replaced"
"""Where a previous result waits while a run replaces it (`replacing_result`)."""
JOB_FILES = ("job.json", "job.log", "ground_truth.ply", ".complete")
"""Files a worker's job adds to its result beside what the reconstruction lists (jobs.py, publishing.py: the job's
options, its log, the ground truth it was scored against, the queue's completion marker). A run that replaces such a
result must not leave them: they would describe how another mesh was made, and the marker would go on naming the
queue's claim."""


def held_result(out) -> list[str]:
    """The result files `out` holds (RESULT_FILES, in it or set aside in its `.replaced/` by a run that was killed)."""
    out = Path(out)
    return [name for name in RESULT_FILES if (out / name).exists() or (out / ASIDE_DIR / name).exists()]


def check_out(out, overwrite: bool, capture=None) -> Path:
    """`out` as a Path, refused when it is a file, or holds a result and `overwrite` is not set, or lies inside the
    folder of `capture` (when given) anywhere but under its recon/ folder, where the worker puts results. (An empty
    --out the command line refuses: cli.FOLDER_OPTIONS.)"""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if capture is not None:
        inside = _relative_to(out, Path(capture))
        if inside is not None and (not inside.parts or inside.parts[0] != "recon"):
            raise ConfigError(f"--out {out} lies inside the capture {capture}: results there would be mixed into "
                              f"its measurements; choose a folder outside it (or under its recon/ folder)")
    held = held_result(out)
    if held and not overwrite:
        raise ConfigError(f"{out}: already holds a result ({', '.join(held)}); choose another --out, or pass "
                          "--overwrite to replace it")
    return out


def check_ground_truth_kept(gt, out) -> None:
    """Refuse a ground-truth file (`--gt`) that is one of the previous result's files in `out`, which a run with
    --overwrite removes when it publishes its own (`previous_result`: a worker job's ground_truth.ply, say): the new
    report would name a file that is gone. A built-in scene (builtin:NAME) or a file elsewhere passes."""
    if gt is None or str(gt).startswith(BUILTIN_PREFIX):
        return
    gt, out = Path(gt), Path(out)
    if out.is_dir() and _relative_to(gt.parent, out) == Path(".") and gt.name in previous_result(out):
        raise ConfigError(f"--gt {gt} is a file of the result in --out {out}, which --overwrite replaces with the "
                          f"new result; copy it out of that folder and pass the copy")


def _relative_to(path: Path, folder: Path) -> Path | None:
    """`path` relative to `folder` when it lies inside it (or is it), both resolved; else None."""
    try:
        return path.resolve().relative_to(folder.resolve())
    except ValueError:
        return None


def export_mesh(mesh, path, **options) -> Path:
    """Write `mesh` as PLY to `path` through a temporary file renamed over it: a failed write (a full disk) leaves
    the previous file, not a truncated one. `options` go to trimesh's export (e.g. vertex_normal=True)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        mesh.export(tmp, file_type="ply", **options)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def previous_result(out) -> set[str]:
    """The file names of the result `out` holds before a run replaces it (--overwrite): those its report.json lists
    (`files`), the report itself, its page, its 3D view and its mesh, and, when it is a worker job's result
    (`is_job_result`), the files the job added (JOB_FILES). Files it does not list (the user's own: a ground_truth.ply
    or job.log kept beside a plain `spadscan reconstruct` result, which writes neither) are no part of it; nor are a
    job's files in a folder that holds no result yet (the job's own scratch folder, where they are written before the
    reconstruction that adds the result)."""
    out = Path(out)
    names = {*RESULT_FILES, "report.html", VIEW3D}
    if any((out / name).is_file() for name in RESULT_FILES) and is_job_result(out):
        names |= set(JOB_FILES)
    try:
        listed = json.loads((out / "report.json").read_text()).get("files")
    except (OSError, ValueError, AttributeError):
        listed = None
    if isinstance(listed, list):
        names |= {Path(str(n)).name for n in listed}
    return {n for n in names if (out / n).is_file()}


def is_job_result(folder) -> bool:
    """Whether `folder` holds a worker job's result: the queue's completion marker (.complete) naming a job, or the
    job's own job.json (a job's id and scan), which results published before markers existed carry."""
    for name, keys in ((".complete", ("job",)), ("job.json", ("id", "scan"))):
        try:
            data = json.loads((Path(folder) / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict) and all(isinstance(data.get(k), str) and data.get(k) for k in keys):
            return True
    return False


def folder_files(out) -> dict[str, int]:
    """The plain files in `out` (hidden ones left out) by name, each with its inode; empty when `out` is missing."""
    try:
        entries = list(Path(out).iterdir())
    except OSError:
        return {}
    return {p.name: p.stat().st_ino for p in entries if p.is_file() and not p.name.startswith(".")}


def files_written_after(out, before: dict[str, int]) -> set[str]:
    """Names of the plain files in `out` that a run wrote since `before` (`folder_files` then): new names, or names
    that now stand for another file. A run writes every file of its result anew (the previous result is set aside
    first), while a file of the user's that was there before keeps its inode even when edited meanwhile, and its
    modification time says nothing (copied with -p, from a machine whose clock runs ahead)."""
    return {name for name, ino in folder_files(out).items() if before.get(name) != ino}


@contextlib.contextmanager
def replacing_result(out, log: Callable[[str], None] | None = None) -> Iterator[set[str]]:
    """While a run writes its result into `out` (--overwrite): the previous result's files (`previous_result`) wait
    in `out/.replaced/`. A run that ends without finishing (an error, Ctrl-C) has them put back over what it wrote,
    and the files it wrote besides removed, so that the folder holds the previous result whole; a run that finishes
    drops them, and with them those it did not write again (a normals picture of a run with a ground truth must not
    stand beside a run without one). A `.replaced/` left by a run that was killed is put back first. Yields the
    names set aside."""
    out = Path(out)
    log = log or (lambda line: None)
    aside = out / ASIDE_DIR
    if aside.is_dir():
        back = _put_back(out, aside, set())
        log(f"put back the previous result that a run stopped mid-way had set aside ({', '.join(back)})")
    previous = previous_result(out) if out.is_dir() else set()
    if previous:
        aside.mkdir(exist_ok=True)
        for name in sorted(previous):
            os.replace(out / name, aside / name)
    before = folder_files(out)
    try:
        yield previous
    except BaseException:
        if previous:
            _put_back(out, aside, files_written_after(out, before) - previous)
        raise
    if previous:
        gone = sorted(previous - {p.name for p in out.iterdir() if p.is_file()})
        shutil.rmtree(aside, ignore_errors=True)
        if gone:
            log(f"removed the replaced result's {', '.join(gone)} (this run wrote none)")


def _put_back(out: Path, aside: Path, also_remove: set[str]) -> list[str]:
    """Move the files set aside in `aside` back into `out` (over what stands there) and remove the files named in
    `also_remove`; returns the names put back."""
    back = sorted(p.name for p in aside.iterdir() if p.is_file())
    for name in sorted(also_remove - set(back)):
        (out / name).unlink(missing_ok=True)
    for name in back:
        os.replace(aside / name, out / name)
    shutil.rmtree(aside, ignore_errors=True)
    return back


def capture_state_note(capture, state: str, views: int, planned: int | None = None) -> str | None:
    """A warning for a capture that is not complete (a scan still running, paused or aborted), or that says complete
    but holds fewer than its `planned` poses (a copy cut short, or still under way), or None."""
    if state == "complete":
        if isinstance(planned, int) and not isinstance(planned, bool) and views < planned:
            return (f"{capture}: the capture says complete but holds {views} of its {planned} planned views (a copy "
                    f"cut short or still under way?): reconstructed from those")
        return None
    return (f"{capture}: the capture is {state}, not complete: reconstructing the {views} views it holds so far")


__all__ = ["RESULT_FILES", "JOB_FILES", "check_out", "check_ground_truth_kept", "export_mesh", "capture_state_note",
           "replacing_result", "held_result"]
