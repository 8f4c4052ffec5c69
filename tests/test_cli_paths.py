"""Folders a command must make (--out, --queue, a rig's `captures`) are checked before it runs: one that cannot be made
(a file in the way, a place like /proc that no one can write, root included) is refused in one line that names the
option or key and the user's own path, never an internal one; one that can be made is left unmade by the check."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.protocol.folders import folder_problem

UNMAKEABLE = "/proc/spadscan-test"
"""A folder that no user can create, root included (os.access says yes to root; the real mkdir says no)."""

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a Linux /proc")

RIG = """
captures = "{captures}"
socket = "{socket}"
[arm]
backend = "sim"
[sensor]
backend = "sim"
mesh = "builtin:sphere"
[scan]
views = 8
"""

SWEEP = """
[sweep]
scenes = ["builtin:sphere"]
presets = ["fast"]
baselines = []
[base]
views = 8
rays_per_zone = 256
[grid]
views = [8, 12]
"""


def one_line_error(capsys) -> str:
    """The command's error line (stderr: one line; stdout: nothing, so no listing or suggestion came before it)."""
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and "Traceback" not in captured.err, captured
    return captured.err.strip()


def listing(folder: Path) -> list[str]:
    """Every name under `folder`, hidden ones included (a check's scratch folder would show here)."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    """The test's folder as the current folder, holding `afile` (a regular file) and `caps` (an empty captures
    root)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "caps").mkdir()
    return tmp_path


# ---- worker --queue (defect: --status listed a file as an empty queue and suggested a start that fails) ----------
@pytest.mark.parametrize("queue, reason", [
    ("afile", "no such queue folder (a file, not a folder)"),
    ("afile/q", "afile is a file, not a folder"),
    (UNMAKEABLE, "cannot create it"),
])
def test_worker_status_refuses_a_queue_that_cannot_be_a_folder(here, capsys, queue, reason):
    before = listing(here)
    assert main(["worker", "--root", "caps", "--queue", queue, "--status"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --queue {queue}: {reason}")
    assert listing(here) == before


def test_a_worker_started_on_a_file_as_queue_names_the_option_not_an_inner_path(here, capsys):
    assert main(["worker", "--root", "caps", "--queue", "afile", "--once"]) == 1
    err = one_line_error(capsys)
    assert err == "spadscan: error: --queue afile: no such queue folder (a file, not a folder)", err


@pytest.mark.parametrize("queue", ["cap1", "cap1/q"])
@pytest.mark.parametrize("flag", ["--once", "--status"])
def test_a_worker_refuses_a_queue_that_is_or_lies_inside_a_capture(here, capsys, queue, flag):
    (here / "cap1").mkdir()
    (here / "cap1" / "scan.json").write_text("{}")
    before = listing(here)
    assert main(["worker", "--root", "caps", "--queue", queue, flag]) == 1
    where = "is a capture" if queue == "cap1" else f"lies inside the capture {here.resolve() / 'cap1'}"
    assert one_line_error(capsys) == (f"spadscan: error: --queue {queue} {where} (it holds scan.json): the queue's "
                                      f"folders would be mixed into its measurements; choose a folder outside it")
    assert listing(here) == before, "nothing written into the capture"


def test_worker_status_lists_a_queue_that_can_be_made_as_empty_and_makes_nothing(here, capsys):
    before = listing(here)
    assert main(["worker", "--root", "caps", "--queue", "new/q", "--status"]) == 0
    assert "no jobs in new/q" in capsys.readouterr().out
    assert main(["worker", "--root", "caps", "--status"]) == 0  # a root without its queue yet: empty, as before
    assert "no jobs in caps/.queue" in capsys.readouterr().out
    assert listing(here) == before


# ---- daemon `captures` (defect: --check passed /proc/..., start-up said a bare "No such file or directory") ------
def write_rig(folder: Path, captures: str, sock_dir: Path) -> Path:
    """The rig config in `folder`, its socket in `sock_dir` (the fixture's short folder: beside the config, under a
    long TMPDIR, its path would pass the 107 bytes a Unix socket may have, refused before what these tests check)."""
    path = folder / "rig.toml"
    path.write_text(RIG.format(captures=captures, socket=sock_dir / "ctl.sock"))
    return path


@pytest.fixture
def never_serves(monkeypatch):
    """A daemon start that gets past its captures root stops at the socket, with an error, instead of serving."""
    from spadscan.daemon import app
    from spadscan.protocol.errors import ConfigError

    def stop(path):
        raise ConfigError("start-up went past the captures root")

    monkeypatch.setattr(app, "claim_socket_path", stop)


@pytest.mark.parametrize("flags", [["--check"], []])
def test_daemon_refuses_a_captures_root_that_cannot_be_made_naming_the_config_and_key(tmp_path, sock_dir, capsys,
                                                                                       flags, never_serves):
    """--check refuses what start-up would fail on. (As root the refusal is the creation tried; as another user,
    /proc is already not writable by os.access: either names the config file and `captures`.)"""
    rig = write_rig(tmp_path, UNMAKEABLE, sock_dir)
    assert main(["daemon", "--config", str(rig), *flags]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: {rig}: captures {UNMAKEABLE}: ")


def test_daemon_start_up_names_the_config_and_the_key_when_its_own_mkdir_fails(tmp_path, sock_dir, capsys,
                                                                              monkeypatch, never_serves):
    """Start-up's own mkdir, after the checks passed (a file took the folder's place since), is named as --check's
    refusals are."""
    from spadscan.daemon import app

    monkeypatch.setattr(app, "check_captures_creatable", lambda root: root.write_text("took its place"))
    rig = write_rig(tmp_path, "caps", sock_dir)
    assert main(["daemon", "--config", str(rig)]) == 1
    err = one_line_error(capsys)
    assert err.startswith(f"spadscan: error: {rig}: captures {tmp_path / 'caps'}: cannot create the folder"), err


def test_daemon_check_passes_a_captures_root_that_can_be_made_and_makes_nothing(tmp_path, sock_dir, capsys):
    rig = write_rig(tmp_path, "caps", sock_dir)
    before = listing(tmp_path)
    assert main(["daemon", "--config", str(rig), "--check"]) == 0
    assert "ok" in capsys.readouterr().out
    assert listing(tmp_path) == before


# ---- --out of import-lcspc, sweep and reconstruct (defect: bare OS errors, or a hidden scratch path named) --------
def test_import_lcspc_names_out_when_it_cannot_be_made(here, capsys):
    (here / "s.json").write_text("[]")  # never read: --out is refused first
    assert main(["import-lcspc", "s.json", "--out", f"{UNMAKEABLE}/zz", "--no-progress"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {UNMAKEABLE}/zz: cannot create it")
    assert main(["import-lcspc", "s.json", "--out", "afile/cap", "--no-progress"]) == 1
    assert one_line_error(capsys) == "spadscan: error: --out afile/cap: afile is a file, not a folder"
    assert main(["import-lcspc", "s.json", "--out", "afile", "--no-progress"]) == 1
    assert one_line_error(capsys) == "spadscan: error: --out afile: a file, not a folder"


def test_sweep_names_out_when_it_cannot_be_made(here, capsys):
    (here / "s.toml").write_text(SWEEP)
    assert main(["sweep", "s.toml", "--out", f"{UNMAKEABLE}/sw", "--workers", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"spadscan: error: --out {UNMAKEABLE}/sw: cannot create it"), err


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]])
def test_sweep_names_out_when_it_is_a_file_before_its_plan(here, capsys, dry_run):
    (here / "s.toml").write_text(SWEEP)
    assert main(["sweep", "s.toml", "--out", "afile", "--workers", "1", "--no-progress", *dry_run]) == 1
    assert one_line_error(capsys) == "spadscan: error: --out afile: a file, not a folder"
    assert (here / "afile").read_text() == "x"


@pytest.mark.parametrize("out", ["afile/sub", f"{UNMAKEABLE}/sw"])
def test_sweep_dry_run_refuses_the_out_the_run_refuses(here, capsys, out):
    """--dry-run checks the file and the folder as the run does: it lists no points for a folder the run refuses."""
    (here / "s.toml").write_text(SWEEP)
    before = listing(here)
    assert main(["sweep", "s.toml", "--out", out, "--dry-run"]) == 1
    captured = capsys.readouterr()
    assert captured.out == "", captured.out
    assert captured.err.strip().splitlines()[-1].startswith(f"spadscan: error: --out {out}: "), captured.err
    assert listing(here) == before


def test_sweep_dry_run_passes_a_relative_or_linked_out_and_makes_nothing(here, capsys):
    (here / "s.toml").write_text(SWEEP)
    (here / "results").mkdir()
    (here / "link").symlink_to("results")
    before = listing(here)
    for out in ("new/deeper", "link", "link/new"):
        assert main(["sweep", "s.toml", "--out", out, "--dry-run"]) == 0, capsys.readouterr().err
        assert "2 points, 0 done, 2 to run" in capsys.readouterr().out
    assert listing(here) == before


@pytest.fixture
def stub(here) -> str:
    """`stub`, a capture folder to the checks before the run (it holds a scan.json), which the run cannot read."""
    (here / "stub").mkdir()
    (here / "stub" / "scan.json").write_text("{}")
    return "stub"


def test_reconstruct_names_out_not_its_scratch_folder(here, stub, capsys):
    assert main(["reconstruct", stub, "--out", f"{UNMAKEABLE}/x"]) == 1
    err = one_line_error(capsys)
    assert err.startswith(f"spadscan: error: --out {UNMAKEABLE}/x: cannot create it") and ".tmp-" not in err, err
    assert main(["reconstruct", stub, "--out", "afile/x"]) == 1
    assert one_line_error(capsys) == "spadscan: error: --out afile/x: afile is a file, not a folder"


@pytest.mark.parametrize("out", ["result", "link", "new/deeper", "link/new"])
def test_reconstruct_passes_an_existing_linked_or_new_out(here, stub, capsys, out):
    """A result folder with --overwrite, a link to a folder, a relative new path: the --out check lets each through
    (the run then stops at the capture it cannot read) and leaves nothing behind."""
    (here / "result").mkdir()
    (here / "result" / "mesh.ply").write_text("an earlier result")
    (here / "link").symlink_to("result")
    before = listing(here)
    assert main(["reconstruct", stub, "--out", out, "--overwrite"]) == 1
    err = one_line_error(capsys)
    assert "--out" not in err and "stub/scan.json" in err, err
    assert listing(here) == before


def test_reconstruct_says_an_empty_captures_root_is_no_capture_before_its_out(here, capsys):
    """A folder without scan.json (here the empty captures root) is said to be no capture before --out is judged."""
    assert main(["reconstruct", "caps", "--out", "afile/x"]) == 1
    assert one_line_error(capsys).startswith("spadscan: error: caps: not a capture folder (no scan.json; ")


# ---- a mesh file without a suffix (defect: "format '.'") ----------------------------------------------------------
def test_a_mesh_file_without_a_suffix_is_said_to_have_none(here, capsys):
    assert main(["eval", "afile", "--gt", "builtin:mug"]) == 1
    assert one_line_error(capsys) == ("spadscan: error: afile: not a mesh file spadscan can read (no file suffix; use "
                                      "PLY, STL, OBJ, OFF or GLB)")
    (here / "a.docx").write_text("x")
    assert main(["eval", "a.docx", "--gt", "builtin:mug"]) == 1
    assert "(format '.docx'; use PLY" in one_line_error(capsys)


# ---- the check itself -----------------------------------------------------------------------------------------------
def test_folder_problem_tries_a_folder_that_is_there_and_one_that_is_not(here):
    (here / "dir").mkdir()
    (here / "dangling").symlink_to("nowhere")
    before = listing(here)
    assert folder_problem("dir") is None and folder_problem(here / "dir") is None
    # /proc: there, and no one may make a folder in it (os.access says yes to root): tried, unless only read.
    assert folder_problem("/proc").startswith("cannot write into it (")
    assert folder_problem("/proc", writable=False) is None and folder_problem("dir", writable=False) is None
    assert folder_problem(f"{UNMAKEABLE}/a", writable=False).startswith("cannot create it (")
    assert folder_problem("new/a/b") is None
    assert folder_problem("afile") == "a file, not a folder"
    assert folder_problem("dangling") == "a link to a missing folder"
    assert folder_problem("dangling/q") == "dangling is a link to a missing folder"  # the run would fail at its mkdir
    assert folder_problem("afile/a/b") == "afile is a file, not a folder"
    assert folder_problem(f"{UNMAKEABLE}/a").startswith("cannot create it (")
    assert listing(here) == before
