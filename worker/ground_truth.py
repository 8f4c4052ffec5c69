"""Ground truth for the metrics, scored on the object alone when the mesh includes the table it stands on.

A measured scene's ground truth may hold the table as a slab (LCSPCData's pyramid2.stl: a 2 m slab whose top is at
z = -0.156 m). A reconstruction holds no table, so scored whole the slab's area swamps the object's: a 4.4 mm mesh of
the real pyramid scored 380 mm (completeness 750 mm). Such a ground truth is scored on the object: both meshes are
cut `CUT_ABOVE_TABLE_M` above the slab's top (as `benchmarks/error_vs_time.py` has always scored the pyramid).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CUT_ABOVE_TABLE_M = 0.005
"""How far above the table top (metres) both meshes are cut: a reconstruction's base meets the table over a voxel or
two, where no histogram tells object from table."""

TABLE_AREA_SHARE = 0.25
"""A table slab is one level of upward-facing triangles holding more than this share of the mesh's whole area (its
top; its bottom and sides hold most of the rest), with an object standing on it (see OBJECT_ABOVE_M). An object's own
flat tops hold far less of it, or have nothing above them (a stool's flat seat)."""

OBJECT_ABOVE_M = 0.005
"""A level is a table's top only where part of the mesh rises at least this far (metres) above it."""



@dataclass(frozen=True)
class GroundTruth:
    """The mesh a reconstruction is compared with (trimesh.Trimesh, metres) and the height above which both are
    scored (None: all of both)."""

    mesh: object
    cut_above_z_m: float | None = None
    units_read: str = "m"
    """The unit its file was read in ('mm' when millimetres were detected: protocol.mesh_io.load_mesh)."""

    def scored(self, pred):
        """The part of a reconstruction `pred` that is compared: what lies above the cut. A MeshError names the cut
        when nothing does."""
        if self.cut_above_z_m is None:
            return pred
        if not np.any(pred.triangles_center[:, 2] > self.cut_above_z_m):
            from spadscan.protocol.errors import MeshError

            raise MeshError(f"the reconstruction has nothing above z = {self.cut_above_z_m:.4f} m, where the ground "
                            f"truth's object is scored (its table top + {CUT_ABOVE_TABLE_M * 1e3:g} mm)")
        return cut_above(pred, self.cut_above_z_m)

    def metrics(self, pred, **options):
        """`metrics.mesh_metrics` of the scored part of `pred` against the ground truth (options: n_points, seed,
        fscore_threshold_m)."""
        from spadscan.worker.metrics import mesh_metrics

        return mesh_metrics(self.scored(pred), self.mesh, **options)

    def mismatch_warning(self, scored, name) -> str | None:
        """A warning when the scored part of a reconstruction and this ground truth (read from `name`) plainly are
        not one object in one frame and unit (`metrics.mismatch`): figures against it score the mistake, not the
        reconstruction. None otherwise."""
        from spadscan.worker.metrics import mismatch

        found = mismatch(scored, self.mesh)
        if found is None:
            return None
        return (f"the ground truth {name} does not match the reconstruction: {found}; its figures score that, not "
                f"the reconstruction: check that it is the scanned object's, in metres, in the capture's frame")

    def report_fields(self) -> dict:
        """What a report.json records of how it was scored: `ground_truth_cut_above_z_m` (None: whole), and with a
        cut, `ground_truth_scored` (the note)."""
        fields = {"ground_truth_cut_above_z_m": self.cut_above_z_m}
        if self.note():
            fields["ground_truth_scored"] = self.note()
        return fields

    def note(self) -> str | None:
        """One line for reports and the console when the table is left out, else None."""
        if self.cut_above_z_m is None:
            return None
        return (f"the object above z = {self.cut_above_z_m:.4f} m (the ground truth's table top + "
                f"{CUT_ABOVE_TABLE_M * 1e3:g} mm; a reconstruction holds no table)")


def table_top_z(mesh) -> float | None:
    """Height (metres) of a table slab's top in `mesh`, or None when it has none (see TABLE_AREA_SHARE)."""
    normals, areas = mesh.face_normals, mesh.area_faces
    # A closed mesh wound inside out (its volume negative) has its normals inward: its slab's bottom would read as
    # an upward level with the object above it, and the whole slab be scored as the object.
    inward = mesh.is_watertight and mesh.volume < 0
    up = (-normals[:, 2] if inward else normals[:, 2]) > 0.99
    if not up.any():
        return None
    heights = np.round(mesh.triangles_center[up, 2], 4)  # one level to 0.1 mm
    levels, inverse = np.unique(heights, return_inverse=True)
    level_area = np.bincount(inverse, weights=areas[up])
    if level_area.max() <= TABLE_AREA_SHARE * areas.sum():
        return None
    top = float(levels[np.argmax(level_area)])
    if float(mesh.vertices[:, 2].max()) < top + OBJECT_ABOVE_M:
        return None  # the mesh's own flat top, nothing stands on it
    return top


def cut_above(mesh, z: float):
    """The surface of `mesh` above height `z` (metres), its faces across that height split (`metrics.crop_to_box`),
    whatever its tessellation."""
    from spadscan.worker.metrics import crop_to_box

    big = 1e6
    return crop_to_box(mesh, np.array([-big, -big, z]), np.array([big, big, big]))


def object_on_table(mesh) -> GroundTruth:
    """`mesh` as ground truth: cut `CUT_ABOVE_TABLE_M` above its table slab's top when it holds one, else whole."""
    top = table_top_z(mesh)
    if top is None:
        return GroundTruth(mesh)
    z = top + CUT_ABOVE_TABLE_M
    return GroundTruth(cut_above(mesh, z), z)


def load_ground_truth(spec, *, units: str = "auto", keep_table: bool = False) -> GroundTruth:
    """Ground truth from a mesh file or `builtin:NAME` (see protocol.mesh_io.load_mesh_spec); scored above its table
    unless `keep_table`."""
    from spadscan.protocol.mesh_io import load_mesh_spec

    import dataclasses

    mesh = load_mesh_spec(str(spec), units=units)[0]
    truth = GroundTruth(mesh) if keep_table else object_on_table(mesh)
    return dataclasses.replace(truth, units_read=mesh.metadata.get("units_read", "m"))


def named_ground_truth(manifest: dict) -> tuple[str | None, str | None]:
    """(the ground truth a capture's manifest names, as a mesh path or `builtin:NAME` that loads, or None; why there
    is none although the manifest names one, or None).

    The scene record may name a mesh file (`ground_truth`, written by import-lcspc; `mesh`, by simulate) or a built-in
    scene (`builtin`); the first that loads wins. Ground truth only adds metrics, so one that does not load is a
    reason to say, never an error: each is loaded here, before hours of training."""
    from spadscan.protocol.errors import SpadscanError
    from spadscan.protocol.mesh_io import BUILTIN_PREFIX, load_mesh_spec

    scene = manifest.get("scene") if isinstance(manifest, dict) else None
    if not isinstance(scene, dict):
        return None, None
    named = [(key, scene[key]) for key in ("ground_truth", "mesh", "builtin") if isinstance(scene.get(key), str)]
    why = None
    for key, value in named:
        spec = BUILTIN_PREFIX + value if key == "builtin" else value
        if key != "builtin" and not Path(value).is_file():
            why = why or f"{value}: no such ground-truth mesh"
            continue
        try:
            load_mesh_spec(spec)
        except SpadscanError as exc:
            why = why or (f"built-in scene {value!r}: {exc}" if key == "builtin" else str(exc))
            continue
        return spec, None
    return None, None if why is None else f"{why}; no metrics"


def scene_offset_m(manifest: dict) -> np.ndarray | None:
    """The translation (metres) by which the capture's scene was placed (the daemon's simulated sensor records
    `mesh_offset_m`), or None when there is none: the named mesh is the scene only once moved by it."""
    scene = manifest.get("scene") if isinstance(manifest, dict) else None
    try:
        offset = np.asarray((scene or {}).get("mesh_offset_m", (0.0, 0.0, 0.0)), float).reshape(3)
    except (TypeError, ValueError):
        return None
    return offset if np.all(np.isfinite(offset)) and np.any(offset != 0) else None


def capture_ground_truth(capture) -> tuple[str | None, str | None]:
    """`named_ground_truth` of the capture folder `capture`; (None, None) when its manifest cannot be read (reading
    the capture says why)."""
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.errors import SpadscanError

    try:
        manifest = CaptureReader(capture).manifest
    except (OSError, SpadscanError):
        return None, None
    spec, why = named_ground_truth(manifest)
    offset = scene_offset_m(manifest)
    if spec is not None and offset is not None:
        return None, (f"{spec} stood offset by mesh_offset_m {offset.tolist()} in the capture's scene; give --gt "
                      f"a mesh placed as scanned for metrics")
    return spec, why


def add_ground_truth_options(parser, what: str) -> None:
    """--gt MESH and --no-gt (exclusive), as `ground_truth_for_run` reads them; `what` ends --gt's help: what the
    ground truth is for."""
    truth = parser.add_mutually_exclusive_group()
    truth.add_argument("--gt", default=None, metavar="MESH",
                       help=f"ground-truth mesh (metres; STL in mm detected) or builtin:NAME{what} (default: the "
                            "one the capture names, as import-lcspc and simulate record it)")
    truth.add_argument("--no-gt", action="store_true",
                       help="no metrics, even when the capture names a ground truth")


def ground_truth_for_run(capture, gt, no_gt: bool, log) -> tuple[str | None, str | None]:
    """(the ground truth a command scores the capture's reconstruction against, why the one the capture names is not
    used or None): `gt` when given, none with `no_gt`, else the one the capture names (`capture_ground_truth`), said
    through `log` (a line each) with how to skip it. The reason goes into the report too (`ground_truth_note`), as a
    worker's job records it: a line on the terminal scrolls away, and a page without metrics should say why."""
    if gt is not None or no_gt:
        return gt, None
    spec, why = capture_ground_truth(capture)
    if spec is not None:
        log(f"ground truth: {spec}, named by the capture (--gt MESH for another, --no-gt for none)")
    elif why is not None:
        log(f"ground truth: {why}")
    return spec, why


__all__ = ["CUT_ABOVE_TABLE_M", "GroundTruth", "table_top_z", "cut_above", "object_on_table", "load_ground_truth",
           "named_ground_truth", "scene_offset_m", "capture_ground_truth",
           "add_ground_truth_options", "ground_truth_for_run"]
