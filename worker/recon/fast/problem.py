"""Everything the fast model fits, built from a SceneData: counts, sensor model, candidate rays, hull, table.

The hull comes from the space carving the baselines share (`worker.carving.carve_scene`) inside the scene's box; the
SDF grid's box is the hull's bounding box plus a few voxels. With a table (named by the capture, or detected in the
histograms of a measured capture) the carving and the object stay above it, and the plane is rendered exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from spadscan.protocol.raycast import zone_rays

from ...carving.returns import RESCAN, below_default_level, first_returns
from ...carving.space_carving import MIN_VIEWS, carve_scene
from ...carving.view_subset import spread_views
from ...carving.views import summed_by_cycles
from ...table_height import RAYS_PER_ZONE, detect_height
from ..errors import ReconstructionError
from ..forward import TransientForward
from .grid_field import GridField
from .hull import hull_field, object_hull, returns_box


HELD_SHARE = 0.5
"""Share of the first-return points that must lie in the scene box and above the floor for carving's failure to be
put down to a thin or faint object rather than to the box or the floor. A 6 mm rod 20 cm tall, 83 % of whose 193
returns lay in a box that held its lowest 6 cm, was carved away by the views that missed it in that box and in one
that held it all (99 %); lowering the carving thresholds kept it."""


@dataclass
class FastProblem:
    """What the model fits, as tensors on the model's device. V views, Z zones, B bins, D candidate rays per zone.

    counts (V, Z, B), cycles (V,), valid (V, Z, B) bool, background (V, Z) per bin per cycle, poses (V, 4, 4);
    zone_dirs (Z, D, 3) and zone_weights (Z, D): candidate directions (sensor frame) and steradians;
    forward: the shared TransientForward; hull: the carved hull's SDF (GridField, negative inside);
    floor_z: nothing solid below this height (metres) or None; box: (min (3,), max (3,)) of the SDF grid;
    notes: what was decided, for the report;
    measured: real sensor data, not simulated.
    """

    counts: torch.Tensor
    cycles: torch.Tensor
    valid: torch.Tensor
    background: torch.Tensor
    poses: torch.Tensor
    zone_dirs: torch.Tensor
    zone_weights: torch.Tensor
    forward: TransientForward
    hull: GridField
    floor_z: float | None
    box: tuple[np.ndarray, np.ndarray]
    table_plane: tuple[np.ndarray, float, bool] | None = None
    """(normal (3,), offset, fitted) of the table, or None."""
    notes: dict = field(default_factory=dict)
    measured: bool = False
    """The histograms come from a real sensor (the capture's `real` flag), not from a simulator."""
    setup_views: torch.Tensor | None = None
    """(k,) long: the evenly spread views (`view_subset`) that the set-up's O(views x cells) stages read of a large
    capture (carving, the empty-space weights), or None for all. Training reads every view: its steps sample a fixed
    number of views, so only the set-up grew with them (a 2000-view capture made one step in a 120 s budget)."""


def candidate_rays(sensor, per_sr: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(dirs (Z, D, 3), weights (Z, D)) spread evenly over each zone, D = per_sr x the largest zone's solid angle."""
    solid = max(z.solid_angle_sr() for z in sensor.zones)
    n = max(16, int(math.ceil(per_sr * solid)))
    zr = zone_rays(sensor.zones, n, seed)
    return zr.directions, zr.weights


def _table_plane(scene, forward_kernel):
    """(normal, offset, fitted, source) of the table, or None.

    A plane the capture fixes is used as given. A fitted horizontal table (the capture says only that there is
    one) starts where `table_height.detect_height` finds it in the histograms, else where the scene data put it."""
    t = scene.table
    if t is None:
        return None
    normal = np.asarray(t.normal, float)
    if not t.fitted or abs(normal[2]) < 0.99:
        return normal, float(t.offset), bool(t.fitted), "capture"
    kernel, origin = forward_kernel
    rays = zone_rays(scene.sensor.zones, RAYS_PER_ZONE, 0)
    h = detect_height(scene.counts.double().cpu().numpy(), scene.cycles.double().cpu().numpy(),
                      scene.background.double().cpu().numpy(), scene.poses.double().cpu().numpy(),
                      rays.directions, rays.weights, scene.sensor, np.asarray(kernel, float), origin,
                      ignore_bins=scene.sensor.ignore_bins)
    if h is None:
        return normal, float(t.offset), True, "fitted from the scene data's start"
    return np.array([0.0, 0.0, 1.0]), h * float(np.sign(normal[2])), True, "detected, then fitted"


def build_problem(scene, config, device, terms, keep_setup_views=None) -> FastProblem:
    """Assemble a FastProblem from a SceneData and the resolved config (see the module docstring).
    keep_setup_views: indices of the views the last set-up of this capture read (as it then stood), which the
    subset of a large capture keeps (`view_subset.spread_views`), or None: a live fit's rebuilds then carve from
    nearly the same views each time."""
    fc, sc = config.field, config.schedule
    f32 = dict(device=device, dtype=torch.float32)
    sensor = scene.sensor
    kernel, origin = scene.pulse(config.time_oversample)
    forward = TransientForward(sensor, terms, torch.as_tensor(kernel, dtype=torch.float32), origin,
                               config.time_oversample).to(device)
    dirs, weights = candidate_rays(sensor, sc.candidate_rays_per_sr, 0)
    table = _table_plane(scene, scene.pulse(1))
    floor_z, floor_source = fc.floor_z, "config"
    if isinstance(scene.scene.get("floor_z"), (int, float)):
        floor_z, floor_source = float(scene.scene["floor_z"]), "capture"
    if table is not None and abs(table[0][2]) > 0.99:
        floor_z, floor_source = table[1] / table[0][2], "table"
    notes = {"table": None if table is None else table[3], "floor": floor_source}
    counts_np, carve_sensor = _carving_views(scene)
    poses_np = scene.poses.double().cpu().numpy()
    setup = _setup_views(poses_np, scene, keep_setup_views)
    hull_res = _carve(scene, counts_np, poses_np, carve_sensor, fc, floor_z, on_table=table is not None,
                      views=setup)
    if setup is not None:
        notes["setup_views"] = int(len(setup))
    voxel = float(np.min(hull_res.voxel_m))
    occ = np.transpose(hull_res.occupancy, (2, 1, 0))  # (x, y, z) -> (z, y, x)
    onset = first_returns(counts_np, carve_sensor, fc.carve_threshold, "leading").onset_range_m(carve_sensor)
    if scene.usable is not None:
        onset = np.where(_usable(scene), onset, np.nan)  # no information, not "no return"
    if table is None:  # on a table the piece vote bought nothing: the real pyramid 4.58 -> 4.56 mm without it
        occ = object_hull(occ, hull_res.origin, voxel, poses_np, dirs, onset, min_views=fc.hull_min_votes)
        if fc.hull_returns_pad_m is not None:
            whole = int(occ.sum())
            occ = returns_box(occ, hull_res.origin, voxel, poses_np, dirs, onset, fc.hull_returns_pad_m)
            notes["hull_cut_to_returns"] = 1.0 - int(occ.sum()) / max(whole, 1)
    if not occ.any():
        points = _return_points(onset, poses_np, dirs, weights)
        weak = carve_weak_threshold(fc, table is not None)
        lowered = below_default_level(fc.carve_threshold, weak, *default_thresholds(fc, table is not None))
        raise ReconstructionError(_nothing_left(points, hull_res, floor_z, fc.carve_threshold, weak, lowered))
    hull = hull_field(occ, hull_res.origin, voxel, device)
    idx = np.argwhere(occ)[:, ::-1]  # (x, y, z)
    lo = hull_res.origin + idx.min(axis=0) * voxel
    hi = hull_res.origin + idx.max(axis=0) * voxel
    size = float(np.max(hi - lo))
    pad = fc.box_pad_voxels * size / max(1, fc.resolution - 1) + fc.hull_margin_m
    lo, hi = lo - pad, hi + pad
    notes.update({"hull_voxel_mm": voxel * 1e3, "hull_box_min_m": lo.tolist(), "hull_box_max_m": hi.tolist(),
                  "hull_occupied_voxels": int(occ.sum())})
    return FastProblem(
        counts=scene.counts.to(**f32), cycles=scene.cycles.to(**f32), valid=scene.valid.to(device),
        background=scene.background.to(**f32), poses=scene.poses.to(**f32),
        zone_dirs=torch.as_tensor(dirs, **f32), zone_weights=torch.as_tensor(weights, **f32), forward=forward,
        hull=hull, floor_z=floor_z, box=(lo, hi),
        table_plane=None if table is None else (table[0], table[1], table[2]), notes=notes,
        measured=bool(scene.real),
        setup_views=None if setup is None else torch.as_tensor(setup, device=device, dtype=torch.long))


def _setup_views(poses: np.ndarray, scene, keep=None) -> np.ndarray | None:
    """Indices of the evenly spread views (`view_subset.spread_views`, keeping `keep` where it can) that the set-up's
    O(views x cells) stages read of a large capture, or None where that is all of them (a capture of up to
    MAX_SETUP_VIEWS views)."""
    picked = spread_views(poses, usable=_usable(scene), keep=keep)
    return None if len(picked) == len(poses) else picked


def carve_box(scene, floor_z: float | None) -> np.ndarray:
    """(2, 3) box (metres) the hull is carved in: the scene sphere's box, reaching down to the floor.

    An object stands on its floor (the table), so the box must reach it: the scene sphere is centred on the first
    returns, which a tall object puts high up, and its box cut the lower 17 cm off a simulated 50 cm head on a can."""
    box = scene.box.double().cpu().numpy().copy()
    if floor_z is not None and floor_z < box[1, 2]:
        box[0, 2] = min(box[0, 2], floor_z)
    return box


def carve_keep_returns_m(scene, fc) -> float:
    """How far beyond a first return carving keeps space that few views see (`field.carve_keep_returns_m`): on
    simulated captures only. On the real pyramid it kept 15 % more hull, all of it air 4-26 cm above the table where
    the real zones' onsets do not mark the object (step-based 4.51 mm against 4.41)."""
    return 0.0 if scene.real else fc.carve_keep_returns_m


def carve_weak_threshold(fc, on_table: bool) -> float | None:
    """The level of faint runs of bins that stop carving (`field.carve_weak_threshold`), or None on a table (the
    carving's own default level, as before the setting existed). With it on a table, the simulated head on a can's
    hull grew by 1.1 % and its fit stood on a skirt round the can's base (1.22 -> 1.79 mm; its lowest 6 cm 33 % over
    5 mm off); the tall block 0.83 -> 0.85, the real pyramid's hull and fit unchanged."""
    return None if on_table else fc.carve_weak_threshold


def default_thresholds(fc, on_table: bool) -> tuple[float, float | None]:
    """(carving threshold, weak threshold or None) as carving is given them (`carve_weak_threshold`) with the
    defaults of `fc`'s config: what `returns.below_default_level` compares the thresholds in effect with."""
    shipped = type(fc)()
    return shipped.carve_threshold, carve_weak_threshold(shipped, on_table)


def _return_points(onset: np.ndarray, poses: np.ndarray, zone_dirs: np.ndarray, zone_weights: np.ndarray):
    """(n, 3) world points (metres) of the first returns: each detected histogram's onset range (onset (V, Z), NaN
    where none) along its zone's mean direction (zone_dirs (Z, D, 3) sensor frame, zone_weights (Z, D) steradians)
    from its view's pose (V, 4, 4)."""
    centre = np.einsum("zd,zdi->zi", zone_weights, zone_dirs)
    centre /= np.linalg.norm(centre, axis=1, keepdims=True)
    v, z = np.nonzero(np.isfinite(onset))
    along = np.einsum("nij,nj->ni", poses[v, :3, :3], centre[z])
    return poses[v, :3, 3] + along * onset[v, z][:, None]


def _lower_thresholds(threshold: float, weak: float | None) -> tuple[float, float | None] | None:
    """Carving thresholds (noise deviations) two lower than `threshold` and `weak` (None: not in effect), never under
    2 and 1 (nearer the noise, carving stops at noise; the config takes a weak one of 1 up to the other) nor raised;
    None when they are that low already."""
    lower = min(threshold, max(2.0, threshold - 2.0))
    lower_weak = None if weak is None else max(1.0, min(weak - 2.0, lower))
    return None if (lower, lower_weak) == (threshold, weak) else (lower, lower_weak)


def _thin_advice(threshold: float, weak: float | None, lowered: bool = False) -> str:
    """What to lower when views that missed a faint return carved the object away: the thresholds in effect, their
    values now, and a `spadscan reconstruct --set` of lower ones. `weak` None: not in effect (on a table), so not
    named, but set along at the other's value, since the config refuses a weak threshold above the other.
    `lowered`: they put carving's level below its default already (`returns.below_default_level`, the rule the end
    of the run judges by too); nothing lower is offered then, since there noise clears them (a 6 mm wand 10 cm
    tall refitted at 3 and 2 was carved away again, at 2 and 1 fitted to noise: 37.6 mm)."""
    keys = [("field.carve_threshold", threshold)] + ([] if weak is None else [("field.carve_weak_threshold", weak)])
    now = " and ".join(f"{k} = {v:g}" for k, v in keys) + " noise deviations"
    if lowered:
        return (f"the detection thresholds {now} put carving's level below its default already, where noise passes "
                f"for returns: {RESCAN}")
    lower = _lower_thresholds(threshold, weak)
    if lower is None:
        return f"the detection thresholds {now} are as low as they go: capture more frames per pose"
    lower_threshold, lower_weak = lower
    sets = (f"--set field.carve_threshold={lower_threshold:g} --set field.carve_weak_threshold="
            f"{lower_threshold if lower_weak is None else lower_weak:g}")
    return (f"lower the detection threshold{'s' if len(keys) > 1 else ''} {now}: run `spadscan reconstruct` on "
            f"the capture with {sets}; a fit that is then mostly noise says 'faint returns' at its end, and the "
            f"capture needs you to {RESCAN}")


def _nothing_left(points: np.ndarray, hull_res, floor_z: float | None, threshold: float,
                  weak: float | None, lowered: bool = False) -> str:
    """Why carving left nothing, in one line, from the first-return points (n, 3) metres (`_return_points`): no return
    at all; returns that the scene box or the floor lost (most lie outside the box or under the floor: a box off the
    object, a floor above it); else a thin or faint object, carved away by the views that missed its return
    (`HELD_SHARE`): lower carving thresholds (`threshold`, `weak` as carving used them, None: not in effect), unless
    `lowered` carving's level below its default already (`_thin_advice`)."""
    found = len(points)
    if not found:
        return (f"space carving removed everything: no histogram shows a return above the threshold ({threshold:g} "
                f"noise deviations) inside the scene box")
    cell_mm = float(np.max(hull_res.voxel_m)) * 1e3
    lo, hi = np.asarray(hull_res.bounds_min, float), np.asarray(hull_res.bounds_max, float)
    # Onsets lie in front of the surface, so a return on the floor sits on it or above: a cell's slack is enough.
    above = np.ones(found, bool) if floor_z is None else points[:, 2] >= floor_z - cell_mm * 1e-3
    held = int(np.sum(np.all((points >= lo) & (points <= hi), axis=1) & above))
    floor = "none" if floor_z is None else f"z = {floor_z:.3f} m"
    where = (f"the scene box {np.round(lo, 3).tolist()} .. {np.round(hi, 3).tolist()} m ({cell_mm:.0f} mm cells) "
             f"and above the floor ({floor})")
    spread_mm = float(np.ptp(points, axis=0).max()) * 1e3 if found > 1 else 0.0
    shown = f"{found} histograms show a return" if found != 1 else "1 histogram shows a return"
    if found > 1 and cell_mm > spread_mm:  # (one return spreads over nothing: any cell would be "larger")
        # A scene radius of metres makes a hull cell larger than all the returns together: no cell is seen empty
        # by few enough views to stay, whatever the thresholds.
        return (f"space carving removed everything although {shown}: the scene box "
                f"{np.round(lo, 3).tolist()} .. {np.round(hi, 3).tolist()} m has {cell_mm:.0f} mm cells, larger "
                f"than the {spread_mm:.0f} mm the returns spread over (check the capture's scene.radius and "
                f"scene.center)")
    if held >= HELD_SHARE * found:
        return (f"space carving removed everything although {shown}, {held} of them in "
                f"{where}: the object is thin or faint, and the views that missed its return carved it away "
                f"({_thin_advice(threshold, weak, lowered)})")
    return (f"space carving removed everything although {shown}, only {held} of them in "
            f"{where}: the box or the floor does not hold the object (check the capture's scene.radius and "
            f"scene.center, or field.floor_z)")


def _carving_views(scene):
    """(counts (V, Z, B), sensor) as carving reads a view: its frames summed, the sensor's cycles a view's."""
    return summed_by_cycles(scene.counts.double().cpu().numpy(), scene.cycles.double().cpu().numpy(), scene.sensor)


def _carve(scene, counts, poses, sensor, fc, floor_z, on_table: bool, views: np.ndarray | None = None):
    """The carved hull of the scene's views: `counts` (V, Z, B) and `sensor` as `_carving_views` gives them, `poses`
    (V, 4, 4); `views`: the indices of those to carve with (None: all; see `FastProblem.setup_views`)."""
    box = carve_box(scene, floor_z)
    usable = _usable(scene)
    min_views = MIN_VIEWS
    if views is not None:
        # Space seen by fewer than MIN_VIEWS views is dropped as never scanned: counted among the subset's views, a
        # part that only a few views see (a cluster of an adaptive scan's views, which the subset takes one of) would
        # be dropped from a hull the fit cannot leave. Of a subset, one view that sees it keeps it (a looser hull).
        min_views = 1
        counts, poses = counts[views], poses[views]
        usable = None if usable is None else usable[views]
    return carve_scene(counts, poses, sensor,
                       resolution=fc.hull_resolution, threshold=fc.carve_threshold, margin_m=fc.carve_margin_m,
                       floor_z=floor_z, bounds=(box[0], box[1]), keep_returns_m=carve_keep_returns_m(scene, fc),
                       weak_threshold=carve_weak_threshold(fc, on_table), usable=usable, min_views=min_views)


def _usable(scene) -> np.ndarray | None:
    """(V, Z) histograms the capture holds data in (scene_data.SceneData.usable), as numpy; None: all."""
    return None if scene.usable is None else scene.usable.cpu().numpy()


__all__ = ["FastProblem", "build_problem", "candidate_rays"]
