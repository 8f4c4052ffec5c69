"""CaptureWriter.flush: a chunk's files are fsynced side by side, yet every one of them (and its folder) is durable
before the chunk is published by its rename, the captures folder is fsynced after it, and a failed write publishes
nothing and leaves no write running."""

from __future__ import annotations

import errno
import json
import os
import threading

import numpy as np
import pytest

import spadscan.protocol.capture_writer as cw
from spadscan.protocol.atomic_files import write_atomic
from spadscan.protocol.capture_format import Measurement, write_json_atomic
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset


def measurement(i: int, sensor, reference: bool = True) -> Measurement:
    rng = np.random.default_rng(i)
    hist = rng.integers(0, 1000, (sensor.n_zones, sensor.n_bins))
    ref = rng.integers(0, 1000, sensor.n_bins) if reference else None
    return Measurement(hist, np.eye(4), i, 0, ref, {"i": i})


@pytest.fixture
def events(monkeypatch):
    """A log of ('fsync', path) and ('rename', src, dst) (os.rename or os.replace), in the order they happened (any
    thread)."""
    log: list[tuple] = []
    lock = threading.Lock()
    real_fsync, real_rename, real_replace = os.fsync, os.rename, os.replace

    def fsync(fd):
        real_fsync(fd)
        with lock:
            log.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))

    def rename(src, dst):
        real_rename(src, dst)
        with lock:
            log.append(("rename", str(src), str(dst)))

    def replace(src, dst):
        real_replace(src, dst)
        with lock:
            log.append(("rename", str(src), str(dst)))

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "rename", rename)
    monkeypatch.setattr(os, "replace", replace)
    return log


@pytest.mark.parametrize("reference", [True, False])
def test_every_file_and_folder_is_fsynced_around_the_publishing_rename(tmp_path, events, reference):
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=2)
    del events[:]
    for i in range(2):
        w.append(measurement(i, sensor, reference))  # the second append publishes chunk 0
    (rename,) = [e for e in events if e[0] == "rename"]
    at = events.index(rename)
    tmp, published = rename[1], rename[2]
    before = {e[1] for e in events[:at] if e[0] == "fsync"}
    files = {"hists.npy", "poses.npy", "meta.json"} | ({"reference.npy"} if reference else set())
    assert before == {f"{tmp}/{f}" for f in files} | {tmp}, before
    assert ("fsync", str(tmp_path / "scan")) in events[at + 1:], "the captures folder is not fsynced after"
    assert sorted(os.listdir(published)) == sorted(files)
    np.testing.assert_array_equal(CaptureReader(tmp_path / "scan").load().pose_indices, [0, 1])


@pytest.mark.parametrize("replace", ["manifest", "file"])
def test_a_replaced_file_is_fsynced_before_its_rename_and_its_folder_after(tmp_path, events, replace):
    """The manifest (`write_json_atomic`) and the other files replaced whole (`write_atomic`: status files, job
    records): a crash after the rename keeps the new content, and the rename itself, only with both fsyncs."""
    path = tmp_path / ("scan.json" if replace == "manifest" else "status.json")
    if replace == "manifest":
        write_json_atomic(path, {"state": "running"})
    else:
        write_atomic(path, '{"state": "running"}')
    (rename,) = [e for e in events if e[0] == "rename"]
    at = events.index(rename)
    assert rename[2] == str(path)
    assert ("fsync", rename[1]) in events[:at], "the new content is not fsynced before the rename"
    assert ("fsync", str(tmp_path)) in events[at + 1:], "the folder is not fsynced after the rename"
    assert json.loads(path.read_text()) == {"state": "running"}


def test_a_failed_write_publishes_nothing_and_leaves_no_write_running(tmp_path, monkeypatch):
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=1)
    w.append(measurement(0, sensor))
    real = cw.save_npy_durable
    running = {"now": 0}
    lock = threading.Lock()

    def save(path, array):
        with lock:
            running["now"] += 1
        try:
            if path.name == "poses.npy":
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            if path.name == "reference.npy":  # a sibling that may still be writing when the error comes
                threading.Event().wait(0.2)
            real(path, array)
        finally:
            with lock:
                running["now"] -= 1

    monkeypatch.setattr(cw, "save_npy_durable", save)
    with pytest.raises(OSError, match="No space left"):
        w.append(measurement(1, sensor))
    assert running["now"] == 0, "flush raised while a write of the chunk was still running"
    assert [t for t in threading.enumerate() if t.name == "capture-fsync"] == []
    assert CaptureReader(tmp_path / "scan").chunk_names() == ["chunk-000000"]
    monkeypatch.setattr(cw, "save_npy_durable", real)
    w = CaptureWriter.resume(tmp_path / "scan")
    assert not [p for p in (tmp_path / "scan").iterdir() if p.name.startswith(".tmp-")]
    w.append(measurement(1, sensor))
    w.finish()
    np.testing.assert_array_equal(CaptureReader(tmp_path / "scan").load().pose_indices, [0, 1])


def short_write(path, array):
    """What numpy raises when the disk fills up under np.save: no errno, no filename."""
    raise OSError(f"{array.nbytes} requested and 3040 written")


def append_to_a_full_disk(tmp_path, monkeypatch) -> tuple[CaptureWriter, OSError]:
    """A writer whose first append meets a full disk (`short_write`), and the error that append raised."""
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=1)
    monkeypatch.setattr(cw, "save_npy_durable", short_write)
    with pytest.raises(OSError) as info:
        w.append(measurement(0, sensor))
    return w, info.value


def test_a_short_write_is_a_full_disk_that_names_the_file(tmp_path, monkeypatch):
    _, error = append_to_a_full_disk(tmp_path, monkeypatch)
    assert error.errno == errno.ENOSPC
    assert error.filename == str(tmp_path / "scan" / ".tmp-chunk-000000" / "hists.npy")
    assert "requested and" in str(error.__cause__), "the original error stays attached"


def test_an_error_with_an_errno_but_no_filename_gains_the_path(tmp_path, monkeypatch):
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=1)

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device")  # what f.write raises: no filename

    monkeypatch.setattr(cw, "write_json_atomic", full)
    with pytest.raises(OSError) as info:
        w.set_state("aborted", "test")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(tmp_path / "scan" / "scan.json")


def test_abandon_marks_the_capture_aborted_and_frees_the_half_written_chunk(tmp_path, monkeypatch):
    w, error = append_to_a_full_disk(tmp_path, monkeypatch)
    w.abandon("simulation", error)
    m = CaptureReader(tmp_path / "scan").manifest
    assert m["state"] == "aborted"
    assert m["reason"] == f"simulation failed: {error.filename}: No space left on device"
    assert not [p for p in (tmp_path / "scan").iterdir() if p.name.startswith(".tmp-")]


def test_abandon_never_hides_the_error_that_stopped_the_writer(tmp_path, monkeypatch):
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=1)

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cw, "write_json_atomic", full)
    w.abandon("import", KeyboardInterrupt())  # the manifest cannot be written either: no new error
    assert CaptureReader(tmp_path / "scan").manifest["state"] == "running"


@pytest.mark.parametrize("state, reason, expect", [
    ("complete", None, "already holds a capture (complete); choose another folder"),
    ("running", None, "already holds a capture that was not finished (state 'running'); delete the folder or "
                      "choose another"),
    ("aborted", "simulation failed: disk\nfull", "(state 'aborted': simulation failed: disk full); delete the folder"),
])
def test_create_on_an_existing_capture_says_what_to_do(tmp_path, state, reason, expect):
    sensor = sensor_preset("tmf8820")
    w = CaptureWriter.create(tmp_path / "scan", sensor)
    w.set_state(state, reason)
    with pytest.raises(CaptureError) as info:
        CaptureWriter.create(tmp_path / "scan", sensor)
    assert expect in str(info.value) and "resume" not in str(info.value)
    assert "\n" not in str(info.value)


def test_set_state_stores_the_reason_on_one_line(tmp_path):
    """The format defines `reason` as one line; `ctl abort --reason` (and any other writer) may pass line breaks."""
    w = CaptureWriter.create(tmp_path / "scan", sensor_preset("tmf8820"))
    w.set_state("aborted", "sensor cable\n  unplugged\r\nby Bob\t")
    assert CaptureReader(tmp_path / "scan").manifest["reason"] == "sensor cable unplugged by Bob"


def _full_while_saving(path, array):
    """A full disk while schedule.npy is written: a few bytes made it to disk."""
    with open(path, "wb") as f:
        f.write(b"\x93NUMPY")
    raise OSError(errno.ENOSPC, "No space left on device", str(path))


def _full_while_writing_the_manifest(path, data):
    with open(path.with_name(".tmp-" + path.name), "wb") as f:
        f.write(b'{"format"')
    raise OSError(errno.ENOSPC, "No space left on device", str(path))


def _interrupted_after_the_manifest(path):
    raise KeyboardInterrupt


@pytest.mark.parametrize("fails", [("save_npy_durable", _full_while_saving),
                                   ("write_json_atomic", _full_while_writing_the_manifest),
                                   ("fsync_dir", _interrupted_after_the_manifest)])
@pytest.mark.parametrize("existing", [False, True])
def test_a_failed_create_leaves_nothing_that_blocks_the_rerun(tmp_path, monkeypatch, fails, existing):
    """A full disk or Ctrl-C inside `create` (an import writes schedule.npy before scan.json) used to leave files
    that made the rerun refuse the folder ("holds other files"). A new folder goes again; an empty one the user made
    stays, empty."""
    sensor = sensor_preset("tmf8820")
    path = tmp_path / "scan"
    if existing:
        path.mkdir()
    name, failure = fails
    monkeypatch.setattr(cw, name, failure)
    with pytest.raises((OSError, KeyboardInterrupt)):
        CaptureWriter.create(path, sensor, planned_poses=np.stack([np.eye(4)] * 3))
    assert (sorted(path.iterdir()) == []) if existing else not path.exists()
    monkeypatch.undo()  # space freed
    CaptureWriter.create(path, sensor, planned_poses=np.stack([np.eye(4)] * 3)).close()
    assert CaptureReader(path).planned_poses().shape == (3, 4, 4)


def test_a_capture_that_lacks_planned_poses_is_not_marked_complete(tmp_path):
    """"complete" promises every planned pose (capture_format.md): a writer asked to mark a capture complete with
    poses still to publish, or with measurements still in its buffer, refuses, and the manifest still says
    running; once the last planned pose is published it is marked complete."""
    sensor = sensor_preset("tmf8820")
    path = tmp_path / "scan"
    w = CaptureWriter.create(path, sensor, planned_poses=np.stack([np.eye(4)] * 3), chunk_size=8)
    hist = np.ones((sensor.n_zones, sensor.n_bins), dtype=np.uint32)
    for i in range(2):
        w.append(Measurement(hist, np.eye(4), i, 0, np.ones(sensor.n_bins), {}))
    w.flush()
    with pytest.raises(CaptureError, match=r"not complete: 2 of 3 planned poses published"):
        w.set_state("complete")
    w.append(Measurement(hist, np.eye(4), 2, 0, np.ones(sensor.n_bins), {}))
    with pytest.raises(CaptureError, match=r"3 planned poses.*still buffered"):
        w.set_state("complete")
    assert CaptureReader(path).state == "running"
    w.set_state("aborted", "stopped early")  # any other state is recorded as it is
    w.finish("complete")
    assert CaptureReader(path).state == "complete"
    w.close()


def test_a_scan_shortened_by_a_writer_that_died_before_its_manifest_can_still_be_completed(tmp_path, monkeypatch):
    """An adaptive scan that ends early writes its shorter schedule.npy, then the manifest's planned_poses: a writer
    that died between the two (a crash, a full disk on scan.json) left 2 poses in the file and 4 in the manifest.
    The resumed writer takes the file's count, which the daemon's resume follows, so the scan can be completed."""
    sensor = sensor_preset("tmf8820")
    path = tmp_path / "scan"
    w = CaptureWriter.create(path, sensor, planned_poses=np.stack([np.eye(4)] * 4), chunk_size=8)
    for i in range(2):
        w.append(measurement(i, sensor))
    w.flush()
    real = cw.write_json_atomic

    def dies_on_the_manifest(target, data):
        if target.name == "scan.json" and data.get("planned_poses") == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(target, data)

    monkeypatch.setattr(cw, "write_json_atomic", dies_on_the_manifest)
    with pytest.raises(OSError):
        w.replace_schedule(np.stack([np.eye(4)] * 2))
    monkeypatch.undo()
    w.close()
    assert json.loads((path / "scan.json").read_text())["planned_poses"] == 4
    again = CaptureWriter.resume(path)
    assert again.manifest["planned_poses"] == 2 == len(CaptureReader(path).planned_poses())
    again.finish("complete")
    again.close()
    assert CaptureReader(path).state == "complete"
