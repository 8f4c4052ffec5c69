"""What the capture reader checks of a manifest, a schedule and the measurement records before anything fits them
(docs/capture_format.md, "Invariants a reader checks"): each problem one line naming the file, never a traceback."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spadscan.protocol.capture_format import MANIFEST, SCHEDULE, Measurement
from spadscan.protocol.capture_reader import CaptureReader, check_capture_counts
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.capture_kind import is_measured

SIM = sensor_preset("lcspc-sim")
TMF = sensor_preset("tmf8820")


def pose_at(i: int) -> np.ndarray:
    """A sensor pose on a circle of 0.5 m, looking at the origin: views i and i + 2 lie 0.259 m and 30 degrees
    apart."""
    a = np.radians(15.0 * i)
    eye = np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.2])
    z = -eye / np.linalg.norm(eye)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = eye
    return pose


def counts(sensor, i: int) -> np.ndarray:
    """Background-like counts (about 2 a bin) of measurement i."""
    return np.random.default_rng(i).poisson(2.0, (sensor.n_zones, sensor.n_bins)).astype(np.uint32)


def write(path, views: int = 6, frames: int = 1, sensor=SIM, chunk_size: int = 4, schedule: bool = True,
          pose_of=lambda view, frame: pose_at(view), **kwargs):
    """A complete capture: `views` poses of `frames` frames each, frame k of view v at pose_of(v, k)."""
    planned = np.stack([pose_at(v) for v in range(views)]) if schedule else None
    with CaptureWriter.create(path, sensor, chunk_size=chunk_size, planned_poses=planned, frames_per_pose=frames,
                              **kwargs) as w:
        for v in range(views):
            for k in range(frames):
                ref = np.full(sensor.n_bins, 50, np.uint32) if sensor.has_reference else None
                w.append(Measurement(counts(sensor, v * frames + k), pose_of(v, k), v, k, ref))
        w.finish("complete")
    return path


def edit_manifest(path, change) -> None:
    manifest = json.loads((path / MANIFEST).read_text())
    change(manifest)
    (path / MANIFEST).write_text(json.dumps(manifest))


def edit_records(path, chunk: str, change) -> None:
    meta_path = path / chunk / "meta.json"
    meta = json.loads(meta_path.read_text())
    change(meta["measurements"])
    meta_path.write_text(json.dumps(meta))


def refusal(path) -> str:
    """The one-line CaptureError reading and loading the capture at `path` gives."""
    with pytest.raises(CaptureError) as info:
        CaptureReader(path).load()
    message = str(info.value)
    assert "\n" not in message
    return message


# ---- the manifest's scene and rig ----------------------------------------------------------------------------------
@pytest.mark.parametrize("key, value, said", [
    ("scene", [1], "scene must be a JSON object, got list"),
    ("scene", "duck", "scene must be a JSON object, got str"),
    ("rig", [1], "rig must be a JSON object, got list"),
    ("rig", {"sensor": "sim"}, "rig.sensor must be a JSON object, got str"),
])
def test_a_scene_or_rig_that_is_no_json_object_is_refused_in_one_line_naming_it(tmp_path, key, value, said):
    """The worker looks keys up in them: a list or a string there ended a reconstruction in a traceback."""
    cap = write(tmp_path / "cap")
    edit_manifest(cap, lambda m: m.update({key: value}))
    with pytest.raises(CaptureError) as info:
        CaptureReader(cap)
    assert str(info.value) == f"{cap / MANIFEST}: {said}"


def test_a_null_scene_or_rig_reads_as_none_given(tmp_path):
    cap = write(tmp_path / "cap")
    edit_manifest(cap, lambda m: m.update(scene=None, rig={"sensor": None}))
    data = CaptureReader(cap).load()
    assert data.manifest["scene"] is None and not is_measured({}, data.manifest, data.sensor)


@pytest.mark.parametrize("real", ["false", "true", 0, 1, None])
def test_scene_real_must_be_true_or_false(tmp_path, real):
    """The string "false" is truthy: a simulated capture was fitted as measured, with a table and an estimated
    background, and nothing said so."""
    cap = write(tmp_path / "cap", rig={"kind": "simulated"})
    edit_manifest(cap, lambda m: m["scene"].update(real=real))
    with pytest.raises(CaptureError) as info:
        CaptureReader(cap)
    assert str(info.value) == f"{cap / MANIFEST}: scene.real = {real!r} must be true or false"
    with pytest.raises(CaptureError, match="scene.real"):
        is_measured({"real": real}, {}, SIM)


@pytest.mark.parametrize("real", [True, False])
def test_a_boolean_scene_real_decides_measured_or_simulated(tmp_path, real):
    cap = write(tmp_path / "cap", rig={"kind": "simulated"}, scene={"real": real})
    data = CaptureReader(cap).load()
    assert is_measured(data.manifest["scene"], data.manifest, data.sensor) is real


@pytest.mark.parametrize("key, value", [("frames_per_pose", 0), ("frames_per_pose", "2"), ("planned_poses", -1),
                                        ("planned_poses", 2.5), ("planned_poses", True)])
def test_malformed_pose_counts_in_the_manifest_are_refused(tmp_path, key, value):
    cap = write(tmp_path / "cap")
    edit_manifest(cap, lambda m: m.update({key: value}))
    with pytest.raises(CaptureError, match=f"^{cap / MANIFEST}: {key} "):
        CaptureReader(cap)


# ---- frames of one pose --------------------------------------------------------------------------------------------
def test_frames_of_one_pose_index_taken_at_different_poses_are_refused(tmp_path):
    """Summed into one view at the first frame's pose, frames taken elsewhere were silently misplaced (24 views
    0.9 m apart read as one)."""
    cap = write(tmp_path / "cap", views=3, frames=2, pose_of=lambda v, k: pose_at(v + 2 * k))
    message = refusal(cap)
    assert message.startswith(f"{cap}: the frames of pose 0 (and 2 other pose(s)) were taken up to 258.8 mm and "
                              f"30.0 degrees apart"), message
    assert "(within 1 mm and 0.5 degrees)" in message


def test_a_small_turn_alone_is_enough_to_refuse(tmp_path):
    def turned(v, k):
        pose = pose_at(v)
        a = np.radians(2.0 * k)  # about the boresight: the position stays
        spin = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        pose[:3, :3] = pose[:3, :3] @ spin
        return pose

    cap = write(tmp_path / "cap", views=2, frames=2, pose_of=turned)
    assert refusal(cap).startswith(f"{cap}: the frames of pose 0 (and 1 other pose(s)) were taken up to 0.0 mm and "
                                   f"2.0 degrees apart")


def test_frames_of_one_settled_pose_that_differ_by_microns_are_one_view(tmp_path):
    """A rig's readings of one settled pose (a retaken pose: the arm's repeatability) differ by microns."""
    def jittered(v, k):
        pose = pose_at(v)
        pose[:3, 3] += 2e-5 * k
        return pose

    cap = write(tmp_path / "cap", views=3, frames=3, pose_of=jittered)
    views = CaptureReader(cap).load().by_pose()
    assert views.frames.tolist() == [3.0, 3.0, 3.0]


def test_a_frame_number_beyond_frames_per_pose_is_refused_naming_the_record(tmp_path):
    cap = write(tmp_path / "cap", views=3, frames=2, chunk_size=2)

    def renumber(records):
        records[1]["frame"] = 2

    edit_records(cap, "chunk-000001", renumber)
    assert refusal(cap) == (f"{cap / 'chunk-000001' / 'meta.json'}: measurement 1 has frame 2 of pose 1, beyond the "
                            f"manifest's frames_per_pose 2 (frames 0..1)")


@pytest.mark.parametrize("frame", [-1, 0.5, "0", True])
def test_a_frame_number_that_is_no_count_is_refused(tmp_path, frame):
    cap = write(tmp_path / "cap", views=2)
    edit_records(cap, "chunk-000000", lambda records: records[1].update(frame=frame))
    assert refusal(cap) == f"{cap / 'chunk-000000' / 'meta.json'}: measurement 1 has frame {frame!r}, not an " \
                           f"integer >= 0"


def test_records_without_frame_numbers_are_read(tmp_path):
    """Another writer's records may lack them (the format requires only pose_index)."""
    cap = write(tmp_path / "cap", views=2)
    edit_records(cap, "chunk-000000", lambda records: [r.pop("frame") for r in records])
    assert len(CaptureReader(cap).load().meta) == 2


# ---- schedule.npy and pose indices ---------------------------------------------------------------------------------
def test_a_schedule_that_is_not_finite_is_refused_naming_it(tmp_path):
    cap = write(tmp_path / "cap")
    schedule = np.load(cap / SCHEDULE)
    schedule[2, 0, 3] = np.nan
    np.save(cap / SCHEDULE, schedule)
    assert refusal(cap) == f"{cap / SCHEDULE}: pose 2 is not finite"


def test_a_schedule_that_is_not_rigid_is_refused_naming_it(tmp_path):
    cap = write(tmp_path / "cap")
    schedule = np.load(cap / SCHEDULE)
    schedule[1, :3, :3] *= 2.0
    np.save(cap / SCHEDULE, schedule)
    assert refusal(cap).startswith(f"{cap / SCHEDULE}: pose 1 is not rigid")


def test_a_pose_index_beyond_the_schedule_is_refused(tmp_path):
    cap = write(tmp_path / "cap", views=6, chunk_size=4)
    np.save(cap / SCHEDULE, np.load(cap / SCHEDULE)[:3])
    assert refusal(cap) == (f"{cap / 'chunk-000000' / 'meta.json'}: measurement 3 has pose_index 3, beyond the 3 "
                            f"planned poses of {cap / SCHEDULE}")


def test_a_huge_pose_index_is_refused(tmp_path):
    cap = write(tmp_path / "cap", views=6, chunk_size=4)
    edit_records(cap, "chunk-000001", lambda records: records[1].update(pose_index=10**15))
    assert refusal(cap) == (f"{cap / 'chunk-000001' / 'meta.json'}: measurement 1 has pose_index 1000000000000000, "
                            f"beyond the 6 planned poses of {cap / SCHEDULE}")


def test_without_a_schedule_the_manifests_planned_poses_bound_the_pose_indices(tmp_path):
    cap = write(tmp_path / "cap", views=4, schedule=False)
    CaptureReader(cap).load()  # planned_poses null: nothing to check against
    edit_manifest(cap, lambda m: m.update(planned_poses=3))
    assert refusal(cap) == (f"{cap / 'chunk-000000' / 'meta.json'}: measurement 3 has pose_index 3, beyond the 3 "
                            f"planned poses of {cap / MANIFEST} (planned_poses)")


# ---- reference histograms ------------------------------------------------------------------------------------------
def test_reference_histograms_some_chunks_lack_are_left_out_with_a_note(tmp_path):
    """The reader keeps the references for every measurement or for none: dropping all of them (a measured
    capture's pulse then the sensor model's) is said in the capture's warning, which a run prints and reports."""
    cap = write(tmp_path / "cap", sensor=TMF, views=6, chunk_size=2)
    assert CaptureReader(cap).load().notes == () and check_capture_counts(cap) is None
    (cap / "chunk-000001" / "reference.npy").unlink()
    data = CaptureReader(cap).load()
    note = ("reference.npy is missing from 1 of 3 chunks (chunk-000001): no reference histogram is used, not even "
            "the other chunks' (a measured capture's pulse is then the sensor model's)")
    assert data.reference is None and data.notes == (note,)
    warned = []
    assert check_capture_counts(cap, warned.append) == f"{cap}: {note}"
    assert warned == [f"warning: {cap}: {note}"]


def test_the_reference_note_follows_the_counts_warning_on_one_line(tmp_path):
    cap = write(tmp_path / "cap", sensor=TMF, views=6, chunk_size=2)
    hists = np.load(cap / "chunk-000000" / "hists.npy")
    hists[0] = 0
    np.save(cap / "chunk-000000" / "hists.npy", hists)
    for chunk in ("chunk-000000", "chunk-000002"):
        (cap / chunk / "reference.npy").unlink()
    assert check_capture_counts(cap) == (
        f"{cap}: 9 of 54 histograms no sensor could have produced (9 all zero), left out; reference.npy is missing "
        f"from 2 of 3 chunks (chunk-000000, chunk-000002): no reference histogram is used, not even the other "
        f"chunks' (a measured capture's pulse is then the sensor model's)")


def test_a_capture_without_any_reference_histograms_gets_no_note(tmp_path):
    cap = write(tmp_path / "cap", sensor=TMF, views=4, chunk_size=2)
    for chunk in ("chunk-000000", "chunk-000001"):
        (cap / chunk / "reference.npy").unlink()
    assert CaptureReader(cap).load().notes == ()


# ---- the sensor model ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("key", ["n_bins", "cycles"])
def test_a_missing_sensor_key_is_named_as_the_manifests_key(tmp_path, key):
    cap = write(tmp_path / "cap")
    edit_manifest(cap, lambda m: m["sensor"].pop(key))
    with pytest.raises(CaptureError) as info:
        CaptureReader(cap)
    assert str(info.value) == f"{cap / MANIFEST}: sensor model lacks {key!r}"


# ---- counts of simulated captures ----------------------------------------------------------------------------------
def over_cycles(path, share: float):
    """Measurement 1 scaled to `share` x its sensor's cycles in all."""
    hists_path = path / "chunk-000000" / "hists.npy"
    hists = np.load(hists_path)
    cycles = CaptureReader(path).sensor.cycles
    hists[1] = np.floor(hists[1] * (share * cycles / hists[1].sum())).astype(np.uint32)
    np.save(hists_path, hists)
    return path


@pytest.mark.parametrize("rig", [{"kind": "simulated"}, {"sensor": {"backend": "sim"}}])
def test_a_simulated_histogram_over_its_cycles_is_implausible(tmp_path, rig):
    """This project's simulator draws one multinomial outcome a cycle: its histograms never hold more counts than
    their cycles. The 1.5 margin is for a real sensor's estimated cycles (the TMF8820's 4 +- 0.7 million)."""
    cap = over_cycles(write(tmp_path / "cap", rig=rig), 1.2)
    assert check_capture_counts(cap) == (f"{cap}: 1 of 6 histograms no sensor could have produced (1 with more "
                                         f"counts than their 5,000 laser cycles), left out")
    data = CaptureReader(cap).load()
    assert data.count_bounds() == (SIM.max_count, SIM.ignore_bins, 5000, 1.0)


def test_a_simulated_histogram_at_its_cycles_is_plausible(tmp_path):
    cap = over_cycles(write(tmp_path / "cap", rig={"kind": "simulated"}), 1.0)
    assert check_capture_counts(cap) is None


@pytest.mark.parametrize("rig", [{}, {"sensor": {"backend": "serial"}}])
def test_other_captures_keep_the_margin_of_estimated_cycles(tmp_path, rig):
    cap = over_cycles(write(tmp_path / "cap", rig=rig), 1.2)
    assert check_capture_counts(cap) is None
    assert CaptureReader(cap).load().count_bounds()[2:] == (5000, 1.5)
    over_cycles(cap, 1.6)
    assert "more counts than 1.5 x their 5,000 laser cycles" in check_capture_counts(cap)
