"""Capture folders: round trip, chunk boundaries, a writer killed mid-chunk, resume, corrupt files, live reading."""

from __future__ import annotations

import inspect
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format
import pytest

from spadscan.protocol.capture_format import MANIFEST, Measurement, chunk_name
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter, mark_paused
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset

from disk_faults import fail_lookup


def make_measurement(i, zones, bins, with_reference):
    """Deterministic measurement number i (also used by the child writer processes, whose source embeds it)."""
    import numpy as np

    from spadscan.protocol.capture_format import Measurement

    rng = np.random.default_rng(i)
    hist = rng.integers(0, 2**24, size=(zones, bins)).astype(np.uint32)
    a, b = 0.1 * i, 0.05 * i
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    pose = np.eye(4)
    pose[:3, :3] = rz @ rx
    pose[:3, 3] = [0.5 * np.cos(a), 0.5 * np.sin(a), 0.01 * i]
    ref = rng.integers(0, 1000, size=bins).astype(np.uint32) if with_reference else None
    meta = {"timestamp_s": 1000.0 + i, "temperature_c": 20 + i % 7, "depths_mm": [i, i + 1]}
    return Measurement(hist=hist, pose=pose, pose_index=i, frame=0, reference=ref, meta=meta)


TMF = sensor_preset("tmf8820")
SIM = sensor_preset("lcspc-sim")


def tmf(i):
    return make_measurement(i, TMF.n_zones, TMF.n_bins, True)


def write(path, n, chunk_size, sensor=TMF, finish=True, **kwargs):
    ref = sensor.has_reference
    with CaptureWriter.create(path, sensor, chunk_size=chunk_size, **kwargs) as w:
        for i in range(n):
            w.append(make_measurement(i, sensor.n_zones, sensor.n_bins, ref))
        if finish:
            w.finish()
    return w


def published_chunks(reader):
    """Every published chunk, read, in the listing's order."""
    return [reader.read_chunk(name) for name in reader.chunk_names()]


# ---- round trip --------------------------------------------------------------------------------------------------
def test_round_trip_keeps_arrays_meta_reference_and_manifest(tmp_path):
    path = tmp_path / "scan"
    he = make_measurement(3, 1, 4, False).pose
    planned = np.stack([tmf(i).pose for i in range(10)])
    write(path, 10, 4, scene={"name": "unit"}, rig={"arm": "sim"}, hand_eye=he, schedule={"kind": "fib"},
          planned_poses=planned, scan_id="abc")
    r = CaptureReader(path)
    assert r.state == "complete" and r.scan_id == "abc"
    assert r.chunk_names() == [chunk_name(0), chunk_name(1), chunk_name(2)]
    assert r.sensor == TMF
    np.testing.assert_allclose(r.hand_eye, he)
    np.testing.assert_array_equal(r.planned_poses(), planned)
    assert r.manifest["scene"] == {"name": "unit"} and r.manifest["rig"] == {"arm": "sim"}
    assert r.manifest["schedule"] == {"kind": "fib"} and r.manifest["planned_poses"] == 10
    data = r.load()
    assert data.hists.shape == (10, 9, 128) and data.hists.dtype == np.uint32
    assert data.poses.shape == (10, 4, 4) and data.poses.dtype == np.float64
    assert data.reference.shape == (10, 128) and data.reference.dtype == np.uint32
    for i in range(10):
        m = tmf(i)
        np.testing.assert_array_equal(data.hists[i], m.hist)
        np.testing.assert_array_equal(data.poses[i], m.pose)
        np.testing.assert_array_equal(data.reference[i], m.reference)
        assert data.meta[i] == {"pose_index": i, "frame": 0, **m.meta}
    np.testing.assert_array_equal(data.pose_indices, np.arange(10))


def test_counts_given_as_other_numeric_types_are_converted(tmp_path):
    m = tmf(0)
    with CaptureWriter.create(tmp_path / "s", TMF) as w:
        w.append(Measurement(m.hist.astype(np.float64), m.pose, 0, reference=m.reference.astype(np.int64)))
        w.finish()
    data = CaptureReader(tmp_path / "s").load()
    np.testing.assert_array_equal(data.hists[0], m.hist)
    assert data.hists.dtype == np.uint32


def test_meta_cannot_overwrite_pose_index_or_frame(tmp_path):
    m = tmf(5)
    m.meta = {"pose_index": 99, "frame": 7, "x": 1}
    with CaptureWriter.create(tmp_path / "s", TMF) as w:
        w.append(m)
    meta = CaptureReader(tmp_path / "s").load().meta[0]
    assert meta["pose_index"] == 5 and meta["frame"] == 0 and meta["x"] == 1


def test_meta_json_is_strict_json_a_number_not_finite_written_as_null(tmp_path):
    """JSON has no NaN or Infinity (Python writes bare tokens that other readers refuse): a meta value that is not
    finite (a sensor's temperature it could not read, a dataset's record) is written as null."""
    m = tmf(5)
    m.meta = {"temperature_c": float("nan"), "extra": {"gain": [1.0, float("inf")]}}
    with CaptureWriter.create(tmp_path / "s", TMF) as w:
        w.append(m)
    text = (tmp_path / "s" / chunk_name(0) / "meta.json").read_text()
    json.loads(text, parse_constant=lambda token: pytest.fail(f"bare {token} in meta.json"))
    meta = CaptureReader(tmp_path / "s").load().meta[0]
    assert meta["temperature_c"] is None and meta["extra"] == {"gain": [1.0, None]}


# ---- chunk boundaries ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n,size", [(1, 3), (2, 3), (3, 3), (4, 3), (6, 3), (7, 3), (5, 1), (3, 64)])
def test_chunks_hold_at_most_chunk_size(tmp_path, n, size):
    write(tmp_path / "s", n, size, sensor=SIM)
    r = CaptureReader(tmp_path / "s")
    chunks = published_chunks(r)
    assert [len(c.meta) for c in chunks] == [size] * (n // size) + ([n % size] if n % size else [])
    assert [c.name for c in chunks] == [chunk_name(k) for k in range(len(chunks))]
    np.testing.assert_array_equal(r.load().pose_indices, np.arange(n))
    assert r.load().reference is None


def test_empty_capture_is_an_error_when_loaded(tmp_path):
    write(tmp_path / "s", 0, 4)
    r = CaptureReader(tmp_path / "s")
    assert r.chunk_names() == [] and r.state == "complete"
    with pytest.raises(CaptureError, match="no published measurements"):
        r.load()


def test_explicit_flush_publishes_partial_chunk_and_numbering_continues(tmp_path):
    w = CaptureWriter.create(tmp_path / "s", TMF, chunk_size=4)
    w.append(tmf(0))
    assert w.flush() == chunk_name(0)
    assert w.flush() is None
    for i in range(1, 6):
        w.append(tmf(i))
    w.finish()
    r = CaptureReader(tmp_path / "s")
    assert [len(c.meta) for c in published_chunks(r)] == [1, 4, 1]
    assert w.n_published == 6 and w.next_pose_index == 6


def test_measurements_with_and_without_reference_never_share_a_chunk(tmp_path):
    w = CaptureWriter.create(tmp_path / "s", TMF, chunk_size=8)
    w.append(tmf(0))
    m = tmf(1)
    m.reference = None
    w.append(m)
    w.finish()
    chunks = published_chunks(CaptureReader(tmp_path / "s"))
    assert [c.reference is None for c in chunks] == [False, True]
    assert CaptureReader(tmp_path / "s").load().reference is None


# ---- writer input checks ---------------------------------------------------------------------------------------------
def _bad_hist_shape(m):
    m.hist = m.hist[:, :-1]


def _negative(m):
    m.hist = m.hist.astype(np.int64) - 2**25


def _nan_count(m):
    m.hist = m.hist.astype(float)
    m.hist[0, 0] = np.nan


def _fraction(m):
    m.hist = m.hist + 0.5


def _overflow(m):
    m.hist = m.hist.astype(np.int64) + 2**32


def _nan_pose(m):
    m.pose[0, 3] = np.nan


def _scaled_pose(m):
    m.pose[:3, :3] *= 1.01


def _mirror_pose(m):
    m.pose[:3, 0] *= -1


def _bad_reference(m):
    m.reference = m.reference[:10]


def _unserialisable_meta(m):
    m.meta["obj"] = object()


def _negative_pose_index(m):
    m.pose_index = -1


@pytest.mark.parametrize("spoil", [_bad_hist_shape, _negative, _nan_count, _fraction, _overflow, _nan_pose,
                                   _scaled_pose, _mirror_pose, _bad_reference, _unserialisable_meta,
                                   _negative_pose_index])
def test_writer_refuses_bad_measurements_in_one_line(tmp_path, spoil):
    w = CaptureWriter.create(tmp_path / "s", TMF, chunk_size=1)
    m = tmf(0)
    spoil(m)
    with pytest.raises(CaptureError) as info:
        w.append(m)
    assert "\n" not in str(info.value)
    assert CaptureReader(tmp_path / "s").chunk_names() == []


def test_create_refuses_an_existing_capture_and_bad_chunk_size(tmp_path):
    write(tmp_path / "s", 1, 4)
    with pytest.raises(CaptureError, match="already holds a capture"):
        CaptureWriter.create(tmp_path / "s", TMF)
    (tmp_path / "file").write_text("x")
    with pytest.raises(CaptureError, match="not a folder"):
        CaptureWriter.create(tmp_path / "file", TMF)
    with pytest.raises(CaptureError, match="chunk size"):
        CaptureWriter.create(tmp_path / "t", TMF, chunk_size=0)
    with pytest.raises(CaptureError):
        CaptureWriter.create(tmp_path / "u", TMF, scene={"x": object()})
    assert not (tmp_path / "u" / MANIFEST).exists()


def test_set_state_refuses_unknown_state_and_records_reason(tmp_path):
    w = write(tmp_path / "s", 2, 4, finish=False)
    with pytest.raises(CaptureError, match="state"):
        w.set_state("paused")
    w.finish("aborted", "arm fault")
    r = CaptureReader(tmp_path / "s")
    assert r.state == "aborted" and r.manifest["reason"] == "arm fault"


def test_mark_paused_records_the_kind_of_pause_and_refuses_an_unknown_one(tmp_path):
    """A pause records its kind ('pause' unless named), kept with the time it began when recorded again; a kind the
    format does not define is refused, the record left as it was."""
    write(tmp_path / "s", 2, 4, finish=False)
    mark_paused(tmp_path / "s", "paused by user")
    first = CaptureReader(tmp_path / "s").manifest["paused"]
    assert first["kind"] == "pause" and first["reason"] == "paused by user", first
    mark_paused(tmp_path / "s", "interrupted at pose 2/9 (daemon restarted)", "interrupted")
    again = CaptureReader(tmp_path / "s").manifest["paused"]
    assert again == {**first, "reason": "interrupted at pose 2/9 (daemon restarted)", "kind": "interrupted"}, again
    with pytest.raises(CaptureError, match="pause kind 'operator' is not one of"):
        mark_paused(tmp_path / "s", "paused by user", "operator")
    assert CaptureReader(tmp_path / "s").manifest["paused"] == again


# ---- a writer killed in the middle of a chunk --------------------------------------------------------------------------
CHILD = """
import sys, time
from pathlib import Path
import numpy as np
import spadscan.protocol.capture_writer as cw
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset

{source}

path, mode, block_chunk = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
sensor = sensor_preset("tmf8820")
real_save = cw.save_npy_durable

def blocking_save(p, array):
    # Write this file, then hang inside the chunk (the parent kills us here).
    real_save(p, array)
    if p.parent.name.endswith(cw.chunk_name(block_chunk)) and p.name == "hists.npy":
        (path.parent / "blocked").write_text("x")
        time.sleep(3600)

if mode == "block":
    cw.save_npy_durable = blocking_save
w = CaptureWriter.create(path, sensor, chunk_size=3)
i = 0
while True:  # writes until killed
    w.append(make_measurement(i, sensor.n_zones, sensor.n_bins, True))
    i += 1
"""


def _start_child(tmp_path, mode, block_chunk=-1):
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(source=textwrap.dedent(inspect.getsource(make_measurement))))
    return subprocess.Popen([sys.executable, str(script), str(tmp_path / "scan"), mode, str(block_chunk)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _wait_for(cond, proc, what, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"child writer exited early: {proc.stderr.read().decode()[-2000:]}")
        if time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def _kill(proc):
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stderr.close()


def _finish_after_resume(path, total):
    w = CaptureWriter.resume(path)
    for i in range(w.next_pose_index, total):
        w.append(tmf(i))
    w.finish()
    data = CaptureReader(path).load()
    np.testing.assert_array_equal(data.pose_indices, np.arange(total))
    for i in (0, total // 2, total - 1):
        np.testing.assert_array_equal(data.hists[i], tmf(i).hist)
        np.testing.assert_array_equal(data.poses[i], tmf(i).pose)


def test_kill_in_the_middle_of_a_chunk_then_resume(tmp_path):
    path = tmp_path / "scan"
    proc = _start_child(tmp_path, "block", block_chunk=2)
    try:
        _wait_for(lambda: (tmp_path / "blocked").exists(), proc, "the writer to block inside chunk 2")
    finally:
        _kill(proc)
    tmp = [p for p in path.iterdir() if p.name.startswith(".tmp-")]
    assert [p.name for p in tmp] == [".tmp-" + chunk_name(2)]
    assert (tmp[0] / "hists.npy").exists()  # half a chunk lies on disk ...
    r = CaptureReader(path)
    assert r.state == "running"
    assert r.chunk_names() == [chunk_name(0), chunk_name(1)]  # ... but readers never see it
    np.testing.assert_array_equal(r.load().pose_indices, np.arange(6))

    w = CaptureWriter.resume(path)
    assert not any(p.name.startswith(".tmp-") for p in path.iterdir())
    assert w.next_pose_index == 6 and w.n_published == 6
    w.append(tmf(6))
    assert w.flush() == chunk_name(2)
    w.finish()
    _finish_after_resume(path, 11)


def test_kill_at_an_arbitrary_moment_leaves_only_whole_chunks(tmp_path):
    path = tmp_path / "scan"
    proc = _start_child(tmp_path, "forever")
    try:
        _wait_for(lambda: path.is_dir() and (path / chunk_name(4)).exists(), proc, "five published chunks")
    finally:
        _kill(proc)
    r = CaptureReader(path)
    names = r.chunk_names()
    assert names == [chunk_name(k) for k in range(len(names))] and len(names) >= 5
    chunks = published_chunks(r)
    assert all(len(c.meta) == 3 for c in chunks)
    n = 3 * len(chunks)
    np.testing.assert_array_equal(r.load().pose_indices, np.arange(n))
    w = CaptureWriter.resume(path)
    assert w.next_pose_index == n
    _finish_after_resume(path, n + 4)
    assert CaptureReader(path).chunk_names()[len(names)] == chunk_name(len(names))


def test_resume_removes_stray_temporary_files_and_reopens_a_finished_scan(tmp_path):
    path = tmp_path / "s"
    write(path, 4, 4)
    (path / ".tmp-scan.json").write_text("{half")
    (path / ".tmp-chunk-000001").mkdir()
    w = CaptureWriter.resume(path)
    assert sorted(p.name for p in path.iterdir()) == [chunk_name(0), MANIFEST]
    assert CaptureReader(path).state == "running" and w.next_pose_index == 4


def test_resume_of_a_folder_without_capture_is_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    for p in (tmp_path / "empty", tmp_path / "missing"):
        with pytest.raises(CaptureError) as info:
            CaptureWriter.resume(p)
        assert "\n" not in str(info.value) and str(p) in str(info.value)


# ---- corrupt files ------------------------------------------------------------------------------------------------------
def _truncate(p, keep):
    data = p.read_bytes()
    p.write_bytes(data[:keep(len(data))])


def _rewrite_npy(name, fn):
    def spoil(path):
        f = path / chunk_name(0) / name
        np.save(f, fn(np.load(f)))
    return spoil


def _patch_manifest(fn):
    def spoil(path):
        m = json.loads((path / MANIFEST).read_text())
        fn(m)
        (path / MANIFEST).write_text(json.dumps(m))
    return spoil


def _set(key, value):
    def fn(m):
        m[key] = value
    return fn


def _nan_pose_file(p):
    p[1, 2, 3] = np.nan
    return p


def _stretch_pose_file(p):
    p[0, :3, :3] *= 1.2
    return p


def _bad_last_row(p):
    p[0, 3, 0] = 0.5
    return p


def _set_sensor_bins(m):
    m["sensor"]["bin_width_m"] = "wide"


def _drop_pose_index(path):
    f = path / chunk_name(0) / "meta.json"
    meta = json.loads(f.read_text())
    del meta["measurements"][1]["pose_index"]
    f.write_text(json.dumps(meta))


def _short_meta(path):
    f = path / chunk_name(0) / "meta.json"
    meta = json.loads(f.read_text())
    meta["measurements"].pop()
    f.write_text(json.dumps(meta))


def _npz_instead(path):
    f = path / chunk_name(0) / "hists.npy"
    arr = np.load(f)
    with open(f, "wb") as fh:
        np.savez(fh, hists=arr)


CORRUPTIONS = {
    "truncated hists": (lambda p: _truncate(p / chunk_name(0) / "hists.npy", lambda n: n - 100), "hists.npy"),
    "truncated header": (lambda p: _truncate(p / chunk_name(0) / "hists.npy", lambda n: 40), "hists.npy"),
    "empty poses": (lambda p: _truncate(p / chunk_name(0) / "poses.npy", lambda n: 0), "poses.npy"),
    "npz hists": (_npz_instead, "hists.npy"),
    "pickled hists": (lambda p: np.save(p / chunk_name(0) / "hists.npy", np.array([{"a": 1}], dtype=object),
                                        allow_pickle=True), "hists.npy"),
    "missing hists": (lambda p: (p / chunk_name(0) / "hists.npy").unlink(), "hists.npy"),
    "garbage meta": (lambda p: (p / chunk_name(0) / "meta.json").write_text("{not json"), "meta.json"),
    "meta not object": (lambda p: (p / chunk_name(0) / "meta.json").write_text("[1, 2]"), "meta.json"),
    "meta without pose index": (_drop_pose_index, "meta.json"),
    "meta too short": (_short_meta, "meta.json"),
    "nan pose": (_rewrite_npy("poses.npy", _nan_pose_file), "poses.npy"),
    "non-rigid pose": (_rewrite_npy("poses.npy", _stretch_pose_file), "poses.npy"),
    "bad last row": (_rewrite_npy("poses.npy", _bad_last_row), "poses.npy"),
    "float32 poses": (_rewrite_npy("poses.npy", lambda p: p.astype(np.float32)), "poses.npy"),
    "too few poses": (_rewrite_npy("poses.npy", lambda p: p[:-1]), "poses.npy"),
    "int64 hists": (_rewrite_npy("hists.npy", lambda h: h.astype(np.int64)), "hists.npy"),
    "float hists": (_rewrite_npy("hists.npy", lambda h: h.astype(np.float64)), "hists.npy"),
    "wrong bins": (_rewrite_npy("hists.npy", lambda h: h[:, :, :-1]), "hists.npy"),
    "flat hists": (_rewrite_npy("hists.npy", lambda h: h.reshape(len(h), -1)), "hists.npy"),
    "reference dtype": (_rewrite_npy("reference.npy", lambda r: r.astype(np.float32)), "reference.npy"),
    "missing manifest": (lambda p: (p / MANIFEST).unlink(), MANIFEST),
    "garbage manifest": (lambda p: (p / MANIFEST).write_text("\x00\x01garbage"), MANIFEST),
    "wrong format": (_patch_manifest(_set("format", "something-else")), MANIFEST),
    "unknown state": (_patch_manifest(_set("state", "paused")), MANIFEST),
    "bad chunk size": (_patch_manifest(_set("chunk_size", "many")), MANIFEST),
    "bad sensor": (_patch_manifest(_set_sensor_bins), MANIFEST),
    "sensor not object": (_patch_manifest(_set("sensor", [1, 2])), MANIFEST),
    "bad hand-eye": (_patch_manifest(_set("hand_eye", "identity")), MANIFEST),
    "ragged hand-eye": (_patch_manifest(_set("hand_eye", [[1, 0], [0, 1, 0]])), MANIFEST),
    "bad schedule file": (lambda p: (p / "schedule.npy").write_bytes(b"\x93NUMPY junk"), "schedule.npy"),
    "newer version": (_patch_manifest(_set("version", 99)), MANIFEST),
    "version not a number": (_patch_manifest(_set("version", "1")), MANIFEST),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_corrupt_files_give_one_line_errors_naming_the_file(tmp_path, name):
    path = tmp_path / "scan"
    write(path, 5, 3, planned_poses=np.stack([tmf(i).pose for i in range(5)]))
    spoil, filename = CORRUPTIONS[name]
    spoil(path)
    with pytest.raises(CaptureError) as info:
        r = CaptureReader(path)
        r.load()
        r.planned_poses()
    msg = str(info.value)
    assert "\n" not in msg and filename in msg, msg
    assert "allow_pickle" not in msg, "numpy's advice to load the file unsafely is not passed on"


def test_a_newer_format_version_is_refused_naming_the_one_this_reads(tmp_path):
    from spadscan.protocol.capture_format import VERSION

    path = tmp_path / "scan"
    write(path, 2, 2)
    _patch_manifest(_set("version", VERSION + 98))(path)
    with pytest.raises(CaptureError) as info:
        CaptureReader(path)
    assert str(info.value) == (f"{path / MANIFEST}: capture format version {VERSION + 98} is newer than this "
                               f"spadscan reads (version {VERSION}); upgrade spadscan to read it")
    with pytest.raises(CaptureError, match="is newer"):
        CaptureWriter.resume(path)  # nor is it rewritten as the version this writer knows


def test_a_manifest_without_a_version_is_version_1(tmp_path):
    path = tmp_path / "scan"
    write(path, 2, 2)
    _patch_manifest(lambda m: m.pop("version"))(path)
    assert len(CaptureReader(path).load().hists) == 2


def test_a_scan_folder_that_is_not_a_directory(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(CaptureError, match="file: a file, not a capture folder"):
        CaptureReader(tmp_path / "file")
    with pytest.raises(CaptureError, match="nope: no such capture folder"):
        CaptureReader(tmp_path / "nope")


# ---- reading while the scan runs -------------------------------------------------------------------------------------
def test_follow_yields_each_chunk_as_it_is_published_and_stops_when_complete(tmp_path):
    path = tmp_path / "scan"
    w = CaptureWriter.create(path, TMF, chunk_size=2)
    got: list[str] = []
    ack = threading.Event()
    failure: list[BaseException] = []

    def produce():
        try:
            for k in range(4):
                w.append(tmf(2 * k))
                w.append(tmf(2 * k + 1))
                # Lock step: the next chunk appears only once the reader has yielded this one, so a reader that
                # waited for the end of the scan would time out here.
                if not ack.wait(20):
                    raise TimeoutError(f"reader did not yield chunk {k} while the scan ran")
                ack.clear()
            w.finish()
        except BaseException as exc:  # reported by the test thread
            failure.append(exc)
            w.finish("aborted", str(exc))

    t = threading.Thread(target=produce)
    t.start()
    try:
        for chunk in CaptureReader(path).follow(poll_s=0.01, timeout_s=30):
            got.append(chunk.name)
            assert CaptureReader(path).state == "running"
            ack.set()
    finally:
        t.join(30)
    assert not failure, failure
    assert got == [chunk_name(k) for k in range(4)]


def test_follow_reads_a_finished_scan_and_times_out_on_a_stalled_one(tmp_path):
    write(tmp_path / "done", 5, 2)
    assert [len(c.meta) for c in CaptureReader(tmp_path / "done").follow(poll_s=0.01)] == [2, 2, 1]
    w = write(tmp_path / "stalled", 2, 2, finish=False)
    chunks = CaptureReader(tmp_path / "stalled").follow(poll_s=0.01, timeout_s=0.2)
    assert next(chunks).name == chunk_name(0)
    with pytest.raises(CaptureError, match="no new chunk"):
        next(chunks)
    w.finish()


@pytest.mark.parametrize("name, content, expect", [
    ("hists.npy", bytes(4096), "not a .npy file"),  # a zeroed block: lost data after a power cut
    ("poses.npy", b"this is text, not an array\n", "not a .npy file"),
    ("reference.npy", b"ab", "not a .npy file"),  # shorter than the magic, and not its beginning
    ("hists.npy", b"\x93NUM", "corrupt or truncated .npy (it ends inside its header)"),
    ("hists.npy", b"", "corrupt or truncated .npy (it ends inside its header)")])
def test_a_chunk_file_that_is_not_npy_is_reported_as_damaged(tmp_path, name, content, expect):
    """Without the .npy magic np.load would try to unpickle the file, and its allow_pickle error read as "holds
    Python objects": that message is for a real .npy of dtype object only (case 'pickled hists' above)."""
    path = tmp_path / "scan"
    write(path, 3, 3)
    (path / chunk_name(0) / name).write_bytes(content)
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    assert str(info.value).startswith(f"{path / chunk_name(0) / name}: {expect}"), str(info.value)
    assert "Python objects" not in str(info.value)


def test_a_damaged_chunk_names_the_way_out_and_the_way_out_works(tmp_path):
    """A torn chunk among whole ones: the error names every damaged chunk and how many are whole, and moving the
    damaged ones out (as it says) leaves a capture that loads with the other chunks' views."""
    path = tmp_path / "scan"
    write(path, 8, 2)  # four chunks of two measurements
    for k in (1, 3):
        (path / chunk_name(k) / "hists.npy").write_bytes(bytes(4096))  # zeroed blocks after a power cut
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    said = str(info.value)
    assert said.startswith(f"{path / chunk_name(1) / 'hists.npy'}: not a .npy file"), said
    assert said.endswith(f"; 2 of 4 chunks cannot be read ({chunk_name(1)}, {chunk_name(3)}): moving them out of "
                         f"{path} leaves the views of the other 2 to use"), said
    aside = tmp_path / "aside"
    aside.mkdir()
    for k in (1, 3):
        (path / chunk_name(k)).rename(aside / chunk_name(k))
    data = CaptureReader(path).load()
    assert [m["pose_index"] for m in data.meta] == [0, 1, 4, 5]


def test_a_chunk_file_that_cannot_be_looked_up_is_a_damaged_chunk_in_one_line(tmp_path, monkeypatch):
    """An I/O error looking reference.npy up (a failing disk) is the chunk's one-line error with the way out, as for
    any file of it that cannot be read, not a bare OSError."""
    path = tmp_path / "scan"
    write(path, 6, 2)
    failing = path / chunk_name(1) / "reference.npy"
    fail_lookup(monkeypatch, failing)
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    said = str(info.value)
    assert said.startswith(f"{failing}: cannot be read (") and "Input/output error" in said, said
    assert said.endswith(f"; 1 of 3 chunks cannot be read ({chunk_name(1)}): moving it out of {path} leaves the "
                         f"views of the other 2 to use"), said


def test_many_damaged_chunks_are_counted_past_the_first_few_named(tmp_path):
    path = tmp_path / "scan"
    write(path, 24, 2)  # twelve chunks
    for k in range(11):
        (path / chunk_name(k) / "hists.npy").write_bytes(b"")
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    named = ", ".join(chunk_name(k) for k in range(8))
    assert f"; 11 of 12 chunks cannot be read ({named} and 3 more): moving them out" in str(info.value)


def test_a_capture_with_no_readable_chunk_offers_no_move(tmp_path):
    path = tmp_path / "scan"
    write(path, 2, 1)
    for k in (0, 1):
        (path / chunk_name(k) / "hists.npy").write_bytes(b"")
    with pytest.raises(CaptureError, match=r"; none of its 2 chunks can be read$"):
        CaptureReader(path).load()


@pytest.mark.parametrize("shape, data_bytes", [((99_999_999_999, 9, 128), 100), ((3, 9, 128), 3 * 9 * 128 * 4 - 10)])
def test_an_npy_whose_header_and_data_disagree_is_reported_as_damaged(tmp_path, shape, data_bytes):
    """A damaged header that claims a huge shape made numpy allocate it (a MemoryError traceback); a short file is
    named as such before numpy reads it."""
    path = tmp_path / "scan"
    write(path, 3, 3)
    hists = path / chunk_name(0) / "hists.npy"
    with hists.open("wb") as f:
        npy_format.write_array_header_1_0(f, {"descr": "<u4", "fortran_order": False, "shape": shape})
        f.write(bytes(data_bytes))
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    assert str(info.value).startswith(f"{hists}: corrupt or truncated .npy (its header describes {shape}"), \
        str(info.value)


def test_big_endian_npy_files_are_read_in_the_machine_order(tmp_path):
    """A `>u4` or `>f8` file holds uint32 counts or float64 poses as well (another writer, another machine)."""
    path = tmp_path / "scan"
    planned = np.stack([tmf(i).pose for i in range(3)])
    write(path, 3, 3, planned_poses=planned)
    before = CaptureReader(path).load()
    chunk = path / chunk_name(0)
    for name in ("hists.npy", "poses.npy", "reference.npy"):
        a = np.load(chunk / name)
        np.save(chunk / name, a.astype(a.dtype.newbyteorder(">")))
    np.save(path / "schedule.npy", planned.astype(">f8"))
    assert np.load(chunk / "hists.npy").dtype.str == ">u4"
    reader = CaptureReader(path)
    after = reader.load()
    assert after.hists.dtype == np.uint32 and after.poses.dtype == np.float64 and after.reference.dtype == np.uint32
    np.testing.assert_array_equal(after.hists, before.hists)
    np.testing.assert_array_equal(after.poses, before.poses)
    np.testing.assert_array_equal(after.reference, before.reference)
    np.testing.assert_array_equal(reader.planned_poses(), planned)


@pytest.mark.parametrize("digit", ["\u0661", "\u00b2"])  # ARABIC-INDIC DIGIT ONE, SUPERSCRIPT TWO
def test_only_six_ascii_digits_name_a_chunk(tmp_path, digit):
    """A copy named with another Unicode digit is not a chunk: ignored by the reader and by resume (a superscript
    made int() raise a bare ValueError in every command)."""
    from spadscan.protocol.capture_format import chunk_index

    path = tmp_path / "scan"
    write(path, 2, 1, finish=False)
    (path / chunk_name(1)).rename(path / f"chunk-00000{digit}")
    assert chunk_index(f"chunk-00000{digit}") is None and chunk_index("chunk-000042") == 42
    assert chunk_index("chunk-42") is None and chunk_index("chunk-0000001") is None
    assert CaptureReader(path).chunk_names() == [chunk_name(0)]
    assert len(CaptureReader(path).load().meta) == 1
    w = CaptureWriter.resume(path)
    assert w.next_pose_index == 1
    w.append(tmf(1))  # chunk size 1: published at once
    assert CaptureReader(path).chunk_names() == [chunk_name(0), chunk_name(1)]
