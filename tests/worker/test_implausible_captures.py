"""A capture whose counts no sensor could produce is refused in one line by `spadscan reconstruct`, `spadscan
baseline` and the worker's jobs (it used to reconstruct with exit status 0 and every loss term 0); a capture with
only some such histograms is reconstructed with a one-line warning that its results keep."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import check_capture_counts
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.recon.forward import ModelTerms, TransientForward
from spadscan.worker.recon.scene_data import load_scene
from spadscan.worker.reconstruct import run_config, set_up_run
from spadscan.worker.worker_config import WorkerConfig

SATURATED = 2**32 - 1


def capture(path, counts: np.ndarray, preset: str = "lcspc-sim"):
    """A complete capture of `counts` (views, zones, bins) looking at the origin from a hemisphere."""
    sensor = sensor_preset(preset)
    poses = fibonacci_hemisphere(len(counts), 0.3, target=(0, 0, 0.0), min_elevation_deg=10)
    w = CaptureWriter.create(path, sensor, chunk_size=8)
    for i, (h, pose) in enumerate(zip(counts, poses)):
        ref = np.full(sensor.n_bins, 50, np.uint32) if sensor.has_reference else None
        w.append(Measurement(h, pose, i, reference=ref))
    w.finish("complete")
    return path


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("preset, shape", [("lcspc-sim", (8, 1, 1024)), ("tmf8820", (8, 9, 128))])
def test_reconstruct_refuses_a_capture_whose_every_count_is_the_uint32_maximum(tmp_path, capsys, preset, shape):
    cap = capture(tmp_path / "cap", np.full(shape, SATURATED, np.uint32), preset)
    assert cli_main(["reconstruct", str(cap), "--out", str(tmp_path / "out"), "--steps", "2", "--device", "cpu",
                     "--no-progress"]) == 1
    err = one_line_error(capsys)
    assert err.startswith(f"spadscan: error: {cap}: no sensor could have produced these counts: all ") and (
        "saturated" in err if preset == "lcspc-sim" else "above the 24-bit counter's limit" in err)
    assert not (tmp_path / "out" / "mesh.ply").exists()


@pytest.mark.parametrize("method, count, words", [
    ("reprojection", 0, "are all zero"), ("space-carving", 0, "are all zero"),
    ("space-carving", 2**24 - 1, "are saturated (every bin at the 24-bit counter's limit 16,777,215)")])
def test_baselines_refuse_a_capture_no_sensor_could_produce(tmp_path, capsys, method, count, words):
    cap = capture(tmp_path / "cap", np.full((8, 9, 128), count, np.uint32), "tmf8820")
    assert cli_main(["baseline", method, str(cap), "--out", str(tmp_path / "out"), "--no-gt"]) == 1
    assert one_line_error(capsys) == (f"spadscan: error: {cap}: no sensor could have produced these counts: all 72 "
                                      f"histograms {words}; refusing to fit them")


def counts_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that leaves a report (the counts were checked before it is called)."""
    report = {"preset": preset}
    (out / "report.json").write_text(json.dumps(report))
    return report


def warning_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                  started=None):
    """A stand-in reconstruction whose report carries the counts note among its warnings, as reconstruct's does."""
    report = {"preset": preset, "warnings": [check_capture_counts(capture)]}
    (out / "report.json").write_text(json.dumps(report))
    return report


@pytest.mark.usefixtures("recon_stand_ins")
def test_the_done_line_says_a_counts_warning_once(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    some = np.random.default_rng(0).poisson(2.0, (8, 1, 1024)).astype(np.uint32)
    some[3] = SATURATED
    capture(root / "some", some)
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_implausible_captures:warning_recon")
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"some-fast": "done"}
    done = [line for line in lines if "some-fast done" in line]
    assert len(done) == 1 and done[0].count("1 of 8 histograms no sensor could have produced") == 1, done


@pytest.mark.usefixtures("recon_stand_ins")
def test_the_worker_fails_an_implausible_capture_once_and_warns_about_a_partly_implausible_one(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    rng = np.random.default_rng(0)
    capture(root / "flat", np.full((8, 1, 1024), 7, np.uint32))
    some = rng.poisson(2.0, (8, 1, 1024)).astype(np.uint32)
    some[3] = SATURATED
    capture(root / "some", some)
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_implausible_captures:counts_recon")
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"flat-fast": "failed", "some-fast": "done"}
    rows = {r.id: r for r in Queue.for_root(root).statuses()}
    assert rows["flat-fast"].attempts == 1, "bad input is not retried"
    assert rows["flat-fast"].error == (f"{root / 'flat'}: no sensor could have produced these counts: all 8 "
                                       "histograms have every bin equal; refusing to fit them")
    note = (f"{root / 'some'}: 1 of 8 histograms no sensor could have produced (1 saturated (every bin at the 32-bit "
            "counter's limit 4,294,967,295)), left out")
    result = root / "some" / "recon" / "some-fast"
    assert json.loads((result / "report.json").read_text())["capture_counts_note"] == note
    assert f"warning: {note}" in (result / "job.log").read_text()
    assert any(line.startswith("some-fast done") and f"\n  warning: {note}" in line for line in lines), lines


def test_a_dropped_frame_is_left_out_and_carves_nothing_away(tmp_path):
    """One all-zero histogram among 16 (a dropped frame): read as "no return", it proved its zone's whole field of
    view empty, and the hull kept a third of the ball (the fit cannot grow past the hull); the likelihood read it so
    too."""
    poses = fibonacci_hemisphere(16, 0.5, target=(0, 0, 0.1), min_elevation_deg=0)
    cap = simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=1024), progress=False)
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    counts[3] = 0
    np.save(hists, counts)
    scene = load_scene(cap)
    assert not scene.usable[3].any() and scene.usable[[2, 4]].all() and not scene.valid[3].any()
    run = set_up_run(cap, run_config("fast", {}), torch.device("cpu"), steps=1, budget_s=None, seed=0,
                     log=lambda line: None)
    rng = np.random.default_rng(0)
    ball = rng.uniform(-1, 1, (50_000, 3))
    ball = torch.as_tensor(ball[np.linalg.norm(ball, axis=1) < 1] * 0.1 + [0, 0, 0.1], dtype=torch.float32)
    assert float((run.model.problem.hull.sample(ball) < 0).float().mean()) > 0.97
    # Nor does it pull the fit: the data term and its gradient over views 2-4 are those of views 2 and 4 alone. With
    # pile-up its "no photon in any of N cycles" term told the fit that the zone saw nothing.
    problem = run.model.problem
    assert problem.forward.terms.pileup
    views, kept = torch.tensor([2, 3, 4]), torch.tensor([0, 2])
    lam = run.model._rates(views)[0].detach().requires_grad_(True)
    loss = problem.forward.nll(lam, problem.counts[views], problem.cycles[views], problem.valid[views])
    (grad,) = torch.autograd.grad(loss, lam)
    alone = lam.detach()[kept].requires_grad_(True)
    loss_kept = problem.forward.nll(alone, problem.counts[views[kept]], problem.cycles[views[kept]],
                                    problem.valid[views[kept]])
    (grad_kept,) = torch.autograd.grad(loss_kept, alone)
    assert float(loss.detach()) == pytest.approx(float(loss_kept.detach()), rel=1e-6)
    assert float(grad[1].abs().max()) == 0.0
    torch.testing.assert_close(grad[kept], grad_kept, rtol=1e-6, atol=0.0)
    # The space-carving baseline reads the same capture: its mesh is the ball, not what one dead zone left of it.
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(tmp_path / "carved")]) == 0
    carved = trimesh.load(tmp_path / "carved" / "mesh.ply")
    assert carved.contains(ball.numpy().astype(np.float64)).mean() > 0.97


def test_a_dropped_frame_carves_as_if_it_were_not_there(tmp_path):
    """Space seen by too few views is dropped (min_views): a view whose histograms hold no data saw nothing and must
    not count as one that looked, so the hull with the dropped view is the hull without it."""
    from spadscan.worker.carving.space_carving import carve_hull

    poses = fibonacci_hemisphere(8, 0.4, target=(0, 0, 0.1), min_elevation_deg=20)
    sensor = sensor_preset("lcspc-sim")
    cap = simulate_capture(builtin_scene("sphere"), sensor, poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=256), progress=False)
    counts = np.load(cap / "chunk-000000" / "hists.npy").astype(np.float64)
    usable = np.ones(counts.shape[:2], bool)
    usable[5] = False
    box = {"bounds_min": [-0.2, -0.2, -0.05], "bounds_max": [0.2, 0.2, 0.35], "resolution": 32, "min_views": 3}
    with_dropped = carve_hull(counts, poses, sensor, usable=usable, **box).occupancy
    keep = np.arange(len(poses)) != 5
    without = carve_hull(counts[keep], poses[keep], sensor, **box).occupancy
    assert with_dropped.sum() > 0
    np.testing.assert_array_equal(with_dropped, without)


def test_a_histogram_with_more_counts_than_its_cycles_is_left_out_of_the_fit(tmp_path):
    """One bin of one histogram raised to 50,000 in a 5,000-cycle capture: a first-photon sensor counts at most one a
    cycle, so no sensor produced it. Fitted, it pulled the albedo down and 11 of the 24 histograms misfit; it is left
    out as an all-zero one is (no valid bin, not a usable histogram), and the others are kept as they were."""
    poses = fibonacci_hemisphere(8, 0.5, target=(0, 0, 0.1), min_elevation_deg=0)
    cap = simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=64), progress=False)
    before = load_scene(cap)
    assert before.usable.all()
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    assert counts.sum(axis=-1).max() < 5000
    counts[5, 0, 500] = 50_000
    np.save(hists, counts)
    scene = load_scene(cap)
    assert scene.usable[:, 0].tolist() == [True] * 5 + [False] + [True] * 2
    assert not scene.valid[5].any()
    torch.testing.assert_close(scene.valid[[0, 1, 2, 3, 4, 6, 7]], before.valid[[0, 1, 2, 3, 4, 6, 7]])


def test_a_bin_clipped_at_the_counters_limit_is_left_out_of_everything_the_fit_reads(tmp_path):
    """Bin 500 of every histogram at 2**32-1 (a clipped bin: the histograms' other bins are fitted). It was masked
    out of the bins' terms only: the fit's "no photon" term read it as every cycle having seen a photon, and the
    scene's bound took it for every view's return (a 0.40 m sphere 11 cm low); 50 steps fitted a sphere 115 mm off
    instead of 56. Now the scene, its bound and the fit's loss are the clean capture's."""
    poses = fibonacci_hemisphere(16, 0.5, target=(0, 0, 0.1), min_elevation_deg=0)
    sensor = sensor_preset("lcspc-sim")
    cap = simulate_capture(builtin_scene("sphere"), sensor, poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=64), progress=False)
    clean = load_scene(cap)
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    counts[:, :, 500] = SATURATED
    np.save(hists, counts)
    clipped = load_scene(cap)
    assert clipped.usable.all() and not clipped.valid[..., 500].any() and clipped.valid[..., :500].all()
    assert float(clipped.counts[..., 500].abs().max()) == 0.0
    torch.testing.assert_close(clipped.center, clean.center)
    assert clipped.radius == pytest.approx(clean.radius)
    forward = TransientForward(sensor, ModelTerms(True, False, False, False, False),
                               torch.tensor(sensor.pulse.kernel(1)[0]), sensor.pulse.kernel(1)[1], 1)
    lam = torch.full(clean.counts.shape, 2.5e-4)
    lam[..., 300] = 0.3
    mask = clean.valid.clone()
    mask[..., 500] = False
    # Bin 500 of the clean capture holds 0-2 counts: left out, its loss moves by a count's worth, not by the cycles'.
    assert float(forward.nll(lam, clipped.counts, clipped.cycles, clipped.valid)) == pytest.approx(
        float(forward.nll(lam, clean.counts, clean.cycles, mask)), rel=0.01)


def test_a_simulated_histogram_over_its_exact_cycles_is_left_out_of_the_fit(tmp_path):
    """This project's simulator knows its cycles exactly: one histogram at 1.2 x them (within the 1.5 x margin that
    covers a real sensor's estimated cycles) is corrupt, and the fit leaves it out as the reader's warning says."""
    poses = fibonacci_hemisphere(8, 0.5, target=(0, 0, 0.1), min_elevation_deg=0)
    cap = simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=64), progress=False)
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    counts[3, 0, 700] += 6000 - counts[3, 0].sum()  # 6,000 counts over 5,000 cycles
    np.save(hists, counts)
    assert "1 of 8 histograms" in (check_capture_counts(cap) or "")
    assert load_scene(cap).usable[:, 0].tolist() == [True] * 3 + [False] + [True] * 4


def test_reconstruct_refuses_a_capture_whose_every_histogram_holds_more_counts_than_its_cycles(tmp_path, capsys):
    """Every histogram over what a first-photon sensor's cycles allow: nothing is left to fit, and the run says why
    in one line (not that carving found no return)."""
    counts = np.random.default_rng(0).poisson(2.0, (8, 1, 1024)).astype(np.uint32)
    counts[:, 0, 300] = 50_000
    cap = capture(tmp_path / "cap", counts)
    with pytest.raises(CaptureError, match="all 8 histograms hold more counts than 1.5 x their 5,000 laser cycles"):
        load_scene(cap)
    assert cli_main(["reconstruct", str(cap), "--out", str(tmp_path / "out"), "--steps", "1", "--no-progress"]) != 0
    err = one_line_error(capsys)
    assert "no sensor could have produced these counts" in err and "5,000 laser cycles" in err, err
    assert not (tmp_path / "out" / "mesh.ply").exists()


def test_the_counts_warning_names_the_histograms_over_their_cycles(tmp_path):
    """The warning a run prints and the worker's job keeps names the histograms the fit leaves out for holding more
    counts than their cycles allow (the fit and the baselines leave them out alike)."""
    counts = np.random.default_rng(0).poisson(2.0, (8, 1, 1024)).astype(np.uint32)
    counts[5, 0, 300] = 50_000
    cap = capture(tmp_path / "cap", counts)
    assert check_capture_counts(cap) == (f"{cap}: 1 of 8 histograms no sensor could have produced (1 with more "
                                         "counts than 1.5 x their 5,000 laser cycles), left out")


def test_reconstruct_prints_a_counts_warning_once(tmp_path, capsys):
    """The warning is printed when the capture is loaded; the end of run's warnings, which report.json keeps, do not
    print it again."""
    poses = fibonacci_hemisphere(8, 0.5, target=(0, 0, 0.1), min_elevation_deg=0)
    cap = simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=64), progress=False)
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    counts[[1, 6]] = 0
    np.save(hists, counts)
    out = tmp_path / "out"
    assert cli_main(["reconstruct", str(cap), "--out", str(out), "--steps", "5", "--threads", "1", "--no-gt",
                     "--no-progress"]) == 0
    said = "2 of 8 histograms no sensor could have produced (2 all zero), left out"
    assert capsys.readouterr().err.count(said) == 1
    assert sum(said in line for line in json.loads((out / "report.json").read_text())["warnings"]) == 1
