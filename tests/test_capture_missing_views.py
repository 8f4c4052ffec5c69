"""A capture that says complete but lacks planned views: the warning names the views it lacks and the chunk they were
in. After the capture reader's advice for a damaged chunk (move it out) was followed, the run warned of "a copy cut
short or still under way?", which sent the user looking for a copy problem that was not there."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.worker.outputs import capture_state_note, missing_views_note

VIEWS, CHUNK = 16, 4
"""The capture: 16 views in chunks of 4 (chunk-000002 holds views 8-11)."""


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """A complete simulated capture of VIEWS views, CHUNK to a chunk."""
    cap = tmp_path_factory.mktemp("sim") / "cap"
    assert main(["simulate", "builtin:sphere", "--out", str(cap), "--views", str(VIEWS), "--chunk-size", str(CHUNK),
                 "--no-progress"]) == 0
    return cap


@pytest.fixture
def cap(simulated, tmp_path) -> Path:
    """A copy of the simulated capture, for the test to take chunks out of."""
    return Path(shutil.copytree(simulated, tmp_path / "cap"))


def moved_out(cap: Path, *names: str) -> None:
    """Move chunks out of `cap`, as the reader's advice for a damaged chunk says."""
    (cap.parent / "set-aside").mkdir(exist_ok=True)
    for name in names:
        (cap / name).rename(cap.parent / "set-aside" / name)


def test_the_baseline_names_the_chunk_that_was_moved_out(cap, capsys):
    moved_out(cap, "chunk-000002")
    assert main(["baseline", "space-carving", str(cap), "--out", str(cap.parent / "out"), "--no-gt",
                 "--resolution", "16", "--points", "1000"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "warning:" in line]
    assert warnings == [f"spadscan baseline: warning: {cap}: the capture says complete but holds 12 of its 16 planned "
                        f"views: chunk-000002 (views 8-11) is missing; reconstructed from those"], warnings


def test_chunks_moved_out_at_the_start_and_in_the_middle_are_each_named(cap):
    moved_out(cap, "chunk-000000", "chunk-000002")
    assert capture_state_note(cap, "complete", 8, VIEWS) == (
        f"{cap}: the capture says complete but holds 8 of its 16 planned views: chunk-000000 (views 0-3) is missing; "
        f"chunk-000002 (views 8-11) is missing; reconstructed from those")
    moved_out(cap, "chunk-000001")  # two neighbours: one run of views
    assert missing_views_note(cap, VIEWS) == "chunk-000000, chunk-000001 and chunk-000002 (views 0-11) are missing"


def test_views_missing_at_the_end_may_be_a_copy_cut_short(cap):
    moved_out(cap, "chunk-000003")
    assert capture_state_note(cap, "complete", 12, VIEWS) == (
        f"{cap}: the capture says complete but holds 12 of its 16 planned views: views 12-15 after its last chunk, "
        f"chunk-000002, are missing (a copy cut short or still under way, or a chunk moved out?); reconstructed from "
        f"those")


def test_views_missing_with_no_chunk_number_free_are_said_missing(cap):
    """Chunk numbers need not be contiguous: missing views between two neighbouring numbers are in no chunk."""
    moved_out(cap, "chunk-000002")
    (cap / "chunk-000003").rename(cap / "chunk-000002")
    assert missing_views_note(cap, VIEWS) == "views 8-11 are in none of its chunks"
    assert missing_views_note(cap, VIEWS + 1) == ("views 8-11 are in none of its chunks; view 16 after its last chunk, "
                                                  "chunk-000002, is missing (a copy cut short or still under way, or "
                                                  "a chunk moved out?)")


def test_a_capture_whose_chunks_cannot_be_listed_keeps_the_general_note(tmp_path):
    assert capture_state_note(tmp_path / "gone", "complete", 3, 4) == (
        f"{tmp_path / 'gone'}: the capture says complete but holds 3 of its 4 planned views (a copy cut short or still "
        f"under way?): reconstructed from those")
    assert capture_state_note(tmp_path, "complete", 4, 4) is None
