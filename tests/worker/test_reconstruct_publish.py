"""`spadscan reconstruct --out DIR` writes its result beside DIR, in a hidden scratch folder, and moves it in once it
has finished: a result a worker publishes into `<scan>/recon/<job>/` while a hand run goes is never mixed with the
hand run's files, nor replaced in silence.

The reconstruction is a stand-in (`reconstruct_capture` patched): what is under test is where its files go."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import SpadscanError
from spadscan.worker import reconstruct as reconstruct_module
from spadscan.worker.jobs import COMPLETE, move_aside

RUN_FILES = {"mesh.ply": "the hand run's mesh", "report.json": json.dumps({"steps": 5}),
             "report.html": "the hand run's page"}
WORKER_FILES = {"mesh.ply": "the job's mesh", "report.json": json.dumps({"steps": None}),
                "job.json": json.dumps({"id": "s-fast", "scan": "s"}), "job.log": "the job's log",
                COMPLETE: json.dumps({"job": "s-fast", "token": "0" * 16, "queue": "/q"})}


def _files(folder):
    return {p.name: p.read_text() for p in folder.iterdir() if p.is_file()}


def _write(folder, files):
    folder.mkdir(parents=True)
    for name, text in files.items():
        (folder / name).write_text(text)


@pytest.fixture
def hand_run(tmp_path, monkeypatch):
    """Run `spadscan reconstruct CAPTURE --out OUT` with a stand-in reconstruction that writes RUN_FILES into the
    folder it is given, calling `meanwhile(folder)` half-way (a worker publishing, say). Returns the exit status."""
    capture = tmp_path / "s"
    capture.mkdir()
    (capture / "scan.json").write_text("{}")  # a capture folder to the early check; the run is a stand-in

    def run(out, *extra, meanwhile=None):
        def stand_in(capture, out_dir, **kwargs):
            out_dir.mkdir(parents=True, exist_ok=True)
            (out_dir / "mesh.ply").write_text(RUN_FILES["mesh.ply"])
            if meanwhile is not None:
                meanwhile(out_dir)
            for name in ("report.json", "report.html"):
                (out_dir / name).write_text(RUN_FILES[name])
            return {"preset": "fast", "steps": 5, "seconds": 1.0, "wall_seconds": 1.5, "device": "cpu",
                    "converged": False, "final_loss": 1.0, "files": sorted(RUN_FILES)}

        monkeypatch.setattr(reconstruct_module, "reconstruct_capture", stand_in)
        return main(["reconstruct", str(capture), "--out", str(out), "--no-gt", "--no-progress", *extra])

    return run


def _worker_publishes(final):
    """What the worker's publishing does to `final` (jobs.move_aside, then one rename of its scratch folder)."""
    def publish(running_in):
        assert not final.exists() or not (final / "mesh.ply").exists(), "the hand run writes nothing into --out yet"
        scratch = final.with_name(".tmp-s-fast-0123456789abcdef")
        _write(scratch, WORKER_FILES)
        os.rename(scratch, final)
    return publish


def test_a_result_a_worker_publishes_meanwhile_is_kept_and_the_run_is_refused_saying_where_its_own_is(
        tmp_path, hand_run, capsys):
    final = tmp_path / "s" / "recon" / "s-fast"
    assert hand_run(final, meanwhile=_worker_publishes(final)) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error:")]
    assert len(errors) == 1 and "appeared there while this run went" in errors[0], errors
    assert _files(final) == WORKER_FILES, "the worker's result stands as it published it"
    (kept,) = [p for p in final.parent.iterdir() if p.name.startswith("s-fast.new-")]
    assert str(kept) in errors[0]
    assert _files(kept) == RUN_FILES, "the hand run's result is kept, whole, beside it"
    assert sorted(p.name for p in final.parent.iterdir()) == ["s-fast", kept.name], "no scratch folder is left"


def test_with_overwrite_a_result_published_meanwhile_is_moved_aside_whole(tmp_path, hand_run, capsys):
    final = tmp_path / "s" / "recon" / "s-fast"
    assert hand_run(final, "--overwrite", meanwhile=_worker_publishes(final)) == 0
    assert _files(final) == RUN_FILES, "none of the job's files stand beside the hand run's mesh"
    (aside,) = [p for p in final.parent.iterdir() if p.name.startswith("s-fast.replaced-")]
    assert _files(aside) == WORKER_FILES
    assert f"moved that result aside to {aside}" in capsys.readouterr().err
    assert sorted(p.name for p in final.parent.iterdir()) == ["s-fast", aside.name]


def test_a_new_folder_appears_whole_and_a_users_own_folder_keeps_their_files(tmp_path, hand_run):
    new = tmp_path / "results" / "new"
    seen = []
    assert hand_run(new, meanwhile=lambda running_in: seen.append((running_in.parent, new.exists()))) == 0
    assert seen == [(new.parent, False)], "written beside --out, which does not exist until the run has finished"
    assert _files(new) == RUN_FILES and sorted(p.name for p in new.parent.iterdir()) == ["new"]
    own = tmp_path / "results" / "own"
    _write(own, {"notes.txt": "the user's own notes"})
    assert hand_run(own, meanwhile=lambda running_in: seen.append(_files(own))) == 0
    assert seen[-1] == {"notes.txt": "the user's own notes"}, "nothing of the run's in --out while it goes"
    assert _files(own) == {**RUN_FILES, "notes.txt": "the user's own notes"}
    assert sorted(p.name for p in own.parent.iterdir()) == ["new", "own"]


def test_an_overwrite_keeps_the_previous_result_whole_until_the_run_has_finished(tmp_path, hand_run, capsys):
    out = tmp_path / "out"
    previous = {"mesh.ply": "the previous mesh", "normals.png": "the previous normals",
                "report.json": json.dumps({"files": ["mesh.ply", "normals.png", "report.json"]}),
                "notes.txt": "the user's own notes"}
    _write(out, previous)
    seen = []
    assert hand_run(out, "--overwrite", meanwhile=lambda running_in: seen.append(_files(out))) == 0
    assert seen == [previous]
    assert _files(out) == {**RUN_FILES, "notes.txt": "the user's own notes"}
    assert "removed the replaced result's normals.png (this run wrote none)" in capsys.readouterr().err


def test_a_run_that_fails_leaves_no_folder_and_the_previous_result_as_it_was(tmp_path, hand_run):
    out = tmp_path / "out"
    previous = {"mesh.ply": "the previous mesh", "report.json": "{}"}
    _write(out, previous)

    def fails(running_in):
        raise SpadscanError("the run failed")

    assert hand_run(out, "--overwrite", meanwhile=fails) == 1
    assert _files(out) == previous and sorted(p.name for p in tmp_path.iterdir()) == ["out", "s"]
    # a new --out in folders that do not exist yet: the run that fails leaves none of them
    assert hand_run(tmp_path / "results" / "today" / "new", meanwhile=fails) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "s"]


def _inside(path, folder) -> bool:
    return Path(os.path.abspath(path)).is_relative_to(folder)


def _mount_point(monkeypatch, mount, blocked=()):
    """Make `mount` behave as another filesystem's mount point: a rename in or out of it fails as across
    filesystems (EXDEV). A rename or a new folder in the folders `blocked` fails as in one the user cannot write."""
    for name in ("rename", "replace"):
        real = getattr(os, name)

        def move(src, dst, *args, real=real, **kwargs):
            if _inside(src, mount) != _inside(dst, mount):
                raise OSError(errno.EXDEV, "Invalid cross-device link", os.fspath(src), None, os.fspath(dst))
            if any(Path(os.path.abspath(p)).parent in blocked for p in (src, dst)):
                raise PermissionError(errno.EACCES, "Permission denied", os.fspath(src))
            return real(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, name, move)
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):
        if Path(os.path.abspath(path)).parent in blocked:
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)


def _hidden(*folders):
    return [p for folder in folders for p in folder.iterdir() if p.name.startswith(".tmp-")]


def test_an_out_that_is_a_mount_point_gets_the_result_moved_in_within_its_filesystem(tmp_path, hand_run, monkeypatch,
                                                                                       capsys):
    mount = tmp_path / "mnt"
    _write(mount, {"notes.txt": "the user's own notes"})
    _mount_point(monkeypatch, mount)
    seen = []
    assert hand_run(mount, meanwhile=lambda running_in: seen.append(running_in.parent)) == 0, capsys.readouterr().err
    assert seen == [mount], "written inside --out: a rename from beside it would cross filesystems"
    assert _files(mount) == {**RUN_FILES, "notes.txt": "the user's own notes"}
    assert not _hidden(tmp_path, mount)
    # --overwrite replaces the previous result there the same way, the user's files kept
    assert hand_run(mount, "--overwrite") == 0
    assert _files(mount) == {**RUN_FILES, "notes.txt": "the user's own notes"} and not _hidden(tmp_path, mount)


def test_a_result_that_appears_meanwhile_in_a_mount_point_is_kept_and_the_runs_own_kept_inside_it(
        tmp_path, hand_run, monkeypatch, capsys):
    mount = tmp_path / "mnt"
    mount.mkdir()
    _mount_point(monkeypatch, mount)
    other = {"mesh.ply": "another run's mesh", "report.json": "{}"}

    def another_run_publishes(running_in):
        for name, text in other.items():
            (mount / name).write_text(text)

    assert hand_run(mount, meanwhile=another_run_publishes) == 1
    (error,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error:")]
    (kept,) = [p for p in mount.iterdir() if p.is_dir()]
    assert kept.name.startswith("mnt.new-") and str(kept) in error
    assert _files(mount) == other and _files(kept) == RUN_FILES and not _hidden(tmp_path, mount)


def test_out_dot_is_written_though_its_parent_cannot_be(tmp_path, hand_run, monkeypatch, capsys):
    shared = tmp_path / "shared"
    results = shared / "results"
    _write(results, {"notes.txt": "the user's own notes"})
    _mount_point(monkeypatch, tmp_path / "elsewhere", blocked={shared})
    monkeypatch.chdir(results)
    assert hand_run(".") == 0, capsys.readouterr().err
    assert _files(results) == {**RUN_FILES, "notes.txt": "the user's own notes"}
    assert sorted(p.name for p in shared.iterdir()) == ["results"] and not _hidden(results)
    # a new --out there cannot be made: said in one line, naming the folder that cannot be written
    assert hand_run(shared / "new") == 1
    (error,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error:")]
    assert f"--out {shared / 'new'}: cannot create it (Permission denied" in error


def test_a_move_into_out_that_fails_at_the_end_says_where_the_whole_result_is(tmp_path, hand_run, monkeypatch,
                                                                              capsys):
    out = tmp_path / "out"
    previous = {"mesh.ply": "the previous mesh", "report.json": "{}", "notes.txt": "the user's own notes"}
    _write(out, previous)
    real, calls = os.replace, []

    def replace(src, dst, *args, **kwargs):
        if Path(src).parent.name.startswith(".tmp-") and Path(dst).parent == out:
            calls.append(src)
            if len(calls) == 2:
                raise OSError(errno.EIO, "Input/output error", os.fspath(src))
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    assert hand_run(out, "--overwrite") == 1
    (error,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error:")]
    (scratch,) = _hidden(tmp_path)
    assert f"this run's finished result is whole in {scratch}" in error and "Input/output error" in error
    assert _files(scratch) == RUN_FILES, "nothing of the finished result lost"
    assert _files(out) == previous, "the previous result as it was"


def _worker_replaces(final):
    """What the worker's publishing does to an existing `final`: moves it aside whole, renames its result in."""
    def publish(running_in):
        move_aside(final)
        scratch = final.with_name(".tmp-s-fast-0123456789abcdef")
        _write(scratch, WORKER_FILES)
        os.rename(scratch, final)
    return publish


@pytest.mark.parametrize("overwrite", [False, True])
def test_an_existing_out_a_worker_replaces_meanwhile_is_never_mixed_with_the_runs_result(tmp_path, hand_run,
                                                                                         overwrite):
    final = tmp_path / "s" / "recon" / "s-fast"
    # a folder of the user's own, or (--overwrite) an earlier result the job is being redone over
    before = {"mesh.ply": "an earlier mesh", "report.json": "{}"} if overwrite else {"notes.txt": "own notes"}
    _write(final, before)
    extra = ["--overwrite"] if overwrite else []
    assert hand_run(final, *extra, meanwhile=_worker_replaces(final)) == (0 if overwrite else 1)
    others = sorted((_files(p) for p in final.parent.iterdir() if p != final), key=lambda files: sorted(files))
    if overwrite:  # both set aside whole: the earlier result by the worker, the worker's by this run
        assert _files(final) == RUN_FILES and others == sorted([before, WORKER_FILES], key=sorted)
    else:
        assert _files(final) == WORKER_FILES and others == sorted([before, RUN_FILES], key=sorted)
    assert not _hidden(final.parent, final)


def test_a_scratch_folder_a_killed_run_left_is_named_by_the_next_run_into_that_out(tmp_path, hand_run, capsys):
    out = tmp_path / "out"
    left = tmp_path / ".tmp-out-0123abcd"
    _write(left, {"mesh.ply": "a killed run's mesh"})
    worker_scratch = tmp_path / ".tmp-out-0123456789abcdef"  # a worker's (16 hex digits): not this command's
    worker_scratch.mkdir()
    assert hand_run(out) == 0
    err = capsys.readouterr().err
    assert f"{left}: the scratch folder of an earlier run into this --out that never finished" in err
    assert str(worker_scratch) not in err
    assert _files(left) == {"mesh.ply": "a killed run's mesh"}, "left for the user: it may be a running one's"


STOPPABLE_RUN = """
import sys, time
from spadscan.cli import main
from spadscan.worker import reconstruct

def stand_in(capture, out_dir, **kwargs):
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "mesh.ply").write_text("half a result")
    print("writing", flush=True)
    time.sleep(120)  # a bound, not a wait: the test stops it long before
    raise SystemExit("never stopped")

reconstruct.reconstruct_capture = stand_in
sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_stops_a_run_as_ctrl_c_does_leaving_no_scratch_folder(tmp_path):
    capture, out = tmp_path / "s", tmp_path / "out"
    capture.mkdir()
    (capture / "scan.json").write_text("{}")  # a capture folder to the early check; the run is a stand-in
    previous = {"mesh.ply": "the previous mesh", "report.json": "{}"}
    _write(out, previous)
    proc = subprocess.Popen([sys.executable, "-c", STOPPABLE_RUN, "reconstruct", str(capture), "--out", str(out),
                             "--no-gt", "--no-progress", "--overwrite"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "writing\n", "the run ended before it could be stopped"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "spadscan: interrupted", err
    assert _files(out) == previous and not _hidden(tmp_path, out)
