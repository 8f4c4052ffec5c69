"""LCSPCData import: both kinds detected from the data, everything kept, every malformation a one-line error."""

from __future__ import annotations

import hashlib
import json
import math
import os

import numpy as np
import pytest
import trimesh

from spadscan.cli import main
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import DatasetError
from spadscan.protocol.lcspc import ground_truth_for, import_lcspc, read_lcspc
from spadscan.protocol.sensor_presets import sensor_preset


def look_at_pose(k: int, n: int, radius: float = 0.5) -> list[list[float]]:
    """Sensor pose k of n on a ring above the origin, looking at it (+z toward the origin)."""
    az, el = 2 * math.pi * k / n, math.radians(20 + 40 * k / n)
    pos = radius * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    z = -pos / np.linalg.norm(pos)
    x = np.cross([0, 0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = pos
    return pose.tolist()


def sim_records(n=5, seed=0):
    rng = np.random.default_rng(seed)
    return [{"hists": rng.integers(0, 400, 1024).tolist(), "pose": look_at_pose(k, n)} for k in range(n)]


def real_records(n=4, seed=1):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        out.append({
            "hists": rng.integers(40, 600_000, (9, 128)).tolist(),
            "reference_hist": rng.integers(0, 60_000, 128).tolist(),
            "pose": look_at_pose(k, n),
            "time_captured": 0,
            "joint_angles": rng.uniform(-3, 3, 6).tolist(),
            "distances": [{"temperature": 22 + k, "num_valid_results": 18, "I2C_address": 65, "tick": 1000 + k,
                           "measurement_num": 100 + k, "depths_1": list(range(9)), "depths_2": list(range(9)),
                           "confs_1": [255] * 9, "confs_2": [255] * 9}],
            "custom_field": {"k": k},
        })
    return out


def write_json(path, records):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(records))
    return path


# ---- conversion ----------------------------------------------------------------------------------------------------
def test_simulated_file_becomes_a_single_zone_capture(tmp_path):
    records = sim_records(5)
    src = write_json(tmp_path / "scenes" / "ball.json", records)
    trimesh.creation.icosphere().export(tmp_path / "scenes" / "ball.obj")
    summary = import_lcspc(src, tmp_path / "cap", chunk_size=2)
    assert (summary.kind, summary.sensor, summary.measurements, summary.chunks) == ("simulated", "lcspc-sim", 5, 3)
    r = CaptureReader(tmp_path / "cap")
    assert r.state == "complete" and r.sensor == sensor_preset("lcspc-sim")
    data = r.load()
    assert data.hists.shape == (5, 1, 1024) and data.hists.dtype == np.uint32 and data.reference is None
    np.testing.assert_array_equal(data.hists[:, 0], np.array([rec["hists"] for rec in records]))
    np.testing.assert_allclose(data.poses, np.array([rec["pose"] for rec in records]), atol=1e-15)
    assert [m["source_index"] for m in data.meta] == list(range(5))
    scene = r.manifest["scene"]
    assert scene["kind"] == "simulated" and scene["dataset"] == "LCSPCData" and scene["name"] == "ball"
    assert scene["source"] == str(src.resolve())
    assert scene["source_sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()
    assert scene["ground_truth"] == str((tmp_path / "scenes" / "ball.obj").resolve())
    assert "table" not in scene
    assert r.planned_poses().shape == (5, 4, 4)


def test_real_file_keeps_reference_and_every_extra_field(tmp_path):
    records = real_records(4)
    src = write_json(tmp_path / "pyr" / "capture.json", records)
    trimesh.creation.box().export(tmp_path / "pyr" / "object2.stl")
    import_lcspc(src, tmp_path / "cap")
    r = CaptureReader(tmp_path / "cap")
    assert r.sensor == sensor_preset("tmf8820")
    data = r.load()
    assert data.hists.shape == (4, 9, 128) and data.reference.shape == (4, 128)
    np.testing.assert_array_equal(data.hists, np.array([rec["hists"] for rec in records]))
    np.testing.assert_array_equal(data.reference, np.array([rec["reference_hist"] for rec in records]))
    for k, (meta, rec) in enumerate(zip(data.meta, records)):
        for key in ("time_captured", "joint_angles", "distances", "custom_field"):
            assert meta[key] == rec[key]
        assert meta["temperature_c"] == 22 + k and meta["pose_index"] == k
    assert r.manifest["scene"]["kind"] == "real"
    assert r.manifest["scene"]["ground_truth"].endswith("object2.stl")
    assert "table" not in r.manifest["scene"]


def test_kind_comes_from_the_data_not_the_name(tmp_path):
    src = write_json(tmp_path / "simulated" / "sphere.json", real_records(2))
    assert read_lcspc(src).kind == "real"
    src = write_json(tmp_path / "real" / "pyramid.json", sim_records(2))
    assert read_lcspc(src).kind == "simulated"


def test_single_zone_histograms_may_carry_their_zone_axis(tmp_path):
    records = sim_records(2)
    records[1]["hists"] = [records[1]["hists"]]  # (1, 1024)
    assert read_lcspc(write_json(tmp_path / "a.json", records)).hists.shape == (2, 1, 1024)


def test_ground_truth_lookup(tmp_path):
    src = write_json(tmp_path / "a" / "scene.json", real_records(1))
    assert ground_truth_for(src, "real") is None
    (tmp_path / "a" / "one.stl").write_text("solid x\nendsolid x\n")
    assert ground_truth_for(src, "real") == tmp_path / "a" / "one.stl"
    assert ground_truth_for(src, "simulated") is None  # simulated scenes name their mesh after the scene
    (tmp_path / "a" / "two.stl").write_text("solid x\nendsolid x\n")
    assert ground_truth_for(src, "real") is None  # two candidates: do not guess
    (tmp_path / "a" / "scene.stl").write_text("solid x\nendsolid x\n")
    assert ground_truth_for(src, "real") == tmp_path / "a" / "scene.stl"


def test_progress_reports_bytes_read_and_measurements_written(tmp_path):
    src = write_json(tmp_path / "s.json", sim_records(3))
    calls = []
    import_lcspc(src, tmp_path / "cap", progress=lambda *a: calls.append(a))
    reads = [c for c in calls if c[0] == "read"]
    writes = [c for c in calls if c[0] == "write"]
    assert reads[-1] == ("read", src.stat().st_size, src.stat().st_size)
    assert writes == [("write", k, 3) for k in (1, 2, 3)]


# ---- malformed files -------------------------------------------------------------------------------------------------
def _sim(edit):
    def make():
        recs = sim_records(4)
        edit(recs)
        return recs
    return make


def _real(edit):
    def make():
        recs = real_records(3)
        edit(recs)
        return recs
    return make


def _set(i, key, value):
    def edit(recs):
        recs[i][key] = value
    return edit


def _set_count(i, value, key="hists"):
    def edit(recs):
        h = recs[i][key]
        (h[2] if isinstance(h[0], list) else h)[5] = value
    return edit


def _mix(recs):
    recs[2] = real_records(1)[0]


def _ragged(recs):
    recs[1]["hists"][4] = recs[1]["hists"][4][:-1]


def _nonfinite_rotation(value):
    """A pose (2) with last row [0, 0, 0, 0], as the real captures store them, and `value` in its rotation."""
    def edit(recs):
        recs[2]["pose"][3] = [0, 0, 0, 0]
        recs[2]["pose"][0][0] = value
    return edit


def _translations_times(factor, shift=0.0):
    def edit(recs):
        for rec in recs:
            for row in range(3):
                rec["pose"][row][3] = rec["pose"][row][3] * factor + shift
    return edit


def _pose_scale(recs):
    p = np.array(recs[1]["pose"])
    p[:3, :3] *= 1.05
    recs[1]["pose"] = p.tolist()


BAD = {
    "not json": ("{[oops", "not valid JSON"),
    "object": ({"hists": []}, "JSON list"),
    "empty list": ([], "no measurements"),
    "record not object": (_sim(lambda r: r.__setitem__(2, [1, 2])), "measurement 2 is a list"),
    "missing pose": (_sim(lambda r: r[1].pop("pose")), "measurement 1 lacks 'pose'"),
    "missing hists": (_sim(lambda r: r[3].pop("hists")), "measurement 3 lacks 'hists'"),
    "unknown shape": (_sim(lambda r: [x.__setitem__("hists", x["hists"][:1000]) for x in r]), "(1000,)"),
    "wrong length": (_sim(_set(2, "hists", list(range(1000)))), "measurement 2 has hists of shape (1000,)"),
    "mixed kinds": (_sim(_mix), "mixed kinds"),
    "ragged": (_real(_ragged), "measurement 1 has a ragged"),
    "nan count": (_sim(_set_count(1, float("nan"))), "measurement 1 has non-finite"),
    "inf count": (_sim(_set_count(1, float("inf"))), "measurement 1 has non-finite"),
    "negative": (_sim(_set_count(3, -2)), "measurement 3 has negative"),
    "fraction": (_sim(_set_count(0, 2.5)), "measurement 0 has fractional"),
    "string count": (_sim(_set_count(0, "7")), "non-numeric"),
    "bool counts": (_sim(_set(0, "hists", [True] * 1024)), "non-numeric"),
    "one bool count": (_sim(_set_count(1, True)), "measurement 1 has non-numeric hists (true or false"),
    "bool real count": (_real(_set_count(2, False)), "measurement 2 has non-numeric hists (true or false"),
    "bool reference": (_real(_set_count(1, True, "reference_hist")), "measurement 1 has non-numeric reference_hist"),
    "bool in pose": (_sim(lambda r: r[2]["pose"].__setitem__(3, [False, False, False, True])),
                     "measurement 2 has non-numeric pose (true or false"),
    "huge int": (_sim(_set_count(0, 10**30)),
                 "measurement 0 has a number too large in hists (1000000000000000000000000000000, beyond 64 bits)"),
    "huge negative int": (_real(_set_count(1, -2**63 - 1)), "measurement 1 has a number too large in hists"),
    "over 24 bits": (_real(_set_count(2, 2**24)), "measurement 2 has > 16777215"),
    "reference negative": (_real(_set_count(1, -1, "reference_hist")), "negative counts in reference_hist"),
    "pose 3x4": (_sim(_set(1, "pose", np.eye(4)[:3].tolist())), "measurement 1 has pose of shape (3, 4)"),
    "nan pose": (_sim(_set(2, "pose", [[float("nan")] * 4] * 4)), "pose 2 is not finite"),
    "scaled pose": (_sim(_pose_scale), "pose 1 is not rigid"),
    "nan rotation, zero last row": (_sim(_nonfinite_rotation(float("nan"))), "pose 2 is not finite"),
    "inf rotation, zero last row": (_real(_nonfinite_rotation(float("inf"))), "pose 2 is not finite"),
    "poses in mm": (_sim(_translations_times(1000)), "are the poses in millimetres? give them in metres"),
    "real poses in mm": (_real(_translations_times(1000)), "4 x the tmf8820 sensor's range of 1.57 m"),
    "string pose": (_sim(_set(0, "pose", "identity")), "pose"),
    "reference length": (_real(_set(1, "reference_hist", [1] * 127)), "reference_hist of shape (127,)"),
    "reference missing": (_real(lambda r: r[2].pop("reference_hist")), "measurement 2 lacks the reference_hist"),
    "reference on sim": (_sim(_set(0, "reference_hist", [0] * 1024)), "does not produce"),
    "joint angles short": (_real(_set(1, "joint_angles", [0.0] * 5)), "measurement 1 has joint_angles"),
    "joint angles nan": (_real(_set(0, "joint_angles", [float("nan")] * 6)), "joint_angles"),
}


@pytest.mark.filterwarnings("error")  # one line means no numpy warning printed before it either
@pytest.mark.parametrize("name", list(BAD))
def test_malformed_files_are_one_line_errors_and_write_nothing(tmp_path, name):
    content, why = BAD[name]
    src = tmp_path / "bad.json"
    if isinstance(content, str):
        src.write_text(content)
    else:
        write_json(src, content() if callable(content) else content)
    with pytest.raises(DatasetError) as info:
        import_lcspc(src, tmp_path / "cap")
    msg = str(info.value)
    assert "\n" not in msg and "bad.json" in msg and why in msg, msg
    assert not (tmp_path / "cap").exists()


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(DatasetError, match="no such"):
        read_lcspc(tmp_path / "none.json")
    with pytest.raises(DatasetError, match="no such"):
        read_lcspc(write_json(tmp_path / "s.json", sim_records(1)) / "x.json")  # a file as a folder in the path
    with pytest.raises(DatasetError, match="folder"):
        read_lcspc(tmp_path)


def test_a_pipe_or_device_is_named_not_called_missing(tmp_path):
    fifo = tmp_path / "piped.json"
    os.mkfifo(fifo)  # what `<(zcat scene.json.gz)` hands over; it must not be opened (that would wait for a writer)
    for path, what in ((fifo, "a pipe"), (os.devnull, "a device")):
        with pytest.raises(DatasetError) as info:
            import_lcspc(path, tmp_path / "cap")
        assert str(info.value) == f"{path}: is {what}, not an LCSPCData JSON file; give the JSON file's own path"
        assert not (tmp_path / "cap").exists()


def test_poses_far_from_the_origin_are_fine_when_close_together(tmp_path):
    """The spread check measures from the sensors' mean position, so a world frame 100 m away is no error."""
    recs = sim_records(4)
    _translations_times(1, shift=100.0)(recs)
    np.testing.assert_allclose(read_lcspc(write_json(tmp_path / "far.json", recs)).poses[:, :3, 3],
                               np.array([r["pose"] for r in recs])[:, :3, 3])


# ---- the command -----------------------------------------------------------------------------------------------------
def test_cli_imports_and_reports(tmp_path, capsys):
    src = write_json(tmp_path / "r.json", real_records(3))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap"), "--chunk-size", "2", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "imported 3 measurements" in out and "real" in out and "tmf8820" in out and "9 x 128" in out
    assert "2 chunks" in out and "ground truth: none" in out
    assert len(CaptureReader(tmp_path / "cap").chunk_names()) == 2


def test_cli_errors_are_one_line(tmp_path, capsys):
    src = write_json(tmp_path / "s.json", sim_records(2))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap")]) == 0
    capsys.readouterr()
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap")]) == 1  # already a capture there
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error:") and "already holds a capture" in err and err.count("\n") == 1
    (tmp_path / "bad.json").write_text("[1, 2")
    assert main(["import-lcspc", str(tmp_path / "bad.json"), "--out", str(tmp_path / "c2")]) == 1
    err = capsys.readouterr().err
    assert "bad.json" in err and err.count("\n") == 1 and not (tmp_path / "c2").exists()


# ---- the public dataset ----------------------------------------------------------------------------------------------
@pytest.mark.dataset
@pytest.mark.parametrize("rel,kind,n,shape,gt", [
    ("simulated/bunny/bunny.json", "simulated", 256, (1, 1024), "bunny.obj"),
    ("real/pyramid/pyramid.json", "real", 128, (9, 128), "pyramid2.stl"),
])
def test_dataset_files_import(lcspc_dataset, tmp_path, rel, kind, n, shape, gt):
    src = lcspc_dataset / rel
    summary = import_lcspc(src, tmp_path / "cap")
    assert (summary.kind, summary.measurements, summary.hists_shape[1:]) == (kind, n, shape)
    assert summary.ground_truth.name == gt
    data = CaptureReader(tmp_path / "cap").load()
    records = json.loads(src.read_text())
    np.testing.assert_array_equal(data.hists.reshape(n, -1), np.array([r["hists"] for r in records]).reshape(n, -1))
    np.testing.assert_array_equal(data.poses, np.array([r["pose"] for r in records]))
    if kind == "real":
        assert data.reference.shape == (n, 128) and data.reference.argmax(axis=1).min() >= 10
        assert {"joint_angles", "distances", "time_captured", "temperature_c"} <= set(data.meta[0])


@pytest.mark.parametrize("scan_id", ["a/b", "..", ".hidden", "../up", "with space", "x" * 101, ""])
def test_a_scan_id_must_be_a_plain_name_as_the_daemon_requires(tmp_path, capsys, scan_id):
    src = write_json(tmp_path / "s.json", sim_records(2))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap"), "--scan-id", scan_id]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error: --scan-id: scan name ") and err.count("\n") == 1
    assert "must be" in err
    assert not (tmp_path / "cap").exists()


def test_a_plain_scan_id_is_recorded(tmp_path):
    src = write_json(tmp_path / "s.json", sim_records(2))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap"), "--scan-id", "bunny_2.run-1",
                 "--no-progress"]) == 0
    assert CaptureReader(tmp_path / "cap").scan_id == "bunny_2.run-1"


def test_a_temperature_that_is_not_a_number_is_left_out_with_a_note(tmp_path, capsys):
    records = real_records(3)
    records[0]["distances"][0]["temperature"] = "hot"
    records[2]["distances"][0]["temperature"] = True
    src = write_json(tmp_path / "r.json", records)
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap"), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert err == ("spadscan: note: 2 measurements give a distances[0].temperature that is not a number (first: "
                   "measurement 0, 'hot'); stored without temperature_c (the original stays in its 'distances')\n")
    meta = CaptureReader(tmp_path / "cap").load().meta
    assert [m.get("temperature_c") for m in meta] == [None, 23, None]
    assert meta[0]["distances"][0]["temperature"] == "hot", "the record itself is kept verbatim"


def test_numeric_temperatures_give_no_note(tmp_path):
    data = read_lcspc(write_json(tmp_path / "r.json", real_records(2)))
    assert data.notes == () and [m["temperature_c"] for m in data.meta] == [22, 23]


# ---- poses stored without their last row -----------------------------------------------------------------------------
def _zero_last_rows(records, which):
    for i in which:
        records[i]["pose"][3] = [0, 0, 0, 0]
    return records


def test_poses_with_a_zero_last_row_are_completed_with_one_warning_line(tmp_path, capsys):
    records = real_records(4)
    src = write_json(tmp_path / "r.json", _zero_last_rows(records, range(4)))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "cap"), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert err == ("spadscan: warning: all 4 poses have last row [0, 0, 0, 0]; read as [0, 0, 0, 1], the last row of "
                   "every rigid transform (their rotations and translations are valid)\n")
    data = CaptureReader(tmp_path / "cap").load()
    expect = np.array([look_at_pose(k, 4) for k in range(4)])
    np.testing.assert_array_equal(data.poses, expect)  # rotation and translation kept exactly, last row completed
    assert data.manifest["scene"]["import_warnings"] == [err.split("warning: ", 1)[1].strip()]


def test_some_poses_with_a_zero_last_row_are_counted_and_the_first_named(tmp_path):
    data = read_lcspc(write_json(tmp_path / "r.json", _zero_last_rows(sim_records(5), [2, 4])))
    assert data.warnings == ("2 of 5 poses (first: pose 2) have last row [0, 0, 0, 0]; read as [0, 0, 0, 1], the "
                             "last row of every rigid transform (their rotations and translations are valid)",)
    np.testing.assert_array_equal(data.poses[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)))
    assert read_lcspc(write_json(tmp_path / "ok.json", sim_records(2))).warnings == ()


def _scaled_rotation(recs):
    _pose_scale(recs)
    recs[1]["pose"][3] = [0, 0, 0, 0]


def _reflection(recs):
    p = np.array(recs[2]["pose"])
    p[:3, 0] *= -1
    p[3] = 0
    recs[2]["pose"] = p.tolist()


@pytest.mark.parametrize("edit, why", [
    (_scaled_rotation, "pose 1 has last row [0, 0, 0, 0] and a 3x3 block that is not a rotation"),
    (_reflection, "pose 2 has last row [0, 0, 0, 0] and a 3x3 block that is not a rotation"),
    (_set(0, "pose", (np.eye(4) * [1, 1, 1, 2]).tolist()), "pose 0 has last row [0.0, 0.0, 0.0, 2.0]"),
    (_set(3, "pose", np.vstack([np.eye(4)[:3], [0.5, 0, 0, 1]]).tolist()), "pose 3 has last row [0.5, 0.0, 0.0, 1.0]"),
    (_set(1, "pose", np.vstack([np.eye(4)[:3], [0, 0, 0, 1e-3]]).tolist()), "pose 1 has last row"),
])
def test_poses_that_are_really_broken_are_still_refused(tmp_path, edit, why):
    recs = sim_records(4)
    edit(recs)
    with pytest.raises(DatasetError) as info:
        import_lcspc(write_json(tmp_path / "bad.json", recs), tmp_path / "cap")
    msg = str(info.value)
    assert "\n" not in msg and "bad.json" in msg and why in msg, msg
    assert not (tmp_path / "cap").exists()
