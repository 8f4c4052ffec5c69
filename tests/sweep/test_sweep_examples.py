"""The shipped sweep files and the overhead benchmark stay runnable."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import trimesh

from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec

REPO = Path(__file__).resolve().parents[2]
SWEEPS = REPO / "examples" / "sweeps"


def test_small_example_is_a_few_short_points():
    plan = make_plan(load_spec(SWEEPS / "small.toml"))
    assert len(plan.points) == 5 and set(plan.spec.grid) == {"views", "ambient"}
    assert plan.spec.presets[0].steps <= 500


def test_figure_a_spans_the_supplements_panels(tmp_path):
    root = tmp_path / "LCSPCData"  # a stand-in for the dataset: any mesh where the bunny's file lies
    (root / "simulated" / "bunny").mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(root / "simulated" / "bunny" / "bunny.obj")
    plan = make_plan(load_spec(SWEEPS / "figure_a.toml"), root)
    grid = plan.spec.grid
    assert list(grid) == ["views", "min_elevation_deg", "bin_ps", "fov_deg", "power", "ambient", "cycles"]
    assert min(grid["views"]) <= 16 and max(grid["views"]) >= 512
    assert max(grid["min_elevation_deg"]) >= 60 and max(grid["bin_ps"]) * 0.3 >= 66.7  # bins up to 8 cm of light
    assert min(grid["fov_deg"]) <= 10 and max(grid["fov_deg"]) >= 90
    for axis in ("power", "cycles"):
        assert max(grid[axis]) / min(grid[axis]) >= 100
    assert 0.0 in grid["ambient"]
    base = plan.spec.base
    # The base condition sits on every axis: one point serves all seven panels.
    assert all(base[axis] in values for axis, values in grid.items())
    assert len(plan.entries) == 41 and len(plan.points) == 41 - 6
    assert plan.spec.baselines.thresholds is not None and len(plan.spec.baselines.thresholds) >= 10


@pytest.mark.slow
def test_overhead_benchmark_prints_the_table(tmp_path):
    run = subprocess.run([sys.executable, str(REPO / "benchmarks" / "sweep_overhead.py"), "--skip-sweep",
                          "--noop-points", "8", "--workers", "1"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    row = next(line for line in run.stdout.splitlines() if line.startswith("| 8 no-op points"))
    serial, dask = (float(cell) for cell in row.strip("| ").split(" | ")[1:])
    assert serial > 0 and dask > 0


def test_figure_a_points_to_the_list_of_every_built_in_scene():
    """The comment on `scenes` names where every built-in scene is listed, and that list holds them all."""
    from protocol.scenes import BUILTIN_SCENES

    text = (SWEEPS / "figure_a.toml").read_text()
    comment = text[text.index("[sweep]"):text.index("scenes = ")]
    assert "`spadscan simulate --help` lists them all" in comment, comment
    run = subprocess.run([sys.executable, "-m", "spadscan.cli", "simulate", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    listed = {line.split()[0] for line in run.stdout.splitlines() if line.startswith("    ") and line.split()}
    assert set(BUILTIN_SCENES) <= listed, set(BUILTIN_SCENES) - listed
