"""`spadscan reconstruct --out DIR` writes its result beside DIR, in a hidden scratch folder, and moves it in once it
has finished: a result a worker publishes into `<scan>/recon/<job>/` while a hand run goes is never mixed with the
hand run's files, nor replaced in silence.

The reconstruction is a stand-in (`reconstruct_capture` patched): what is under test is where its files go."""

from __future__ import annotations

import json
import os

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import SpadscanError
from spadscan.worker import reconstruct as reconstruct_module
from spadscan.worker.jobs import COMPLETE

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
