"""Helpers of the sweep tests: a tiny sweep file (2 parameters x 2 values, one point that fails), the CLI in a child
process, and a real Dask cluster (`dask scheduler` and `dask worker` processes on loopback)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

TINY = """
[sweep]
scenes = ["builtin:sphere"]

[base]
views = 12
rays_per_zone = 256
bin_ps = 33.4

[grid]
views = [8, 12]
power = [1.0, 1e-7]        # 1e-7: no photon comes back, every method fails at that point

[fast]
steps = {steps}
set = {{ "field.resolution" = 20, "field.hull_resolution" = 40, mesh_resolution = 48, trace_checkpoints = 1, trace_mesh_resolution = 24, trace_points = 1000 }}

[baselines]
thresholds = [5, 20]
resolution = 40

[metrics]
points = 5000
calibration_points = 5000
"""
FAILING_POWER = 1e-7


def write_tiny(folder: Path, steps: int = 20) -> Path:
    """The tiny sweep: views 8 and 12, power 1 and 1e-7 around views 12 / power 1: four entries, three points."""
    path = Path(folder) / "tiny.toml"
    path.write_text(TINY.format(steps=steps))
    return path


def spadscan(*args: str, **kwargs) -> subprocess.CompletedProcess:
    """Run the spadscan CLI in a child process (the way a user runs it)."""
    return subprocess.run([sys.executable, "-m", "spadscan.cli", *args], capture_output=True, text=True,
                          timeout=kwargs.pop("timeout", 600), **kwargs)


class DaskCluster:
    """`dask scheduler` and `dask worker` processes on 127.0.0.1, each in its own process group (a worker's nanny
    and its worker process go together)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.scheduler_file = self.folder / "scheduler.json"
        self.procs: dict[str, subprocess.Popen] = {}

    def _start(self, name: str, args: list[str]) -> subprocess.Popen:
        log = open(self.folder / f"{name}.log", "w")
        proc = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True, cwd=self.folder)
        log.close()
        self.procs[name] = proc
        return proc

    def start(self, workers: int = 2, deadline_s: float = 120) -> "DaskCluster":
        self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                  "--scheduler-file", str(self.scheduler_file)])
        self._wait(lambda: self.scheduler_file.exists(), deadline_s, "the scheduler's file")
        for i in range(1, workers + 1):
            self._start(f"w{i}", ["worker", "--scheduler-file", str(self.scheduler_file), "--name", f"w{i}",
                                  "--nthreads", "1", "--nworkers", "1", "--host", "127.0.0.1", "--no-dashboard",
                                  "--death-timeout", "60"])
        self.wait_for_workers(workers, deadline_s)
        return self

    @property
    def address(self) -> str:
        import json

        return json.loads(self.scheduler_file.read_text())["address"]

    def wait_for_workers(self, n: int, deadline_s: float) -> None:
        from distributed import Client

        with Client(scheduler_file=str(self.scheduler_file), timeout=deadline_s) as client:
            client.wait_for_workers(n, timeout=deadline_s)

    def kill(self, name: str) -> None:
        """SIGKILL a worker's whole process group: its nanny and its worker process die at once."""
        proc = self.procs[name]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)

    def stop(self) -> None:
        for name, proc in reversed(list(self.procs.items())):
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        for proc in self.procs.values():
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)

    def _wait(self, ready, deadline_s: float, what: str) -> None:
        end = time.monotonic() + deadline_s
        while not ready():
            if time.monotonic() > end:
                raise TimeoutError(f"no {what} within {deadline_s} s")
            if any(p.poll() is not None for p in self.procs.values()):
                raise RuntimeError(f"a Dask process exited while waiting for {what}: see {self.folder}/*.log")
            time.sleep(0.1)
