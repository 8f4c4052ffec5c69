"""The soak's stand-in reconstruction (tests/e2e/test_soak_faults.py): a job process that reads the whole capture,
checks that it holds every planned pose with every frame exactly once, takes a second or so (so that a worker killed
at a random moment is often killed mid-job), and leaves a mesh and a report, as a reconstruction does."""

from __future__ import annotations

import collections
import json
import random
import time
from pathlib import Path

from spadscan.protocol.capture_reader import CaptureReader


def reconstruct(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None) -> dict:
    import trimesh

    reader = CaptureReader(capture)
    data = reader.load()
    frames = collections.Counter(zip(data.pose_indices.tolist(), (m["frame"] for m in data.meta)))
    per_pose = int(reader.manifest["schedule"]["frames_per_pose"])
    planned = len(reader.planned_poses())
    expected = {(p, f) for p in range(planned) for f in range(per_pose)}
    if set(frames) != expected or set(frames.values()) != {1}:
        raise RuntimeError(f"{capture}: not every planned pose and frame exactly once")
    time.sleep(random.Random(Path(capture).name).uniform(0.3, 1.5))
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(Path(out) / "mesh.ply")
    report = {"preset": preset, "measurements": len(data.hists), "poses": planned}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report
