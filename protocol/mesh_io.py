"""Loading meshes the user names: one-line errors for missing, empty or non-finite files, unit detection for STL
(and the other unitless formats: OBJ, PLY, OFF)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import MeshError

# An object this tool scans fits in a 2 m box; an STL whose extent exceeds this is taken to be in millimetres.
MM_EXTENT_THRESHOLD_M = 5.0
# No object spadscan scans, nor a 100-1000x units mix-up of one, comes near this size (metres across, after reading
# millimetres): a mesh larger is a units or export error, and distances between samples of one so large and one of
# an object's size lose all precision (exact nearest samples then take hours).
MAX_EXTENT_M = 1e4
# Formats that carry no unit. STL is the usual millimetre culprit (CAD exports); an OBJ, PLY or OFF exported from
# CAD in millimetres is just as wrong read as metres, so 'auto' applies the same rule to them.
UNITLESS_SUFFIXES = (".stl", ".obj", ".ply", ".off")
# glTF (GLB) is y-up by its specification (and its exporters write it so); every other format here, and spadscan, is
# z-up: a glTF mesh is turned +90 degrees about x as it is read, or it would lie on its side, half below the table.
Y_UP_SUFFIXES = (".glb", ".gltf")


def load_mesh(path, *, units: str = "auto"):
    """Load a triangle mesh in metres as a trimesh.Trimesh.

    units: 'm', 'mm' or 'auto' (STL files, which carry no units, and the other UNITLESS_SUFFIXES are read as
    millimetres when their extent exceeds MM_EXTENT_THRESHOLD_M metres). Scenes with several bodies are concatenated.
    glTF files (GLB), y-up by their specification, are turned z-up (Y_UP_SUFFIXES).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: {'is a folder, not a' if path.is_dir() else 'no such'} mesh file")
    if units not in ("auto", "m", "mm"):
        raise MeshError(f"units {units!r} must be 'auto', 'm' or 'mm'")
    try:
        with open(path, "rb"):  # the file's own trouble (permissions) said as such, not as a damaged mesh
            pass
    except OSError as exc:
        raise MeshError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    # Non-finite or huge coordinates make trimesh's normals and areas print numpy warnings on the way; the checks
    # below say what is wrong in one line.
    with np.errstate(all="ignore"):
        return _load(path, units, trimesh)


def _load(path: Path, units: str, trimesh):
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files; all mean "cannot read this mesh"
        raise MeshError(_unreadable(path, exc, trimesh.available_formats())) from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{path}: holds no triangles")
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    if not np.all(np.isfinite(verts)):
        raise MeshError(f"{path}: has non-finite vertex coordinates")
    faces = np.asarray(loaded.faces)
    missing = faces[(faces < 0) | (faces >= len(verts))]
    if missing.size:
        raise MeshError(f"{path}: a face names vertex {int(missing[0])} of {len(verts)} (damaged or truncated)")
    if path.suffix.lower() in Y_UP_SUFFIXES:
        verts = verts[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # +90 deg about x: glTF's +y up becomes +z up
    scale = 1.0
    if units == "mm" or (units == "auto" and path.suffix.lower() in UNITLESS_SUFFIXES
                         and np.ptp(verts, axis=0).max() > MM_EXTENT_THRESHOLD_M):
        scale = 1e-3
    span = np.ptp(verts, axis=0)
    widest = float(span.max())  # the diagonal in units of the widest side: squared in metres, 1e155 m overflowed
    extent = widest * float(np.linalg.norm(span / widest)) * scale if 0 < widest < np.inf else widest * scale
    if not extent <= MAX_EXTENT_M:  # inf where the diagonal overflows
        read = " (read as millimetres)" if scale != 1.0 else ""
        raise MeshError(f"{path}: {extent:.3g} m across{read}, far larger than anything scanned (at most "
                        f"{MAX_EXTENT_M:g} m accepted): check its units and coordinates")
    written = trimesh.Trimesh(verts * scale, faces, process=False)
    # A surface closed as written keeps its own connectivity: merging the vertices of a marching-cubes mesh (which
    # repeats a vertex where the surface passes through a grid node) pinches it there into edges of three or more
    # faces, and a one-piece ground truth was counted as five pieces with no genus (end_of_run's pieces and tunnels
    # checks then said nothing). A triangle soup (STL) has no connectivity but what merging gives it, and the
    # triangles that merging collapses to nothing go: they joined pieces only through pinched edges.
    mesh = written if written.is_watertight else _merged(verts * scale, faces)
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise MeshError(f"{path}: all triangles are degenerate (zero area; it spans {extent:.3g} m)")
    # Which unit the file was read in, so that a caller can say so: a silent x1000 is a surprise otherwise.
    mesh.metadata["units_read"] = "mm" if scale != 1.0 else "m"
    return mesh


def _merged(verts: np.ndarray, faces: np.ndarray):
    """The mesh with its coincident vertices merged and the triangles that collapsed (zero area) left out."""
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


def _unreadable(path: Path, exc: Exception, formats) -> str:
    """Why a file that trimesh could not load is no mesh, in one line. The parser's own words ("list index out of
    range") come last: they help someone who debugs a file, and say nothing to someone who named the wrong one."""
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in formats:
        said = f"format '.{suffix}'" if suffix else "no file suffix"
        return f"{path}: not a mesh file spadscan can read ({said}; use PLY, STL, OBJ, OFF or GLB)"
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return (f"{path}: not a valid {suffix.upper()} mesh: damaged, truncated or not a mesh at all (the reader "
            f"stopped with: {detail})")


BUILTIN_PREFIX = "builtin:"


def load_mesh_spec(spec: str, *, units: str = "auto"):
    """A mesh in metres from a file path or `builtin:NAME` (a scene of spadscan.protocol.scenes).

    Returns (mesh, record): the record is what captures store in their manifest's `scene` dict so that the worker
    can find the ground truth again: {"builtin": NAME} or {"mesh": absolute path}, with "mesh_units": "mm" when the
    file was read as millimetres.
    """
    if spec.startswith(BUILTIN_PREFIX):
        from .scenes import builtin_scene  # lazily: building the scenes costs time nobody else should pay

        name = spec[len(BUILTIN_PREFIX):]
        return builtin_scene(name), {"builtin": name}
    mesh = load_mesh(spec, units=units)
    record = {"mesh": str(Path(spec).resolve())}
    if mesh.metadata.get("units_read") == "mm":
        record["mesh_units"] = "mm"
    return mesh, record
