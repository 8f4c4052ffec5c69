"""What `spadscan eval` records beside its numbers: the box it scored inside (--box), the units it read, and a note
when the two meshes plainly cannot be the same object in the same frame and units."""

from __future__ import annotations

import json

import pytest
import trimesh

from spadscan.cli import main
from spadscan.worker.metrics import crop_to_box

N = 5_000
BOX = ["-0.2", "-0.2", "0.001", "0.2", "0.2", "0.3"]


def ball(radius=0.1, center=(0, 0, 0.1)):
    return trimesh.creation.icosphere(subdivisions=4, radius=radius).apply_translation(center)


def on_table():
    """A ball standing on a 2 m slab whose top is z = 0: the ground truth of a real scene, table included."""
    plate = trimesh.creation.box([2.0, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    return trimesh.util.concatenate([plate, ball()])


def evaluate(capsys, mesh, gt, *options) -> tuple[int, str, str]:
    rc = main(["eval", str(mesh), "--gt", str(gt), "--points", str(N), *options])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def row(table: str, name: str) -> str | None:
    """The value of the table's row `name`, or None when it has none."""
    return next((line[len(name):].strip() for line in table.splitlines() if line.startswith(name + " ")), None)


# ---- the box ---------------------------------------------------------------------------------------------------------
def test_a_score_inside_a_box_names_the_box_in_the_table_and_the_json(tmp_path, capsys):
    on_table().export(tmp_path / "gt.ply")
    ball().export(tmp_path / "recon.ply")
    rc, out, err = evaluate(capsys, tmp_path / "recon.ply", tmp_path / "gt.ply", "--box", *BOX)
    assert rc == 0, err
    assert row(out, "scored") == "both meshes inside the box [-0.2, -0.2, 0.001] .. [0.2, 0.2, 0.3] m (--box)"
    rc, out, err = evaluate(capsys, tmp_path / "recon.ply", tmp_path / "gt.ply", "--box", *BOX, "--json")
    assert rc == 0, err
    record = json.loads(out)
    assert record["box_m"] == [[-0.2, -0.2, 0.001], [0.2, 0.2, 0.3]] and record["cut_above_z_m"] is None


def test_a_score_without_a_box_records_none(tmp_path, capsys):
    ball().export(tmp_path / "gt.ply")
    rc, out, err = evaluate(capsys, tmp_path / "gt.ply", tmp_path / "gt.ply", "--json")
    assert rc == 0, err
    assert json.loads(out)["box_m"] is None
    rc, out, _ = evaluate(capsys, tmp_path / "gt.ply", tmp_path / "gt.ply")
    assert row(out, "scored") is None


def test_keep_table_with_a_box_is_refused_in_one_line(tmp_path, capsys):
    """The box replaces the cut above a table (what of the table lies in the box is scored): --keep-table would do
    nothing, and the help said the box is used instead of the cut."""
    on_table().export(tmp_path / "gt.ply")
    rc, out, err = evaluate(capsys, tmp_path / "gt.ply", tmp_path / "gt.ply", "--box", *BOX, "--keep-table")
    assert rc == 1 and out == ""
    assert err.startswith("spadscan: error: --keep-table and --box") and err.count("\n") == 1, err


# ---- units -----------------------------------------------------------------------------------------------------------
def test_units_forced_to_millimetres_are_named_in_the_table(tmp_path, capsys):
    ball(100.0, (0, 0, 100.0)).export(tmp_path / "gt.ply")
    rc, out, err = evaluate(capsys, tmp_path / "gt.ply", tmp_path / "gt.ply", "--units", "mm")
    assert rc == 0, err
    assert row(out, "units") == "both read as millimetres (--units mm)"
    ball().export(tmp_path / "m.ply")
    rc, out, _ = evaluate(capsys, tmp_path / "m.ply", tmp_path / "m.ply")
    assert row(out, "units") is None  # metres, the default, need no row


# ---- meshes that cannot be the same object ---------------------------------------------------------------------------
@pytest.mark.parametrize("case, said", [
    ("in centimetres read as metres", "the reconstruction is 10x the size of the ground truth"),
    ("in another frame", "the bounding boxes of the reconstruction and the ground truth do not overlap"),
])
def test_meshes_that_plainly_differ_get_a_note_and_keep_their_score(tmp_path, capsys, case, said):
    ball().export(tmp_path / "gt.ply")
    wrong = ball(1.0, (0, 0, 1.0)) if case == "in centimetres read as metres" else ball(center=(2.0, 0, 0.1))
    wrong.export(tmp_path / "recon.ply")
    rc, out, err = evaluate(capsys, tmp_path / "recon.ply", tmp_path / "gt.ply")
    assert rc == 0, err
    note = row(out, "note")
    assert note is not None and note.startswith(said) and "--units" in note and "frame" in note, out
    assert float(row(out, "Chamfer").split()[0]) > 100  # the score itself stays
    rc, out, _ = evaluate(capsys, tmp_path / "recon.ply", tmp_path / "gt.ply", "--json")
    record = json.loads(out)
    assert record["mismatch_note"] == note and record["chamfer_mm"] > 100


@pytest.mark.parametrize("case", ["itself", "a partial reconstruction", "above a table", "inside a box",
                                  "table kept", "inside a box holding the table", "a built-in scene"])
def test_ordinary_evaluations_get_no_note(tmp_path, capsys, case):
    ball().export(tmp_path / "ball.ply")
    on_table().export(tmp_path / "table.ply")
    # Half of the ball (its top, as a scan that saw little of it): a poor result, not a mistake of units or frame.
    crop_to_box(ball(), [-1, -1, 0.15], [1, 1, 1]).export(tmp_path / "cap.ply")
    mesh, gt, options = {"itself": ("ball.ply", "ball.ply", []),
                         "a partial reconstruction": ("cap.ply", "ball.ply", []),
                         "above a table": ("ball.ply", "table.ply", []),
                         "inside a box": ("ball.ply", "table.ply", ["--box", *BOX]),
                         # a table slab many times the ball's size: no unit or frame mistake
                         "table kept": ("ball.ply", "table.ply", ["--keep-table"]),
                         "inside a box holding the table": ("ball.ply", "table.ply",
                                                            ["--box", "-0.8", "-0.8", "-0.05", "0.8", "0.8", "0.3"]),
                         "a built-in scene": ("builtin:cup", "builtin:cup", [])}[case]
    paths = [m if m.startswith("builtin:") else tmp_path / m for m in (mesh, gt)]
    rc, out, err = evaluate(capsys, *paths, *options)
    assert rc == 0, err
    assert row(out, "note") is None, out
    rc, out, _ = evaluate(capsys, *paths, *options, "--json")
    assert json.loads(out)["mismatch_note"] is None
