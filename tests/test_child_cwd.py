"""spadscan's child processes import the installed package, whatever folder they start in.

`python -m MODULE` puts its working folder first on sys.path: started from the folder that holds a clone of the
repository (`~` for `~/spadscan`), `import spadscan` found the clone's top folder (no `__init__.py`) as a namespace
package in place of the installed one, and the child failed on what the package itself defines: the job process's
report (`spadscan.__version__`), after the whole fit. Each test here starts a child the way spadscan does, from a
folder that holds an empty `spadscan` folder.
"""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import spadscan
from spadscan.demo import _spadscan
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.child_command import module_command
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.children import spawn_job
from spadscan.worker.jobs import EXIT_DONE, Job

REPO = Path(__file__).resolve().parent.parent
HERE = Path(__file__).resolve().parent


@pytest.fixture
def clone_parent(tmp_path):
    """A working folder like the one that holds a clone of the repository: a `spadscan` folder without
    `__init__.py`."""
    folder = tmp_path / "home"
    (folder / "spadscan").mkdir(parents=True)
    return folder


def versions_recon(capture, out, **options):
    """A stand-in reconstruction that reports the package's version, as the real one's report does."""
    report = {"versions": {"spadscan": spadscan.__version__}}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def make_capture(root: Path, name: str) -> None:
    """A tiny complete capture (two histograms of background counts)."""
    sensor = sensor_preset("lcspc-sim")
    rng = np.random.default_rng(0)
    writer = CaptureWriter.create(root / name, sensor, chunk_size=4)
    for i in range(2):
        writer.append(Measurement(rng.poisson(2.0, (1, sensor.n_bins)).astype(np.uint32), np.eye(4), i))
    writer.finish("complete")


def test_a_job_process_imports_the_installed_package(tmp_path, clone_parent, monkeypatch):
    root = tmp_path / "captures"
    make_capture(root, "s")
    outcome, log = tmp_path / "outcome.json", tmp_path / "job.log"
    monkeypatch.chdir(clone_parent)  # the job process starts where the worker runs

    async def run() -> int:
        proc = await spawn_job(Job(id="s-fast", scan="s"), root, tmp_path / "scratch", outcome, log,
                               recon="test_child_cwd:versions_recon", extra_env={"PYTHONPATH": str(HERE)})
        return await proc.wait()

    code = asyncio.run(run())
    assert code == EXIT_DONE, f"{json.loads(outcome.read_text())}\n{log.read_text()}"
    assert json.loads((tmp_path / "scratch" / "report.json").read_text())["versions"]["spadscan"] == \
        spadscan.__version__


def test_the_demos_children_import_the_installed_package(clone_parent):
    done = subprocess.run(_spadscan("--version"), cwd=clone_parent, capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout.strip()) == (0, f"spadscan {spadscan.__version__}"), done.stderr


def test_without_P_the_folder_takes_the_packages_place(clone_parent):
    # What the tests above guard against, shown: where the package is found by an import hook (the editable install
    # the README and tests/run.sh use), not on sys.path itself, the working folder's `spadscan` wins without -P.
    if _found_on_sys_path(clone_parent):
        pytest.skip("spadscan is installed as a plain package on sys.path, which a folder without __init__.py "
                    "cannot shadow")
    cmd = module_command("spadscan.cli", "--version")
    assert cmd[1] == "-P"
    done = subprocess.run([cmd[0], *cmd[2:]], cwd=clone_parent, capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "__version__" in done.stderr, (done.stdout, done.stderr)


def test_every_module_child_is_started_with_module_command():
    # `sys.executable, "-m"` anywhere else starts a child that the working folder can shadow.
    started = re.compile(r"sys\.executable\s*,\s*[\"']-m[\"']")
    found = [f"{path.relative_to(REPO)}:{text.count(chr(10), 0, m.start()) + 1}"
             for folder in ("spadscan", "protocol", "daemon", "worker", "benchmarks")
             for path in sorted((REPO / folder).rglob("*.py"))
             for text in [path.read_text()] for m in started.finditer(text)]
    assert found == []


def _found_on_sys_path(cwd: Path) -> bool:
    """Whether a child's `import spadscan` finds a regular package on its sys.path (the working folder left out)."""
    code = ("import importlib.machinery, sys; spec = importlib.machinery.PathFinder.find_spec('spadscan', sys.path); "
            "print(spec is not None and spec.origin is not None)")
    done = subprocess.run([sys.executable, "-P", "-c", code], cwd=cwd, capture_output=True, text=True, timeout=120,
                          check=True)
    return done.stdout.strip() == "True"
