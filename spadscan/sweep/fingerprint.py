"""What decides a stored method's result beyond its point's id: a fingerprint per method, kept in its point's file.

A point's id (plan.py) holds what the sweep file says: the scene, the parameters, the methods' settings. What the file
leaves to spadscan is not in it: a preset's config after its defaults (presets.py), the thresholds a baseline calibrates
over when the file gives none (CALIBRATION_THRESHOLDS), the code itself (spadscan's version, and a hash of the source
that makes a point's results: `code_digest`, so that a change between two versions, as while developing a method, is not
taken for the code that stored the point), and for a preset the device it reconstructs on. Each method's fingerprint
hashes those with the point's id; a stored method whose fingerprint differs from the one this run computes is stale: it
runs again, and its point's file is replaced once the new result is stored (never before).

A point stored before fingerprints were (no "fingerprints" in its file) holds the version and the device it ran
with: it is stale where either differs from this run's (a preset's device only: a baseline runs on the CPU), and is
taken as it is where its file does not say.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path

import spadscan
from spadscan.worker.baselines.common import CALIBRATION_THRESHOLDS
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.presets import preset_config

from .plan import PointTask, canonical_hash

FINGERPRINT_FORMAT = 2
"""Version of what a fingerprint hashes; a new one makes every stored method stale (2: the source's hash too)."""
RESULT_PACKAGES = ("spadscan.protocol", "spadscan.worker")
"""Packages whose source makes a point's results (the simulator, the sensor models, the methods, the metrics)."""
POINT_MODULES = ("point.py", "params.py", "scenes.py")
"""The sweep's own modules that run a point (beside this one); the rest (planning, storing, drawing) does not change a
result, and a change there leaves the stored points current."""


NO_SOURCE = "no-source"
"""`code_digest` of an install without the source files (bytecode only, a zip): its version alone then says."""


def source_digest(files: list[tuple[str, Path]]) -> str:
    """A hash of source files given as (name, path) pairs: their names and contents (line ends as LF: a Windows
    checkout hashes as a Linux one), in name order."""
    h = hashlib.sha256()
    for name, path in sorted(files):
        data = path.read_bytes().replace(b"\r\n", b"\n")
        h.update(f"{name}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()[:16]


def code_digest() -> str:
    """`source_digest` of the Python source that makes a point's results: RESULT_PACKAGES' and POINT_MODULES'
    (regular files only, none under a dot-name: an editor's lock file `.#model.py` is a dangling link), or NO_SOURCE
    where the install holds none of it."""
    files = []
    for package in RESULT_PACKAGES:
        root = Path(importlib.import_module(package).__file__).parent
        for p in root.rglob("*.py"):
            rel = p.relative_to(root)
            if p.is_file() and not any(part.startswith(".") for part in rel.parts):
                files.append((f"{package}/{rel.as_posix()}", p))
    here = Path(__file__).parent
    files += [(f"spadscan.sweep/{name}", here / name) for name in POINT_MODULES if (here / name).is_file()]
    return source_digest(files) if files else NO_SOURCE


class Digests:
    """Each method's inputs hashed, per distinct set of presets, baselines and counts: most points of a plan share
    them, so one instance per run resolves and hashes them once (a sweep of 100,000 points looks at every point's
    state). Made afresh for each run: a preset's defaults are read as the run starts."""

    def __init__(self):
        self._configs: dict[tuple[str, str], dict] = {}
        self._digests: dict[str, dict[str, str]] = {}
        self.code = code_digest()
        """The source's hash (`code_digest`), read once per run: a few hundred files, some 30 ms."""

    def resolved_config(self, task: PointTask, preset) -> dict:
        """The config `preset` runs with at `task`'s point: the preset's defaults, the sweep file's overrides, and
        the metrics' sample count (as point.py runs it)."""
        overrides = json.dumps({**preset.overrides, "metrics_points": task.metrics_points}, sort_keys=True)
        key = (preset.name, overrides)
        if key not in self._configs:
            config = with_overrides(preset_config(preset.name), json.loads(overrides)).to_dict()
            self._configs[key] = json.loads(json.dumps(config, sort_keys=True, default=str))
        return self._configs[key]

    def method_inputs(self, task: PointTask, device: str, version: str) -> dict[str, dict]:
        """{method: what its fingerprint hashes, less the point's id} for every method of `task` run on `device`."""
        common = {"format": FINGERPRINT_FORMAT, "spadscan": version, "code": self.code}
        inputs = {}
        for preset in task.presets:
            inputs[preset.name] = {**common, "method": preset.name, "config": self.resolved_config(task, preset),
                                   "steps": preset.steps, "budget_s": preset.budget_s, "device": device}
        b = task.baselines
        thresholds = list(CALIBRATION_THRESHOLDS if b.thresholds is None else b.thresholds)
        for method in b.methods:
            inputs[method] = {**common, "method": method, "thresholds": thresholds, "resolution": b.resolution,
                              "calibration_points": task.calibration_points, "metrics_points": task.metrics_points}
        return inputs

    def fingerprints(self, task: PointTask, device: str, version: str) -> dict[str, str]:
        """{method: fingerprint} for every method of `task` run on `device` with spadscan `version`: the hash of
        the point's id and of its method's inputs."""
        key = json.dumps([[{"name": p.name, **p.record()} for p in task.presets], task.baselines.record(),
                          task.metrics_points, task.calibration_points, device, version], sort_keys=True)
        digests = self._digests.get(key)
        if digests is None:
            digests = self._digests[key] = {name: canonical_hash(data)
                                            for name, data in self.method_inputs(task, device, version).items()}
        return {name: canonical_hash([task.id, digest])[:16] for name, digest in digests.items()}


class Expected:
    """What this run would store of one point: its methods' fingerprints, and what a point stored before
    fingerprints were is checked against (the version; for a preset, the device)."""

    def __init__(self, task: PointTask, device: str, version: str | None = None, digests: Digests | None = None):
        self.version = spadscan.__version__ if version is None else version
        self.device = device
        self.presets = {p.name for p in task.presets}
        digests = digests or Digests()
        self.code = digests.code
        """The source's hash these fingerprints were made with (`code_digest`): stored with the point, so that a
        client can tell a worker running other source (its points then stale to the client)."""
        self.fingerprints = digests.fingerprints(task, device, self.version)

    def current(self, stored: dict, method: str) -> bool:
        """Whether `method`'s record in the stored point `stored` was made by what this run would run, whatever its
        status."""
        stored_fps = stored.get("fingerprints")
        if isinstance(stored_fps, dict):
            return method in self.fingerprints and stored_fps.get(method) == self.fingerprints[method]
        # Stored before fingerprints were: what its file says of the code and the device (the module's docstring).
        said_version, said_device = stored.get("spadscan"), stored.get("device")
        if said_version is not None and said_version != self.version:
            return False
        return not (method in self.presets and said_device is not None and said_device != self.device)

    def reusable(self, stored: dict | None) -> dict[str, dict]:
        """The methods the stored point `stored` holds done and current: {method: its record}."""
        if not isinstance(stored, dict) or not isinstance(stored.get("methods"), dict):
            return {}
        return {name: record for name, record in stored["methods"].items()
                if name in self.fingerprints and isinstance(record, dict) and record.get("status") == "done"
                and self.current(stored, name)}

    def state(self, stored: dict | None) -> str:
        """'done' (stored done, every method current: nothing to run), 'stale' (stored done, a method not), the
        stored status otherwise ('failed'), or 'to run' where nothing is stored."""
        if not isinstance(stored, dict):
            return "to run"
        if stored.get("status") != "done":
            return str(stored.get("status") or "to run")
        methods = stored.get("methods") if isinstance(stored.get("methods"), dict) else {}
        return "done" if all(self.current(stored, name) for name in methods) else "stale"


__all__ = ["Digests", "Expected", "FINGERPRINT_FORMAT", "NO_SOURCE", "code_digest", "source_digest"]
