"""Seconds to score a reconstruction against its ground truth: `mesh_metrics` beside a plain KD-tree query.

    python benchmarks/metrics_speed.py [--points 300000] [--seed 0] [--repeats 1]

Scoring samples both meshes (`--points` each, one seed) and finds every sample's nearest sample on the other mesh.
The peer is the obvious exact method: scipy's cKDTree with its default build, queried with all cores. Its answers
are slow where the two surfaces are apart (a hollow the tree's boxes span), which is what a rough reconstruction
is: the cases below are the built-in goblet (`demo` scene) against its convex hull (a closed bowl, a filled stem:
what space carving gives) and against a copy pushed 3 mm along its normals with 1 mm of noise (a near miss).

Prints, per case: the seconds of each method, the largest difference of any distance (mm; both are exact, so it
must be 0) and the metrics of both to full precision (they must be equal). Other load on the machine skews the
seconds: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from unittest import mock

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.scenes import builtin_scene
from spadscan.worker import metrics
from spadscan.worker.metrics import mesh_metrics, sample_surface
from spadscan.worker.nearest import nearest_samples


class PlainIndex:
    """The peer, in `mesh_metrics`'s place of `SampleIndex`: a default cKDTree, queried with every core."""

    def __init__(self, data: np.ndarray, **_):
        self.tree = cKDTree(data)

    def build(self) -> None:
        pass

    def query(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.tree.query(queries, workers=-1)


def cases(rng: np.random.Generator) -> dict[str, tuple[trimesh.Trimesh, trimesh.Trimesh]]:
    gt = builtin_scene("demo")
    near = gt.copy()
    near.vertices = near.vertices + 0.003 * near.vertex_normals + rng.normal(0, 0.001, near.vertices.shape)
    return {"goblet vs its convex hull": (gt.convex_hull, gt), "goblet vs a 3 mm offset": (near, gt)}


def timed(fn, repeats: int):
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000, help="samples per mesh (default 300000, the metric's)")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the meshes' samples, the same for every method (default 0)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="best of this many runs per method, mesh_metrics included (default 1)")
    args = ap.parse_args(argv)
    if not 1 <= args.points <= metrics.MAX_POINTS or args.repeats < 1 or args.seed < 0:
        ap.error(f"--points must be in [1, {metrics.MAX_POINTS}] (the metric's), --repeats >= 1 and --seed >= 0")
    try:
        compare(args)
    except SpadscanError as exc:  # the metric refuses what it is given: one line, not a traceback
        raise SystemExit(f"{ap.prog}: error: {exc}") from None


def compare(args) -> None:
    """Both methods on every case, printed."""
    print(f"{args.points} samples per mesh, seed {args.seed}, load average {os.getloadavg()[0]:.2f}")
    for name, (pred, gt) in cases(np.random.default_rng(1)).items():
        rs, rg = (np.random.default_rng(s) for s in np.random.SeedSequence(args.seed).spawn(2))
        p_pts, _ = sample_surface(pred, args.points, rs)
        g_pts, _ = sample_surface(gt, args.points, rg)
        t_ours, (d_ours, _) = timed(lambda: nearest_samples(p_pts, g_pts, spacing_m=math.sqrt(gt.area / args.points)),
                                    args.repeats)
        t_peer, (d_peer, _) = timed(lambda: PlainIndex(g_pts).query(p_pts), args.repeats)
        t_m_ours, m_ours = timed(lambda: mesh_metrics(pred, gt, n_points=args.points, seed=args.seed),
                                 args.repeats)
        with mock.patch.object(metrics, "SampleIndex", PlainIndex):
            t_m_peer, m_peer = timed(lambda: mesh_metrics(pred, gt, n_points=args.points, seed=args.seed),
                                     args.repeats)
        print(f"\n{name}")
        print(f"  reconstruction -> ground truth: nearest_samples {t_ours:6.2f} s   plain cKDTree {t_peer:6.2f} s   "
              f"largest difference {np.max(np.abs(d_ours - d_peer)) * 1e3:.3g} mm")
        print(f"  mesh_metrics (both ways):       nearest_samples {t_m_ours:6.2f} s   plain cKDTree {t_m_peer:6.2f} s")
        for (key, value), other in zip(m_ours.to_dict().items(), m_peer.to_dict().values()):
            print(f"    {key:18s} {value!r:>24}  {other!r:>24}  {'equal' if value == other else 'DIFFERENT'}")


if __name__ == "__main__":
    sys.exit(main())
