"""The benchmarks are scripts, not part of the package: their tests load them as modules from benchmarks/."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(stem: str) -> ModuleType:
    """benchmarks/<stem>.py loaded as the module <stem>."""
    spec = importlib.util.spec_from_file_location(stem, BENCHMARKS / f"{stem}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[stem] = module  # a dataclass looks its module up there while the module runs
    spec.loader.exec_module(module)
    return module


def start_main(stem: str, argv: list[str], stand_ins: str = "", env: dict | None = None) -> subprocess.Popen:
    """benchmarks/<stem>.py's main(argv) in a process of its own (stdout and stderr piped, as text), once
    `stand_ins` (Python run with the script loaded as `bench`) has stood in for its slow parts. Its own process, so
    that a test can signal or kill it as a time limit or a user would."""
    code = "\n".join([
        "import sys",
        f"sys.path.insert(0, {str(Path(__file__).resolve().parent)!r})",
        "from benchmark_helpers import load_benchmark",
        f"bench = load_benchmark({stem!r})",
        textwrap.dedent(stand_ins),
        f"sys.exit(bench.main({[str(a) for a in argv]!r}))",
    ])
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


def children(pid: int) -> set[int]:
    """Live child processes of `pid` (from /proc), zombies excluded."""
    pids: set[int] = set()
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):
                pids.update(int(p) for p in (task / "children").read_text().split())
    return {p for p in pids if running(p)}


def running(pid: int) -> bool:
    """Whether `pid` is a live process (a zombie, exited but not yet reaped by its new parent, is not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def wait_gone(pids, timeout_s: float = 120.0) -> set[int]:
    """Wait until none of `pids` runs (at most `timeout_s`: generous, for a loaded machine); those still running."""
    deadline = time.monotonic() + timeout_s
    left = {p for p in pids if running(p)}
    while left and time.monotonic() < deadline:
        time.sleep(0.05)
        left = {p for p in left if running(p)}
    return left


def kill_all(proc: subprocess.Popen, pids) -> None:
    """Stop `proc` and the processes `pids` (its children, say) that still run, however the test ended."""
    if proc.poll() is None:
        proc.kill()
    with contextlib.suppress(subprocess.TimeoutExpired, OSError, ValueError):
        proc.communicate(timeout=30)
    for pid in pids:
        if running(pid):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
    wait_gone(pids, timeout_s=30)


def tiny_capture(folder: Path, views: int = 2) -> Path:
    """A capture of a box seen from `views` simulated views at 0.3 m, 64 rays a zone: one that reads and holds views
    (the runs never start on it)."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(views, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    return simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, folder / "box",
                            settings=SimSettings(rays_per_zone=64), progress=False)
