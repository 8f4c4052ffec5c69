"""A live result whose preview cannot be drawn (its worker's machine has no off-screen OpenGL) says why, as a run's
report does ("no preview.png: <why>", one line): in the warnings of every live status written while it holds, so in
`spadscan ctl status` and in the dashboard's preview box, and after the job is given back or has failed. The machine
is simulated by the means the drawing's own check asks (offscreen.check_offscreen: the environment and
ctypes.util.find_library), as in test_preview_warning.py."""

from __future__ import annotations

import ctypes.util
from pathlib import Path
from types import SimpleNamespace

import trimesh

from spadscan.dashboard.results import ResultIndex
from spadscan.protocol.live_status import read_status, status_path
from spadscan.worker.jobs import Job
from spadscan.worker.live.follower import ScanProgress
from spadscan.worker.live.done import mark_live_failed, mark_live_queued
from spadscan.worker.live.job import LiveRun, LiveSettings
from spadscan.worker.live.publish import MESH, PREVIEW, live_folder, publish_mesh


def cannot_draw_off_screen(monkeypatch) -> None:
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW"):
        monkeypatch.delenv(name, raising=False)
    find = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name in ("EGL", "OSMesa") else find(name))


class Fit:
    """A live fit of 8 views whose mesh is a small sphere (metres)."""

    model = SimpleNamespace(level=1)
    views_used, steps, converged, not_yet = 8, 40, False, None

    def mesh(self, resolution):
        return trimesh.creation.icosphere(subdivisions=1, radius=0.05)

    def remember(self):
        pass


def progress(views: int = 8) -> ScanProgress:
    return ScanProgress(state="running", reason=None, views_published=views, views_planned=40, new_chunks=1,
                        manifest={"updated_utc": f"poll {views}"})


def live_run(root: Path, lines: list, preview: bool = True) -> LiveRun:
    """A live run of scan `root`/s whose fit is `Fit`, logging into `lines`."""
    scan = root / "s"
    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), scan, live_folder(scan), None,
                  LiveSettings(preview=preview), lines.append)
    run.fit = Fit()
    return run


def test_a_live_mesh_whose_preview_cannot_be_drawn_says_why_in_its_status(tmp_path, monkeypatch, capsys):
    cannot_draw_off_screen(monkeypatch)
    lines: list[str] = []
    run = live_run(tmp_path, lines)
    run.publish(progress(8), force=True)
    folder = tmp_path / "s" / "recon" / "live"
    assert (folder / MESH).exists() and not (folder / PREVIEW).exists()
    status = read_status(status_path(tmp_path / "s"))
    (line,) = status.warnings
    assert line.startswith("no preview.png: ") and "off screen" in line and "\n" not in line, line
    assert status.note is None
    assert not list(folder.glob(".*")), "the warning names the published file, and no temporary one is left"

    run.update_status(progress(9), force=True)  # the status alone, between two meshes: it still has no preview
    run.publish(progress(10), force=True)
    status = read_status(status_path(tmp_path / "s"))
    assert (status.views_published, status.warnings) == (10, (line,))
    assert line in status.summary(), "spadscan ctl status says it"
    assert lines.count(f"live: {line}") == 1 and len([x for x in lines if "preview" in x]) == 1, lines
    assert "preview" not in capsys.readouterr().err, "said in the job's log once, not on stderr at every mesh"

    (entry,) = ResultIndex(tmp_path).for_scan("s")
    assert entry["kind"] == "live" and entry["summary"]["warnings"] == [line], "the dashboard lists it"
    assert entry["no_preview"]["why"] == line, "and its preview's box says why"


def test_an_operators_words_in_the_note_are_not_taken_for_the_preview(tmp_path, monkeypatch):
    cannot_draw_off_screen(monkeypatch)
    run = live_run(tmp_path, [])
    run.last = progress(8)  # the follow loop's last poll
    run.publish(run.last, force=True)
    run.stopped("aborted", "scan aborted: no preview needed, the part was wrong")
    status = read_status(status_path(tmp_path / "s"))
    assert status.note == "scan aborted: no preview needed, the part was wrong"
    (entry,) = ResultIndex(tmp_path).for_scan("s")
    assert entry["no_preview"]["why"] == status.warnings[0] and status.warnings[0].startswith("no preview.png: ")


def test_the_warning_stays_when_the_job_is_given_back_or_fails(tmp_path, monkeypatch):
    cannot_draw_off_screen(monkeypatch)
    for i, mark in enumerate((mark_live_queued, mark_live_failed)):
        root = tmp_path / str(i)
        run = live_run(root, [])
        run.publish(progress(8), force=True)
        mark(run.job, root, "the worker was stopped", print)
        status = read_status(status_path(root / "s"))
        assert status.state in ("queued", "stopped") and status.warnings[0].startswith("no preview.png: "), status
        (entry,) = ResultIndex(root).for_scan("s")
        assert entry["no_preview"]["why"] == status.warnings[0], mark.__name__


def test_a_live_job_asked_for_no_preview_says_nothing_of_it(tmp_path, monkeypatch):
    cannot_draw_off_screen(monkeypatch)
    run = live_run(tmp_path, [], preview=False)
    run.publish(progress(8), force=True)
    status = read_status(status_path(tmp_path / "s"))
    assert status.note is None and status.warnings == ()
    assert "warnings" not in status.to_dict(), "a status without doubts is written as before"
    assert publish_mesh(tmp_path, Fit().mesh(8), preview=False) is None
