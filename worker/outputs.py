"""Result folders (`--out`) of `spadscan reconstruct` and `spadscan baseline`: never a previous result lost by
accident, never a half-written mesh left where a good one was."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path
from typing import Callable, Iterator

from spadscan.protocol.capture_format import MANIFEST, chunk_index, chunk_name, enclosing_capture
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.folders import check_folder_option
from spadscan.protocol.mesh_io import BUILTIN_PREFIX

from .disk_room import NAMED, names_said
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
    folder of a capture (`capture`, or any other: `enclosing_capture`) anywhere but under its recon/ folder, where the
    worker puts results, or is a folder this process cannot write into or make (`check_folder_option`, on `out`
    itself, not on the scratch folder beside it that a run makes first). A `capture` that is no capture folder is
    refused first (`check_capture_folder`). (An empty --out the command line refuses: cli.FOLDER_OPTIONS.)"""
    out = Path(out)
    if capture is not None:
        check_capture_folder(capture)  # first: a plain folder that holds --out is no capture it would be mixed into
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    around = enclosing_capture(out)  # the capture read, or another one (a copy, a daemon's scan): never among them
    if around is not None:
        inside = out.resolve().relative_to(around)
        if not inside.parts or inside.parts[0] != "recon":
            named = capture if capture is not None and _relative_to(around, Path(capture)) == Path() else around
            raise ConfigError(f"--out {out} lies inside the capture {named}: results there would be mixed into "
                              f"its measurements; choose a folder outside it (or under its recon/ folder)")
    held = held_result(out)
    if held and not overwrite:
        raise ConfigError(f"{out}: already holds a result ({', '.join(held)}); choose another --out, or pass "
                          "--overwrite to replace it")
    check_folder_option(out, "--out")
    return out


def check_capture_folder(capture) -> None:
    """Refuse, in one line, a CAPTURE that is no capture folder: not there, a file, or a folder without scan.json (the
    folder a user stands in, `spadscan reconstruct . --out results`, or a captures root, whose capture folders are
    named); a chunk, the scan.json or another part of a capture names that capture (`part_of_capture`). A scan.json
    that is there is the capture reader's to judge, as is a folder that cannot be looked into."""
    capture = Path(capture)
    try:
        if (capture / MANIFEST).exists():
            return
        part = part_of_capture(capture)
        if part is not None:
            raise CaptureError(f"{capture}: {part} {capture.parent}; name {capture.parent}")
        if not capture.is_dir():
            raise CaptureError(f"{capture}: " + ("a file, not a capture folder" if capture.exists() else
                                                 "no such capture folder"))
        held = captures_in(capture)
    except OSError:
        return
    if not held:
        raise CaptureError(f"{capture}: not a capture folder (no {MANIFEST}; a capture is the folder that holds "
                           f"{MANIFEST} and its chunk-NNNNNN folders)")
    named = names_said([str(capture / name) for name in held], last_and=True)
    raise CaptureError(f"{capture}: not a capture folder (no {MANIFEST}); it holds captures: {named}; name one")


def part_of_capture(path: Path) -> str | None:
    """What `path`, a file or folder there in a capture folder (its parent holds scan.json), is of it, in words
    before the capture's name ("a chunk of the capture", "the manifest of the capture"); None for any other path. A
    user who names a chunk (`reconstruct CAP/chunk-000000`) or the manifest meant the capture. OSError where the
    parent cannot be looked into."""
    if not path.exists() or not (path.parent / MANIFEST).is_file():
        return None
    if path.name == MANIFEST:
        return "the manifest of the capture"
    if path.is_dir() and chunk_index(path.name) is not None:
        return "a chunk of the capture"
    return f"a {'folder' if path.is_dir() else 'file'} in the capture"


def captures_in(folder: Path) -> list[str]:
    """The names of the folders in `folder` that hold a scan.json (capture folders), sorted."""
    return sorted(entry.name for entry in folder.iterdir() if _holds_manifest(entry))


def _holds_manifest(folder: Path) -> bool:
    """Whether `folder` holds a scan.json; False for one that cannot be looked into."""
    try:
        return (folder / MANIFEST).is_file()
    except OSError:
        return False


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
    but holds fewer than its `planned` poses, or None. The latter names the views it lacks and, where the chunk
    numbers show one, the chunk they were in (`missing_views_note`): a damaged chunk moved out, as the capture
    reader's error advises, is then told from a copy cut short or still under way."""
    if state == "complete":
        if isinstance(planned, int) and not isinstance(planned, bool) and views < planned:
            lacking = missing_views_note(capture, planned)
            if lacking is None:  # its chunks could not be read: the general cause
                return (f"{capture}: the capture says complete but holds {views} of its {planned} planned views (a "
                        f"copy cut short or still under way?): reconstructed from those")
            return (f"{capture}: the capture says complete but holds {views} of its {planned} planned views: "
                    f"{lacking}; reconstructed from those")
        return None
    return (f"{capture}: the capture is {state}, not complete: reconstructing the {views} views it holds so far")


def missing_views_note(capture, planned: int) -> str | None:
    """Which of the `planned` views (pose indices 0 .. planned - 1) the capture folder `capture` lacks, run by run of
    consecutive views, each with where it was (`_missing_run`); None when it lacks none or its chunks cannot be
    listed."""
    try:
        held = chunk_views(capture)
    except OSError:
        return None
    chunk_of = {view: number for number, views in held.items() for view in views if 0 <= view < planned}
    runs = _missing_runs(sorted(chunk_of), planned)
    said = [_missing_run(first, last, chunk_of, held) for first, last in runs[:NAMED]]
    if len(runs) > NAMED:
        said.append(f"and {len(runs) - NAMED} more runs of views are missing")
    return "; ".join(said) or None


def chunk_views(capture) -> dict[int, set[int]]:
    """The views (pose indices) each published chunk of the capture folder `capture` holds, by chunk number, read from
    the chunks' meta.json alone (docs/capture_format.md); a chunk whose meta.json cannot be read holds none here.
    OSError when the folder cannot be listed."""
    with os.scandir(capture) as entries:
        chunks = {chunk_index(e.name): e.path for e in entries if chunk_index(e.name) is not None and e.is_dir()}
    return {number: _meta_views(Path(path) / "meta.json") for number, path in chunks.items()}


def _meta_views(meta: Path) -> set[int]:
    """The pose indices a chunk's meta.json names (empty when it cannot be read)."""
    try:
        records = json.loads(meta.read_text()).get("measurements")
    except (OSError, ValueError, AttributeError, RecursionError):
        return set()
    if not isinstance(records, list):
        return set()
    return {r["pose_index"] for r in records if isinstance(r, dict) and type(r.get("pose_index")) is int}


def _missing_runs(views: list[int], planned: int) -> list[tuple[int, int]]:
    """(first, last) of each run of consecutive view numbers in 0 .. planned - 1 that sorted `views` lacks."""
    runs, expected = [], 0
    for view in [*views, planned]:
        if view > expected:
            runs.append((expected, view - 1))
        expected = view + 1
    return runs


def _missing_run(first: int, last: int, chunk_of: dict[int, int], held: dict[int, set[int]]) -> str:
    """Where the missing views `first` .. `last` were. Chunks hold the views in pose order, numbered upwards
    (docs/capture_format.md): chunk numbers free between the chunks of the views either side of the run are the
    chunks that held it (moved out). A run after the last view held may be a copy cut short or still under way, or
    the last chunk moved out: nothing tells them apart."""
    views = f"view {first}" if first == last else f"views {first}-{last}"
    verb = "is" if first == last else "are"
    before, after = chunk_of.get(first - 1), chunk_of.get(last + 1)
    if after is None and before is not None:
        return (f"{views} after its last chunk, {chunk_name(before)}, {verb} missing (a copy cut short or still under "
                f"way, or a chunk moved out?)")
    start = 0 if before is None else before + 1
    free = [n for n in range(start, start if after is None else after) if n not in held]
    if not free:
        return f"{views} {verb} in none of its chunks"
    chunks = names_said([chunk_name(n) for n in free], last_and=True)
    return f"{chunks} ({views}) {'is' if len(free) == 1 else 'are'} missing"


__all__ = ["RESULT_FILES", "JOB_FILES", "check_out", "check_capture_folder", "check_ground_truth_kept", "export_mesh",
           "capture_state_note", "missing_views_note", "chunk_views", "replacing_result", "held_result"]
