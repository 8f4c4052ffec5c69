"""Absurd inputs to eval and simulate, through the real command in a fresh process: a one-line error or a result that
says it may be coarse, in seconds, never a run that goes on for good."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import trimesh

SPADSCAN = [sys.executable, "-m", "spadscan.cli"]


def spadscan(*args, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """The command run to its end in a fresh process; a run that outlasts `timeout` fails the test."""
    return subprocess.run([*SPADSCAN, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def one_line_error(done: subprocess.CompletedProcess) -> str:
    """The error line of a refused command: exit status 1, nothing on stdout, one line on stderr."""
    assert done.returncode == 1 and done.stdout == "" and done.stderr.count("\n") == 1, done
    assert done.stderr.startswith("spadscan: error: "), done.stderr
    return done.stderr.strip()


def sphere_obj(path, radius: float, centre=(0.0, 0.0, 0.1)):
    """An icosphere as OBJ text, its coordinates written with every digit (no export rounding or overflow)."""
    unit = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    vertices = unit.vertices * radius + np.asarray(centre)
    lines = ["v %r %r %r" % tuple(float(x) for x in v) for v in vertices]
    path.write_text("\n".join(lines + ["f %d %d %d" % tuple(f + 1) for f in unit.faces]) + "\n")
    return path


def test_eval_against_a_ground_truth_1e17_m_across_is_refused_at_once(tmp_path):
    """It ran for good: its samples, 1e16 m from a reconstruction at its centre, are all equally near it."""
    gt = sphere_obj(tmp_path / "gt.obj", 1e19, centre=(0.0, 0.0, 0.0))  # millimetres by its size: 2e16 m across
    err = one_line_error(spadscan("eval", "builtin:sphere", "--gt", gt))
    assert "m across (read as millimetres)" in err and "check its units" in err, err


def test_eval_of_an_stl_with_an_infinite_vertex_prints_its_error_line_alone(tmp_path):
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    vertices = ball.vertices.copy()
    vertices[0] = np.inf
    with np.errstate(all="ignore"):  # the export's own normals
        trimesh.Trimesh(vertices, ball.faces, process=False).export(tmp_path / "inf.stl")
    err = one_line_error(spadscan("eval", tmp_path / "inf.stl", "--gt", "builtin:sphere", "--points", 2000))
    assert err == f"spadscan: error: {tmp_path / 'inf.stl'}: has non-finite vertex coordinates"


def test_eval_of_a_mesh_1e200_m_across_says_so(tmp_path):
    huge = sphere_obj(tmp_path / "huge.obj", 1e199)
    err = one_line_error(spadscan("eval", huge, "--gt", "builtin:sphere", "--points", 2000))
    assert "m across" in err and "degenerate" not in err, err


def test_eval_refuses_too_few_points_and_says_the_range():
    err = one_line_error(spadscan("eval", "builtin:sphere", "--gt", "builtin:sphere", "--points", 1))
    assert "--points 1 must be in [1000, 20000000]" in err, err
    assert "1000 to 20000000" in " ".join(spadscan("eval", "--help").stdout.split())


def test_eval_of_a_mesh_inside_a_much_larger_one_ends_within_its_budget_and_says_it_measured_less(tmp_path):
    """A 1 m ball around the 20 cm sphere: its exact nearest samples took minutes at 300,000 points."""
    gt = sphere_obj(tmp_path / "gt.obj", 1.0)
    done = spadscan("eval", "builtin:sphere", "--gt", gt, "--points", 100_000, "--budget-s", 0.01)
    assert done.returncode == 0, done.stderr
    measured = [line for line in done.stdout.splitlines() if line.startswith("measured ")]
    assert measured and "500 of the 100,000 samples per mesh within --budget-s 0.01" in measured[0], done.stdout


def test_simulate_refuses_too_few_laser_cycles_and_names_the_minimum(tmp_path):
    """One cycle left every histogram empty or one count, which reconstruct then refused."""
    err = one_line_error(spadscan("simulate", "builtin:sphere", "--views", 4, "--cycles", 1, "--out", tmp_path / "cap",
                                  "--no-progress"))
    assert "--cycles 1" in err and "at least 100" in err, err
    assert not (tmp_path / "cap").exists()


def test_worker_times_out_of_range_name_the_range(tmp_path):
    """`--poll-s 1e6` and `--lease-s inf` were refused as "must be > 0"."""
    (tmp_path / "caps").mkdir()
    for option, value, said in (("--poll-s", "1000000", "poll 1000000.0 s"), ("--lease-s", "inf", "lease inf s"),
                                ("--poll-s", "0", "poll 0.0 s")):
        err = one_line_error(spadscan("worker", "--root", tmp_path / "caps", option, value, "--once"))
        assert err == f"spadscan: error: {said} must be a finite number of seconds over 0 and under 1e+06", err
