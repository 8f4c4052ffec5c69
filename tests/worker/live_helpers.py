"""A stand-in for the daemon in live-job tests: replays a finished capture into a new one pose by pose, through the
project's CaptureWriter (each pose published as its own chunk by one rename, as the daemon does)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.worker.live.job import execute_live_job


class ReplayScan:
    """Publishes the poses of the complete capture `source` into the new capture `dest`, a pose at a time."""

    def __init__(self, source: Path, dest: Path):
        reader = CaptureReader(source)
        data = reader.load()
        m = reader.manifest
        self.measurements = [Measurement(data.hists[i], data.poses[i], int(meta["pose_index"]),
                                         int(meta.get("frame", 0)), None if data.reference is None
                                         else data.reference[i], {}) for i, meta in enumerate(data.meta)]
        self.poses = sorted({mm.pose_index for mm in self.measurements})
        self.writer = CaptureWriter.create(
            dest, reader.sensor, rig=m.get("rig"), schedule=m.get("schedule"), planned_poses=reader.planned_poses(),
            chunk_size=1, scene=m.get("scene"), frames_per_pose=int(m.get("frames_per_pose", 1)))
        self.dest = Path(dest)
        self.published = 0

    def publish(self, n: int = 1) -> int:
        """Publish the next `n` poses (each its own chunk); returns the poses published so far."""
        for index in self.poses[self.published:self.published + n]:
            for mm in self.measurements:
                if mm.pose_index == index:
                    self.writer.append(mm)
            self.writer.flush()
            self.published += 1
        return self.published

    def run(self, every_s: float = 0.0, until: int | None = None) -> None:
        """Publish poses every `every_s` seconds up to pose count `until` (default: all)."""
        while self.published < (len(self.poses) if until is None else until):
            self.publish(1)
            time.sleep(every_s)

    def finish(self, state: str = "complete", reason: str | None = None) -> None:
        self.writer.finish(state, reason)


class SecondLiveJob:
    """A live job of a scan whose live folder another live job holds, run on a thread (`execute_live_job`): `said`
    is set once it logs a line holding `marker` (that it publishes nothing there), `result` gets its report."""

    def __init__(self, job, root: Path, out: Path, marker: str, **kwargs):
        self.lines: list[str] = []
        self.said = threading.Event()
        self.result: dict = {}

        def log(line):
            self.lines.append(line)
            if marker in line:
                self.said.set()

        self.thread = threading.Thread(target=lambda: self.result.update(report=execute_live_job(
            job, root, out, log=log, **kwargs)), daemon=True)
        self.thread.start()

    def after_scan(self, scan: ReplayScan) -> dict:
        """Once the job has said it publishes nothing in the live folder: `scan` completed (every planned pose
        published, as "complete" promises), and the job's report once it has ended."""
        assert self.said.wait(120), self.lines
        scan.run()
        scan.finish("complete")
        self.thread.join(300)
        assert not self.thread.is_alive()
        return self.result["report"]
