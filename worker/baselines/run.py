"""Running a baseline on a capture folder: threshold (given or calibrated), mesh, metrics, report.json.

Writes into the output folder: `mesh.ply`, `report.json` and, for reprojection, `points.ply` (the point cloud).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.plausibility import implausible
from spadscan.protocol.sensor_model import SensorModel

from ..carving.bounds import floor_cut_note, mesh_share_below, returns_below_floor, returns_span
from ..carving.returns import DEFAULT_THRESHOLD, first_returns
from ..carving.space_carving import DEFAULT_EDGE_DEG, MIN_VIEWS, carve_scene, main_components, occupancy_mesh
from ..carving.views import summed_views
from ..ground_truth import load_ground_truth
from ..outputs import capture_state_note, export_mesh
from ..report.report_json import json_safe, write_report
from ..time_axis import check_time_axis
from .common import CALIBRATION_POINTS, CALIBRATION_THRESHOLDS, MIN_SURFACE_POINTS, calibrate, default_threshold
from .floor import ASSUMED_FLOORS, check_given_floor, scene_floor
from .reprojection import reprojection, reprojection_returns

METHODS = ("reprojection", "space-carving")
SURFACES = {
    "occupancy": "marching cubes of the points' occupancy (points splatted on a grid of a quarter of their median "
                 "spacing, dilated by half of it, holes filled)",
    "convex-hull": "convex hull of the points",
}
THRESHOLD_UNITS = "standard deviations of the pulse-filtered background noise (z-score)"
IMPLAUSIBLE_SPAN = 1.5
"""A carved hull wider than this many times the box its first returns lie in (`bounds.returns_span`), along some
axis, is implausible: carving keeps only space behind returns, so most of such a hull is space no return supports.
Measured (space carving, widest axis): simulated lcspc scenes 0.6-0.8 (a mug of 48 and 256 views, the dataset's
bunny); a simulated TMF8820 mug 0.8-1.0 at thresholds 15-30, against 4.2 at 5 (a 1.15 m hull, Chamfer 221 mm); TMF8820
scenes on a table 1.9-3.7 at every threshold from 5 to 30 (the real pyramid, Chamfer 35-38 mm; simulated, a head on a
can 97-163 mm, a tall block), whose hulls keep a skirt of the table's space round the object."""


@dataclass(frozen=True)
class PoseViews:
    """A capture as the baselines read it: one view per pose, its frames summed (`carving.views`). hists (V, zones,
    bins) counts; poses (V, 4, 4); sensor: its cycles those of a view."""

    hists: np.ndarray
    poses: np.ndarray
    sensor: SensorModel


def _build(method: str, data: PoseViews, threshold: float, *, resolution: int, margin_m, floor_z, surface: str,
           edge_deg: float, usable) -> tuple[object, dict]:
    """(mesh or None, extras for the report) for one threshold. usable: the histograms carving may read (see
    `carve_hull`), and those reprojection reads: the others ("left out" in the warning) give no point and stay out
    of the crosstalk unmixing."""
    if method == "reprojection":
        rep = reprojection(data.hists, data.poses, data.sensor, threshold=threshold, surface=surface,
                           floor_z=floor_z, usable=usable)
        return rep.mesh, {"points": rep.points, "surface": surface, "surface_method": SURFACES[surface],
                          "reprojected_points": int(len(rep.points)), "returns_below_floor": rep.below_floor,
                          "returns_behind_sensor": rep.behind_sensor}
    res = carve_scene(data.hists, data.poses, data.sensor, resolution=resolution, threshold=threshold,
                      margin_m=margin_m, floor_z=floor_z, edge_deg=edge_deg, usable=usable)
    occ = main_components(res.occupancy, 0.01)
    mesh = occupancy_mesh(occ, res.origin, res.voxel_m)
    return mesh, {"resolution": resolution, "voxel_mm": (res.voxel_m * 1e3).round(3).tolist(),
                  "margin_mm": round(res.margin_m * 1e3, 3), "edge_deg": edge_deg,
                  "bounds_min_m": res.bounds_min.round(4).tolist(), "bounds_max_m": res.bounds_max.round(4).tolist(),
                  "hull_fraction": float(occ.mean()),
                  "surface_method": "marching cubes of the carved occupancy (Gaussian blur 0.7 voxel, level 0.5); "
                                    "pieces under 1% of the largest dropped"}


def _no_surface(capture, method: str, threshold: float, floor_z, extras: dict, data: PoseViews,
                usable: np.ndarray) -> str:
    """Why a baseline found no surface, with the remedy: the floor when it removed the returns (a lower threshold
    would not bring them back); too few histograms for the points a surface needs, or too few with a return at the
    lowest threshold that `--calibrate` tries (a lower threshold brings no more: more views do); else the threshold."""
    dropped, kept = extras.get("returns_below_floor", 0), extras.get("reprojected_points", 0)
    line = f"{capture}: {method} found no surface at threshold {threshold:g} ({THRESHOLD_UNITS})"
    if dropped and kept < MIN_SURFACE_POINTS <= dropped + kept:
        return (f"{line}: the floor at z = {floor_z:g} m removed {dropped} of its "
                f"{dropped + kept} first returns, which lie below it; check --floor-z "
                f"(metres), or pass --no-floor")
    if method == "reprojection":
        views, zones = data.hists.shape[:2]
        if views * zones < MIN_SURFACE_POINTS:
            return (f"{line}: its {views} view(s) of {zones} zone(s) give at most {views * zones} point(s), and a "
                    f"surface needs {MIN_SURFACE_POINTS}; scan more views")
        lowest = min(CALIBRATION_THRESHOLDS)
        found = int(reprojection_returns(data.hists, data.sensor, min(lowest, threshold), usable).detected.sum())
        if found < MIN_SURFACE_POINTS:
            return (f"{line}: only {found} histogram(s) hold a return even at threshold {min(lowest, threshold):g}, "
                    f"and a surface needs {MIN_SURFACE_POINTS} points; scan more views of the object")
    return f"{line}; try a lower --threshold"


def check_returns(capture, data: PoseViews, usable: np.ndarray) -> None:
    """Refuse (one CaptureError line) a capture in which no histogram holds a return above the noise at the default
    threshold, as the reconstruction does: a lower threshold then finds noise alone, and reprojection built a 4 m
    'surface' of it."""
    if not first_returns(data.hists, data.sensor, DEFAULT_THRESHOLD, "matched", usable=usable).detected.any():
        raise CaptureError(f"{capture}: no histogram holds a return above the noise ({DEFAULT_THRESHOLD:g} standard "
                           f"deviations of its matched-filtered background): nothing to reconstruct (the object out "
                           f"of range or out of every view, or the sensor's settings wrong)")


def hull_warning(method: str, mesh, data: PoseViews, threshold: float, usable: np.ndarray) -> tuple[str | None,
                                                                                              dict]:
    """(one line saying that a carved hull is implausible, or None; the spans for the report). Only space carving:
    reprojection's surface goes through its returns."""
    if method != "space-carving":
        return None, {}
    span = returns_span(first_returns(data.hists, data.sensor, threshold, "leading", usable=usable), data.poses,
                        data.sensor)
    if span is None:
        return None, {}
    hull, box = np.asarray(mesh.extents, float), np.maximum(span[1] - span[0], 1e-6)
    ratio = hull / box
    fields = {"hull_span_m": hull.round(4).tolist(), "returns_span_m": box.round(4).tolist(),
              "hull_to_returns_span": float(ratio.max().round(3))}
    if ratio.max() <= IMPLAUSIBLE_SPAN:
        return None, fields
    axis = "xyz"[int(np.argmax(ratio))]
    return (f"implausible hull: it spans {' x '.join(f'{v:.3f}' for v in hull)} m, {ratio.max():.1f} times the "
            f"{axis} extent of the box its first returns lie in ({' x '.join(f'{v:.3f}' for v in box)} m), so most "
            f"of it is space no return supports (threshold {threshold:g}: returns of noise, or a table's skirt); "
            f"do not read its metrics as the method's, try --calibrate or a higher --threshold"), fields


def floor_warning(floor_z, floor_source: str, data: PoseViews, usable: np.ndarray, truth) -> str | None:
    """The warning that a floor the baseline assumed (z = 0: no table named or found) cuts the object, or None
    (`bounds.floor_cut_note`). A floor given with --floor-z, or a table, is the user's or the histograms' word."""
    if floor_z is None or floor_source not in ASSUMED_FLOORS:
        return None
    below = returns_below_floor(data.hists, data.poses, data.sensor, float(floor_z), usable)
    share = None if truth is None else mesh_share_below(truth.mesh, float(floor_z))
    return floor_cut_note(float(floor_z), floor_source, below, share,
                          "--no-floor takes the floor away, --floor-z M (metres) moves it")


def run_baseline(capture, out, method: str, *, gt=None, threshold: float | None = None, calibrate_: bool = False,
                 resolution: int = 128, margin_m: float | None = None, floor_z: float | str | None = "auto",
                 surface: str = "occupancy", edge_deg: float = DEFAULT_EDGE_DEG,
                 log: Callable[[str], None] | None = None, thresholds=None,
                 calibration_points: int = CALIBRATION_POINTS, metrics_points: int = 300_000) -> dict:
    """Run `method` on the capture folder and write the results into `out`. Returns the report (also report.json).

    threshold: detection threshold (see THRESHOLD_UNITS; None: the sensor's default, `common.default_threshold`);
    `calibrate_` searches it for the best Chamfer against `gt`
    (a mesh path or builtin:NAME, scored above its table when it holds one: ground_truth.py) instead, as the paper
    did. floor_z: height (metres) below which the scene is empty; None: no floor; "auto": a measured scene's table,
    found in its histograms, else z = 0 (`floor.scene_floor`). thresholds: those `calibrate_` tries (default
    common.CALIBRATION_THRESHOLDS), scored on `calibration_points` samples per mesh; the final metrics use
    `metrics_points`.
    """
    if method not in METHODS:
        raise ConfigError(f"baseline {method!r} is not one of {METHODS}")
    if surface not in SURFACES:
        raise ConfigError(f"surface {surface!r} is not one of {tuple(SURFACES)}")
    if calibrate_ and threshold is not None:
        raise ConfigError("give either a threshold or --calibrate, not both")
    if calibrate_ and gt is None:
        raise ConfigError("--calibrate needs a ground truth (--gt MESH, or a capture that names one): the threshold "
                          "is chosen by its Chamfer against it")
    log = log or (lambda line: None)
    start = time.monotonic()
    data = CaptureReader(capture).load()
    data.check_counts(capture, log)  # histograms no sensor could produce: refused, or warned about
    views = data.by_pose()  # the baselines read one view per pose, its frames summed, as the reconstruction does
    state_note = capture_state_note(capture, data.manifest["state"], len(views.first),
                                    data.manifest.get("planned_poses"))
    if state_note:
        log(f"warning: {state_note}")
    truth = load_ground_truth(gt) if gt is not None else None
    floor_source = "given" if floor_z is not None else "none"
    if isinstance(floor_z, str):
        if floor_z != "auto":
            raise ConfigError(f"floor {floor_z!r} must be a height in metres, None or 'auto'")
        try:
            floor_z, floor_source = scene_floor(data)
        except CaptureError as exc:
            raise CaptureError(f"{Path(capture) / 'scan.json'}: {exc}") from None
        log(f"floor: {floor_source}" if floor_z is None else f"floor at z = {floor_z:.4f} m: {floor_source}")
    elif floor_z is not None:
        check_given_floor(float(floor_z), data.poses, data.sensor)
    # Once for every threshold tried: histograms no sensor could produce (in any frame of a pose) carve nothing.
    broken = views.in_any_frame(implausible(data.hists, *data.count_bounds()))
    counts, sensor = summed_views(views.counts, views.frames, data.sensor)
    posed = PoseViews(counts, data.poses[views.first], sensor)
    check_returns(capture, posed, ~broken)
    # as the reconstruction does: a wrong time axis is said as such, not as a bound or a floor that cut everything
    check_time_axis(capture, data.manifest.get("scene") or {}, posed.poses, posed.hists, posed.sensor, ~broken)
    warnings = [w for w in (floor_warning(floor_z, floor_source, posed, ~broken, truth),) if w]
    for line in warnings:
        log(f"warning: {line}")
    if method == "space-carving" and len(posed.hists) < MIN_VIEWS:
        raise CaptureError(f"{capture}: space carving keeps only space that at least {MIN_VIEWS} views see, and the "
                           f"capture holds {len(posed.hists)} (poses); scan more views, or use reprojection")
    opts = dict(resolution=resolution, margin_m=margin_m, floor_z=floor_z, surface=surface, edge_deg=edge_deg,
                usable=~broken)
    calibration = None
    if calibrate_:
        def progress(t, c):
            log(f"threshold {t:g}: " + ("no surface" if c is None else f"Chamfer {c:.2f} mm"))

        calibration = calibrate(lambda t: _build(method, posed, t, **opts)[0], truth, thresholds, progress=progress,
                                n_points=calibration_points)
        threshold = calibration.threshold
    if threshold is None:
        threshold, threshold_source = default_threshold(data.sensor), f"the default for the {data.sensor.name} sensor"
    else:
        threshold, threshold_source = float(threshold), "calibrated" if calibrate_ else "given"
    edge = None if calibration is None else calibration.edge_note()
    if edge:
        log(f"warning: {edge}")
        warnings.append(edge)
    mesh, extras = _build(method, posed, threshold, **opts)
    seconds = time.monotonic() - start
    if mesh is None:
        raise CaptureError(_no_surface(capture, method, threshold, floor_z, extras, posed, ~broken))
    implausible_line, spans = hull_warning(method, mesh, posed, threshold, ~broken)
    if implausible_line:
        log(f"warning: {implausible_line}")
        warnings.append(implausible_line)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    export_mesh(mesh, out / "mesh.ply")
    points = extras.pop("points", None)
    if points is not None:
        export_mesh(trimesh.PointCloud(points), out / "points.ply")
    report = {
        "method": method, "capture": str(Path(capture).resolve()), "sensor": data.sensor.name,
        "views": int(len(posed.hists)), "zones": int(data.sensor.n_zones),
        "threshold": threshold, "threshold_units": THRESHOLD_UNITS, "threshold_source": threshold_source,
        "calibrated": bool(calibrate_),
        "calibration": None if calibration is None else {
            "note": "threshold chosen by the lowest Chamfer against the ground truth, as in the paper "
                    f"(metrics on {calibration_points} samples per mesh during the search)",
            "table": calibration.table, "edge": calibration.edge(), **({"edge_note": edge} if edge else {})},
        "floor_z_m": floor_z, "floor_source": floor_source, "seconds": round(seconds, 3),
        "capture_state": data.manifest["state"],
        **({"capture_note": state_note} if state_note else {}),
        "mesh": {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))},
        "warnings": warnings,
        **({"implausible_hull": implausible_line is not None} if method == "space-carving" else {}),
        **spans,
        **extras,
    }
    if truth is not None:
        report["gt"] = str(gt)
        report["ground_truth"] = str(gt)  # the key reconstruct and eval use too
        if truth.note():
            log(f"scoring {truth.note()}")
        log(f"scoring against the ground truth on {metrics_points:,} points per mesh")
        report.update(truth.report_fields())
        report.update(truth.metrics(mesh, n_points=metrics_points).to_dict())
        unlike = truth.mismatch_warning(truth.scored(mesh), gt)
        if unlike is not None:
            log(f"warning: {unlike}")
            report["warnings"] = [*report["warnings"], unlike]
    write_report(out, report)
    return json_safe(report)
