#!/usr/bin/env python
"""Fit the simulator's sensor model to LCSPCData and report the residuals.

`lcspc-sim`: the simulated scenes (sphere, bunny; their own poses and ground-truth meshes) are fitted by Poisson
deviance with the project's own forward model (ray casting, pulse on the oversampled axis, Coates pile-up over the
known N = 5000 cycles). Free: bins per metre, zero_bin, pulse sigma and tau (exgauss), cone half-angle, signal scale,
background. Rays are cast once over a cone wider than any candidate; the half-angle then acts as a soft edge one ray
ring wide, which keeps the deviance continuous for the derivative-free (Nelder-Mead) search.

`tmf8820` (--tmf): the pulse table p(t) = [ref_n(14.27 + (t - 12.66) / 1.10)]^1.5 built from the real pyramid's
mean reference histogram (docs/sensor_models.md); with it, a loose fit of zero_bin and signal_scale to the real
pyramid's peaks and return photons (poses and table-and-pyramid STL from the dataset).

    python tools/fit_sensor.py --dataset DIR [--scenes sphere bunny] [--rays 8192] [--json out.json]

DIR is LCSPCData's folder (it holds simulated/ and real/), where it was downloaded; it is not part of the
repository.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from spadscan.protocol import pileup
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.mesh_io import load_mesh
from spadscan.protocol.raycast import first_hits, make_intersector, zone_rays
from spadscan.protocol.sensor_model import Pulse, Zone
from spadscan.protocol.transient import FineAxis, convolve_pulse

N_BINS, CYCLES, OVERSAMPLE, MAX_HALF_ANGLE_DEG = 1024, 5000, 8, 18.0
NAMES = ("bins_per_m", "zero_bin", "sigma_bins", "tau_bins", "half_angle_deg", "signal_scale", "background")


def load_scene(root: Path, scene: str):
    data = json.loads((root / "simulated" / scene / f"{scene}.json").read_text())
    hists = np.array([m["hists"] for m in data], dtype=np.float64)
    poses = np.array([m["pose"] for m in data], dtype=np.float64)
    return hists, poses, load_mesh(root / "simulated" / scene / f"{scene}.obj")


def cast(mesh, poses, n_rays: int, seed: int = 0):
    """Returns of every view over a wide cone: (view, range m, cos_i/r^2 * solid angle per ray, theta rad)."""
    rays = zone_rays((Zone(kind="cone", half_angle_rad=math.radians(MAX_HALF_ANGLE_DEG)),), n_rays, seed)
    d, w = rays.directions[0], rays.weights[0]
    dirs = np.einsum("vij,rj->vri", poses[:, :3, :3], d).reshape(-1, 3)
    origins = np.repeat(poses[:, :3, 3], len(d), axis=0)
    ray, r, cos_i = first_hits(make_intersector(mesh), mesh, origins, dirs)
    theta = np.arccos(np.clip(d[ray % len(d), 2], -1, 1))
    return ray // len(d), r, w[ray % len(d)] * cos_i / r**2, theta, theta_step(n_rays)


def theta_step(n_rays: int) -> float:
    """Angular width of one equal-area ring of rays near the cone's edge (radians)."""
    a = math.radians(MAX_HALF_ANGLE_DEG)
    return (1 - math.cos(a)) / n_rays / math.sin(a) * 64  # ~64 rays share a ring's width at the edge


def unpack(x):
    k, z0, ls, lt, a, lsig, lb = x
    return dict(bins_per_m=k, zero_bin=z0, sigma_bins=math.exp(ls), tau_bins=math.exp(lt), half_angle_deg=a,
                signal_scale=math.exp(lsig), background=math.exp(lb))


def pack(p):
    return np.array([p["bins_per_m"], p["zero_bin"], math.log(p["sigma_bins"]), math.log(p["tau_bins"]),
                     p["half_angle_deg"], math.log(p["signal_scale"]), math.log(p["background"])])


def expected_counts(p, returns, n_views: int) -> np.ndarray:
    """Expected counts (n_views, bins) of the forward model with parameters p."""
    view, r, value, theta, step = returns
    edge = np.clip((math.radians(p["half_angle_deg"]) - theta) / step + 0.5, 0.0, 1.0)
    kernel, origin = Pulse(kind="exgauss", sigma_bins=p["sigma_bins"], tau_bins=p["tau_bins"]).kernel(OVERSAMPLE)
    axis = FineAxis(N_BINS, OVERSAMPLE, 64)
    fine = axis.splat(view, p["zero_bin"] + p["bins_per_m"] * r, p["signal_scale"] * value * edge, n_views)
    rate = axis.to_bins(convolve_pulse(fine, kernel, origin)) + p["background"]
    return CYCLES * pileup.detection_probabilities(rate)


def deviance(y: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Poisson deviance per bin."""
    mu = np.maximum(mu, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(y > 0, y * np.log(y / mu), 0.0)
    return 2 * (t - (y - mu))


def nelder_mead(f, x0, steps, iters=600, tol=1e-7):
    """Minimise f from x0 with an initial simplex of the given per-coordinate steps (plain Nelder-Mead)."""
    pts = [np.asarray(x0, float)] + [np.asarray(x0, float) + np.eye(len(x0))[i] * steps[i] for i in range(len(x0))]
    vals = [f(p) for p in pts]
    for _ in range(iters):
        order = np.argsort(vals)
        pts, vals = [pts[i] for i in order], [vals[i] for i in order]
        if abs(vals[-1] - vals[0]) <= tol * (abs(vals[0]) + 1e-12):
            break
        centre = np.mean(pts[:-1], axis=0)
        refl = centre + (centre - pts[-1])
        fr = f(refl)
        if fr < vals[0]:
            exp_ = centre + 2 * (centre - pts[-1])
            fe = f(exp_)
            pts[-1], vals[-1] = (exp_, fe) if fe < fr else (refl, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = refl, fr
        else:
            con = centre + 0.5 * (pts[-1] - centre)
            fc = f(con)
            if fc < vals[-1]:
                pts[-1], vals[-1] = con, fc
            else:
                pts = [pts[0]] + [pts[0] + 0.5 * (q - pts[0]) for q in pts[1:]]
                vals = [vals[0]] + [f(q) for q in pts[1:]]
    best = int(np.argmin(vals))
    return pts[best], vals[best]


def smoothed_peak(h: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """Peak bin of each histogram (..., bins) after a Gaussian smoothing (a matched filter against shot noise)."""
    x = np.arange(-int(4 * sigma), int(4 * sigma) + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    sm = np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), -1, h)
    return sm.argmax(axis=-1)


def residuals(p, scenes) -> dict:
    """Per-scene residuals of parameters p: deviance per bin vs. its noise level, per-view peak and count errors."""
    rng = np.random.default_rng(0)
    out = {}
    for name, (hists, returns) in scenes.items():
        mu = expected_counts(p, returns, len(hists))
        dev = deviance(hists, mu).mean()
        # The deviance the model would score against its own photon draws: what "fits to noise level" means.
        probs = np.concatenate([mu / CYCLES, 1 - mu.sum(1, keepdims=True) / CYCLES], axis=1)
        noise = np.mean([deviance(rng.multinomial(CYCLES, probs)[:, :-1].astype(float), mu).mean() for _ in range(4)])
        peak = smoothed_peak(mu) - smoothed_peak(hists)
        count = mu.sum(1) / hists.sum(1) - 1
        out[name] = dict(deviance_per_bin=float(dev), noise_deviance_per_bin=float(noise),
                         peak_bin_error_mean_abs=float(np.abs(peak).mean()),
                         peak_bin_error_p95_abs=float(np.percentile(np.abs(peak), 95)),
                         count_error_rms=float(np.sqrt(np.mean(count**2))),
                         count_error_max_abs=float(np.abs(count).max()))
    return out


def fit_lcspc(root: Path, scene_names, n_rays: int, iters: int):
    start = time.monotonic()
    scenes = {}
    for name in scene_names:
        hists, poses, mesh = load_scene(root, name)
        scenes[name] = (hists, cast(mesh, poses, n_rays))
    print(f"cast {n_rays} rays x {sum(len(h) for h, _ in scenes.values())} views in {time.monotonic() - start:.1f} s",
          file=sys.stderr)
    p0 = dict(bins_per_m=800.0, zero_bin=-1.1, sigma_bins=2.0, tau_bins=3.6, half_angle_deg=15.25, signal_scale=1.1,
              background=2.48e-4)
    n_bins_total = sum(h.size for h, _ in scenes.values())

    def objective(x):
        p = unpack(x)
        if not (0.3 < p["sigma_bins"] < 10 and p["tau_bins"] < 20 and 5 < p["half_angle_deg"] < MAX_HALF_ANGLE_DEG):
            return 1e30
        return sum(deviance(h, expected_counts(p, ret, len(h))).sum() for h, ret in scenes.values()) / n_bins_total

    x, best = pack(p0), objective(pack(p0))
    print(f"start: mean deviance per bin {best:.4f}", file=sys.stderr)
    steps = np.array([2.0, 0.5, 0.1, 0.1, 0.3, 0.05, 0.05])
    for round_ in range(3):  # restarts shake Nelder-Mead out of a collapsed simplex
        x, best = nelder_mead(objective, x, steps / (round_ + 1), iters)
        print(f"round {round_}: mean deviance per bin {best:.5f} {unpack(x)}", file=sys.stderr)
    p = unpack(x)
    return p, residuals(p, scenes), time.monotonic() - start


def tmf_pulse_table(root: Path, before: int = 4, after: int = 40) -> tuple[tuple[float, ...], int]:
    """The TMF8820 pulse (docs/sensor_models.md) from the mean floor-subtracted reference of the real pyramid."""
    refs = []
    for f in sorted((root / "real" / "pyramid").glob("*.json")):
        refs += [m["reference_hist"] for m in json.loads(f.read_text())]
    ref = np.mean(np.array(refs, dtype=np.float64), axis=0)
    ref_n = np.maximum(ref - np.median(ref[:10]), 0.0)
    ref_n /= ref_n.max()
    k = np.arange(-before, after + 1)
    vals = np.interp(14.27 + k / 1.10, np.arange(ref.size), ref_n, left=0.0, right=0.0) ** 1.5
    return tuple(round(float(v), 5) for v in vals), before


def subbin_peak(h: np.ndarray) -> np.ndarray:
    """Peak bin coordinate (bin i centred at i + 0.5) of each histogram (..., bins): parabola through the argmax."""
    i = np.clip(h.argmax(axis=-1), 1, h.shape[-1] - 2)
    take = lambda k: np.take_along_axis(h, (i + k)[..., None], axis=-1)[..., 0]  # noqa: E731
    a, b, c = take(-1), take(0), take(1)
    den = a - 2 * b + c
    return i + 0.5 + np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)


def fit_tmf(root: Path, pulse_values, pulse_origin: int) -> dict:
    """Loose fit of the TMF8820 time axis and signal scale on the real pyramid (its frames, poses and STL).

    With the reference-derived pulse, the zone histograms' peaks (floor subtracted, Coates corrected) are compared
    with the model's: the mean offset moves zero_bin; the median ratio of return photons rescales signal_scale.
    """
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, Simulator

    frames = json.loads((root / "real" / "pyramid" / "pyramid.json").read_text())
    hists = np.array([m["hists"] for m in frames], dtype=np.float64)
    poses = np.array([m["pose"] for m in frames], dtype=np.float64)
    mesh = load_mesh(root / "real" / "pyramid" / "pyramid2.stl")
    sensor = sensor_preset("tmf8820").with_(pulse=Pulse(kind="table", values=tuple(pulse_values), origin=pulse_origin))
    sim = Simulator(mesh, sensor, SimSettings(rays_per_zone=2048))
    model = sim.signal_rates(poses)
    floor = np.median(hists[..., 1:10], axis=-1, keepdims=True)  # bins before zero range: background only
    rate = pileup.coates_correct(hists, sensor.cycles) * sensor.cycles  # photons per bin, pile-up undone
    rate = rate - np.median(rate[..., 1:10], axis=-1, keepdims=True)
    rate[..., 0] = 0.0  # bin 0 reads high on this sensor
    data_peak, model_peak = subbin_peak(rate), subbin_peak(model)
    err = data_peak - model_peak
    ok = model.max(axis=-1) > 0
    shift = float(np.median(err[ok]))
    ratio = rate.clip(0).sum(-1)[ok] / (sensor.cycles * model.sum(-1)[ok])
    after = err[ok] - shift
    return {"zero_bin": sensor.zero_bin + shift, "zero_bin_shift": shift,
            "peak_error_sd_bins": float(np.std(after)), "peak_within_1_bin": float(np.mean(np.abs(after) <= 1)),
            "signal_scale": float(sensor.signal_scale * np.median(ratio)),
            "signal_ratio_iqr": [float(np.percentile(ratio, 25)), float(np.percentile(ratio, 75))],
            "background_counts_per_bin": [float(np.percentile(floor, 5)), float(np.percentile(floor, 95))]}


def input_problem(args) -> str | None:
    """What the options lack, as one line, or None: checked before any fit runs (a full fit takes a long time, and a
    folder one level off gave an IndexError about the mean of no histograms)."""
    root = args.dataset
    if not root.is_dir():
        return f"dataset not found at {root}"
    hint = "(--dataset is LCSPCData's folder, the one that holds simulated/ and real/)"
    if args.tmf:
        for name in ("pyramid.json", "pyramid2.stl"):
            if not (root / "real" / "pyramid" / name).is_file():
                return f"{root / 'real' / 'pyramid' / name} not found {hint}"
    else:
        if args.rays < 1:
            return f"--rays {args.rays} must be at least 1 (rays per view over the fitting cone)"
        for scene in args.scenes:
            for suffix in (".json", ".obj"):
                path = root / "simulated" / scene / f"{scene}{suffix}"
                if not path.is_file():
                    there = sorted(p.name for p in (root / "simulated").glob("*") if p.is_dir())
                    known = f"(scenes there: {', '.join(there)})" if there else hint
                    return f"scene {scene!r}: {path} not found {known}"
    if args.json is not None and not args.json.parent.is_dir():
        return f"--json {args.json}: the folder {args.json.parent} does not exist"
    if args.json is not None and args.json.is_dir():
        return f"--json {args.json} is a folder: give the file to write"
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, required=True,
                    help="LCSPCData's folder (holds simulated/ and real/), where it was downloaded")
    ap.add_argument("--scenes", nargs="+", default=["sphere", "bunny"])
    ap.add_argument("--rays", type=int, default=8192, help="rays per view over the 18-degree fitting cone")
    ap.add_argument("--iters", type=int, default=400, help="Nelder-Mead iterations per round")
    ap.add_argument("--separate", action="store_true", help="also fit each scene on its own")
    ap.add_argument("--tmf", action="store_true", help="TMF8820: pulse table from the reference, time axis and "
                                                       "signal scale from the real pyramid; skips the lcspc fit")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args(argv)
    problem = input_problem(args)
    if problem:
        print(f"fit_sensor: {problem}", file=sys.stderr)
        return 1
    try:
        run(args)
    except (SpadscanError, OSError, ValueError) as exc:  # a damaged file of the dataset, a full disk: one line
        print(f"fit_sensor: {exc}", file=sys.stderr)
        return 1
    return 0


def run(args) -> None:
    """The fits the options ask for, printed, and written to --json when given."""
    result = {}
    if args.tmf:
        values, origin = tmf_pulse_table(args.dataset)
        result["tmf8820"] = {"pulse": {"values": values, "origin": origin}, **fit_tmf(args.dataset, values, origin)}
        print(json.dumps(result["tmf8820"]))
    else:
        groups = [args.scenes] + ([[s] for s in args.scenes] if args.separate and len(args.scenes) > 1 else [])
        for group in groups:
            p, res, secs = fit_lcspc(args.dataset, group, args.rays, args.iters)
            key = "+".join(group)
            result[key] = {"params": p, "residuals": res, "seconds": secs}
            print(json.dumps({key: result[key]}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    sys.exit(main())
