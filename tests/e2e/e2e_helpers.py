"""Helpers of the end-to-end tests: rig configs in a temporary folder, `spadscan` as real processes, waiting, and
checks of capture folders and of processes left behind (through /proc).

Every process started here is stopped by its owner (`Daemon.stop`, `Procs.stop_all`), also when a test fails.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from spadscan.daemon.client import ControlError, call
from spadscan.protocol.capture_reader import CaptureReader

# A sim rig: instant moves, instant frames, a small scene, few rays. Tests override keys per section.
BASE_RIG = {
    "auto_resume": False,
    "arm": {"backend": "sim", "motion_time_s": 0.0,
            "hand_eye": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]},
    "sensor": {"backend": "sim", "preset": "tmf8820", "mesh": "builtin:sphere", "rays_per_zone": 4,
               "frame_timeout_s": 5.0},
    "scan": {"views": 12, "frames_per_pose": 1, "settle_s": 0.0, "radius_m": 0.4, "target": [0.0, 0.0, 0.1],
             "chunk_size": 64},
}


# ---- configs ---------------------------------------------------------------------------------------------------------
def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (str, Path)):
        return json.dumps(str(v))  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def toml_text(data: dict) -> str:
    """TOML for a dict of top-level keys and tables (one level of tables, as a rig config has)."""
    top = [f"{k} = {toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    out = top[:]
    for name, table in data.items():
        if isinstance(table, dict):
            out.append(f"\n[{name}]")
            out += [f"{k} = {toml_value(v)}" for k, v in table.items()]
    return "\n".join(out) + "\n"


def rig_dict(captures: Path, sock: Path, **sections) -> dict:
    """BASE_RIG with captures and socket set; `sections` maps 'arm' / 'sensor' / 'scan' / 'top' to key overrides
    (a value None removes the key)."""
    data = {"captures": str(captures), "socket": str(sock)}
    for k, v in BASE_RIG.items():
        data[k] = dict(v) if isinstance(v, dict) else v
    for name, over in sections.items():
        target = data if name == "top" else data.setdefault(name, {})
        for k, v in over.items():
            if v is None:
                target.pop(k, None)
            else:
                target[k] = v
    return data


# ---- running spadscan ------------------------------------------------------------------------------------------------
def spadscan_argv(*args) -> list[str]:
    return [sys.executable, "-m", "spadscan.cli", *map(str, args)]


def spadscan(*args, timeout: float = 120, **kwargs) -> subprocess.CompletedProcess:
    """Run `spadscan ARGS` to its end; stdout and stderr as text."""
    return subprocess.run(spadscan_argv(*args), capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL, **kwargs)


def one_line_error(r: subprocess.CompletedProcess) -> str:
    """Assert a command failed with exit 1 and exactly one line `spadscan: error: ...` on stderr; return it."""
    assert r.returncode == 1, f"exit {r.returncode}; stderr: {r.stderr}"
    lines = r.stderr.strip().splitlines()
    assert "Traceback" not in r.stderr, r.stderr
    assert len(lines) == 1 and lines[0].startswith("spadscan: error: "), r.stderr
    return lines[0]


def wait_for(pred, what: str, timeout_s: float = 60.0, poll_s: float = 0.02):
    """Poll pred() until it returns something truthy (returned); AssertionError naming `what` after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Procs:
    """Background processes of one test, stopped (SIGTERM, then SIGKILL) in reverse order by stop_all."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.procs: list[tuple[subprocess.Popen, Path]] = []

    def start(self, argv: list[str], name: str, **kwargs) -> subprocess.Popen:
        log = self.folder / f"{name}-{len(self.procs)}.log"
        # Ctrl-C as a terminal delivers it: a test run started in the background (`.ci/run &`) inherits SIGINT
        # ignored, and Python keeps an ignored SIGINT ignored, so the Ctrl-C tests would test nothing.
        kwargs.setdefault("preexec_fn", _default_sigint)
        with open(log, "wb") as f:
            proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, **kwargs)
        self.procs.append((proc, log))
        return proc

    def log(self, proc: subprocess.Popen) -> str:
        for p, log in self.procs:
            if p is proc:
                return log.read_text(errors="replace")
        return ""

    def stop(self, proc: subprocess.Popen, sig: int = signal.SIGTERM, grace_s: float = 30.0) -> int:
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=30)
        return proc.returncode

    def stop_all(self) -> None:
        for proc, _ in reversed(self.procs):
            self.stop(proc, grace_s=15.0)


class Daemon:
    """`spadscan daemon --config RIG` as a process of `procs`, with its control socket and captures root."""

    def __init__(self, procs: Procs, rig: Path, sock: Path, captures: Path):
        self.procs, self.rig, self.sock, self.captures = procs, Path(rig), Path(sock), Path(captures)
        self.proc: subprocess.Popen | None = None

    def start(self, timeout_s: float = 90.0) -> "Daemon":
        self.proc = self.procs.start(spadscan_argv("daemon", "--config", self.rig), "daemon")
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                call(self.sock, "status", timeout_s=5)
                return self
            except ControlError:
                if self.proc.poll() is not None:
                    raise AssertionError(f"daemon exited with {self.proc.returncode}: {self.log()}")
                if time.monotonic() > deadline:
                    raise AssertionError(f"daemon did not listen within {timeout_s:g} s: {self.log()}")
                time.sleep(0.05)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        return self.procs.log(self.proc)

    def status(self) -> dict:
        return call(self.sock, "status", timeout_s=30)

    def call(self, op: str, **args) -> dict:
        return call(self.sock, op, timeout_s=30, **args)

    def ctl(self, *args, timeout: float = 120) -> subprocess.CompletedProcess:
        """The real `spadscan ctl --socket SOCK ARGS`."""
        return spadscan("ctl", "--socket", self.sock, *args, timeout=timeout)

    def wait_state(self, state: str, timeout_s: float = 60.0) -> dict:
        return wait_for(lambda: (s := self.status())["state"] == state and s, f"daemon state {state!r}", timeout_s)

    def wait_pose(self, scan: str, at_least: int, timeout_s: float = 60.0) -> dict:
        return wait_for(lambda: ((s := self.status())["scan"] == scan and (s.get("pose") or 0) >= at_least) and s,
                        f"scan {scan} at pose {at_least}", timeout_s)

    def kill9(self) -> None:
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)
        assert self.proc.returncode == -signal.SIGKILL

    def stop(self) -> int:
        return self.procs.stop(self.proc)


# ---- captures --------------------------------------------------------------------------------------------------------
def assert_every_pose_once(folder: Path, n_poses: int, frames_per_pose: int, *, complete: bool = True,
                           atol: float = 1e-6):
    """Each (pose, frame) of the plan exactly once in the capture; each measurement at its planned pose.
    Returns the loaded CaptureData."""
    reader = CaptureReader(folder)
    if complete:
        assert reader.state == "complete", reader.manifest.get("reason")
    data = reader.load()
    frames = [m["frame"] for m in data.meta]
    counts = collections.Counter(zip(data.pose_indices.tolist(), frames))
    assert sorted(counts) == [(i, f) for i in range(n_poses) for f in range(frames_per_pose)], \
        f"missing or extra poses: {sorted(set(range(n_poses)) ^ set(data.pose_indices.tolist()))}"
    assert set(counts.values()) == {1}, f"repeated: {[k for k, c in counts.items() if c > 1]}"
    planned = reader.planned_poses()
    # Simulated arms reach their targets exactly: every measurement was taken at the pose its index names.
    np.testing.assert_allclose(data.poses, planned[data.pose_indices], atol=atol)
    return data


def drop_ground_truth(folder: Path) -> None:
    """Remove the scene record from a simulated capture's manifest: the worker then reconstructs it without a ground
    truth and skips the metrics (which cost far more than a two-step reconstruction)."""
    manifest = Path(folder) / "scan.json"
    data = json.loads(manifest.read_text())
    data["scene"] = {}
    manifest.write_text(json.dumps(data, indent=1) + "\n")


def published_prefix(folder: Path) -> tuple[list[int], dict[str, str]]:
    """(sorted pose indices published, {chunk name: sha256 of its files}) of a capture folder right now."""
    reader = CaptureReader(folder)
    poses = sorted(set(reader.load().pose_indices.tolist()))
    return poses, chunk_digests(folder)


def chunk_digests(folder: Path) -> dict[str, str]:
    out = {}
    for chunk in sorted(Path(folder).glob("chunk-*")):
        h = hashlib.sha256()
        for f in sorted(chunk.iterdir()):
            h.update(f.name.encode() + b"\0" + f.read_bytes())
        out[chunk.name] = h.hexdigest()
    return out


# ---- filesystems ----------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def tmpfs(mountpoint: Path, size: str):
    """Mount a tmpfs of `size` (e.g. '2m') at mountpoint (created) for the block; yields False (and mounts nothing)
    where mounting is not allowed (not root). Unmounts on the way out (lazily if something still holds it)."""
    mountpoint.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(mountpoint)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        yield False
        return
    try:
        yield True
    finally:
        if subprocess.run(["umount", str(mountpoint)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(mountpoint)], capture_output=True)


# ---- processes -------------------------------------------------------------------------------------------------------
def processes_mentioning(text: str) -> dict[int, str]:
    """Live processes (not zombies) whose command line contains `text`: {pid: command line}."""
    found = {}
    me = os.getpid()
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == me:
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (d / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if text in cmd and state != "Z":
            found[int(d.name)] = cmd.strip()
    return found


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for pid {pid}")


def open_fds(pid: int) -> dict[int, str]:
    """The process's open file descriptors: {fd: what it points to}."""
    out = {}
    for p in Path(f"/proc/{pid}/fd").iterdir():
        try:
            out[int(p.name)] = os.readlink(p)
        except OSError:
            continue
    return out


def settled_fds(pid: int, timeout_s: float = 30.0) -> dict[int, str]:
    """The process's open fds once none is closing any more (the same set twice, 0.3 s apart)."""
    last = open_fds(pid)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(0.3)
        now = open_fds(pid)
        if now == last:
            return now
        last = now
    return last
