"""A CAPTURE that is no capture folder is said to be none, first: `spadscan reconstruct . --out results` run in the
wrong folder was told that --out lies inside "the capture", and a folder of captures was reported as
"caps/scan.json: missing". A folder of captures names some of them."""

from __future__ import annotations

from pathlib import Path

import pytest

from spadscan.cli import main

NOT_A_CAPTURE = ("spadscan: error: {path}: not a capture folder (no scan.json; a capture is the folder that holds "
                 "scan.json and its chunk-NNNNNN folders)")


def one_line_error(capsys) -> str:
    """The command's error line (stderr: one line; stdout: nothing)."""
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and "Traceback" not in captured.err, captured
    return captured.err.strip()


def listing(folder: Path) -> list[str]:
    """Every name under `folder`, hidden ones included."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    """The test's folder as the current folder, holding `plain` (a folder of the user's files, no capture)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("mine")
    return tmp_path


def stub_capture(folder: Path) -> None:
    """A folder that holds a scan.json (what makes it a capture folder to the check; its content is the reader's)."""
    folder.mkdir(parents=True)
    (folder / "scan.json").write_text("{}")


COMMANDS = [pytest.param(["reconstruct"], id="reconstruct"),
            pytest.param(["baseline", "space-carving"], id="baseline")]


@pytest.mark.parametrize("command", COMMANDS)
def test_a_plain_folder_holding_out_is_said_to_be_no_capture_not_that_out_lies_inside_it(here, capsys, command):
    before = listing(here)
    assert main([*command, "plain", "--out", "plain/x"]) == 1
    assert one_line_error(capsys) == NOT_A_CAPTURE.format(path="plain")
    assert main([*command, ".", "--out", "results"]) == 1  # run in the wrong folder
    assert one_line_error(capsys) == NOT_A_CAPTURE.format(path=".")
    assert listing(here) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_a_missing_capture_holding_out_is_said_to_be_missing(here, capsys, command):
    assert main([*command, "nosuch", "--out", "nosuch/x"]) == 1
    assert one_line_error(capsys) == "spadscan: error: nosuch: no such capture folder"
    assert main([*command, "plain/notes.txt", "--out", "x"]) == 1
    assert one_line_error(capsys) == "spadscan: error: plain/notes.txt: a file, not a capture folder"
    assert not (here / "nosuch").exists() and not (here / "x").exists()


@pytest.mark.parametrize("command", COMMANDS)
def test_a_folder_of_captures_names_some_of_them(here, capsys, command):
    for name in ("b", "a"):
        stub_capture(here / "caps" / name)
    (here / "caps" / "notes").mkdir()  # a folder without scan.json is no capture: not named
    assert main([*command, "caps", "--out", "x"]) == 1
    assert one_line_error(capsys) == ("spadscan: error: caps: not a capture folder (no scan.json); it holds captures: "
                                      "caps/a and caps/b; name one")
    for name in ("c", "d", "e"):
        stub_capture(here / "caps" / name)
    assert main([*command, "caps", "--out", "caps/x"]) == 1
    assert one_line_error(capsys) == ("spadscan: error: caps: not a capture folder (no scan.json); it holds captures: "
                                      "caps/a, caps/b, caps/c and 2 more; name one")
    assert not (here / "x").exists() and not (here / "caps" / "x").exists()


def test_a_capture_folder_still_keeps_out_of_its_measurements(here, capsys):
    """The capture check lets a folder with scan.json through to the --out checks."""
    stub_capture(here / "cap")
    assert main(["reconstruct", "cap", "--out", "cap/x"]) == 1
    assert one_line_error(capsys).startswith("spadscan: error: --out cap/x lies inside the capture cap: ")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_chunk_or_the_manifest_of_a_capture_names_the_capture(here, capsys, command):
    stub_capture(here / "cap")
    (here / "cap" / "chunk-000000").mkdir()
    (here / "cap" / "recon").mkdir()
    before = listing(here)
    for part, what in (("cap/chunk-000000", "a chunk of the capture"), ("cap/scan.json", "the manifest of the capture"),
                       ("cap/recon", "a folder in the capture")):
        assert main([*command, part, "--out", "x"]) == 1
        assert one_line_error(capsys) == f"spadscan: error: {part}: {what} cap; name cap"
    assert main([*command, "cap/chunk-000009", "--out", "x"]) == 1  # not there: said as any missing folder
    assert one_line_error(capsys) == "spadscan: error: cap/chunk-000009: no such capture folder"
    assert listing(here) == before
