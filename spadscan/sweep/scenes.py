"""The scenes a sweep names: a mesh file, a built-in scene, or a scene of the public LCSPCData dataset.

- `path/to/mesh.obj`: a mesh file in metres (millimetres detected), relative to the sweep file's folder;
- `builtin:NAME`: a built-in scene (sphere, cup, teddy, mug, ...: `spadscan simulate --help` lists them all);
- `lcspc:NAME`: the ground-truth mesh of LCSPCData's simulated scene NAME (bunny, soap, sphere), found as
  `DIR/simulated/NAME/NAME.obj` under the dataset folder given with `--lcspc DIR`.

A scene is known by its label (as written) and a digest of its triangles: a point's id holds both, so that moving the
dataset changes nothing and a different mesh under the same name is never mistaken for the one the results came from.
Workers load the mesh from its resolved source (the machines share a filesystem) and check the digest.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import ConfigError, MeshError
from spadscan.protocol.mesh_io import load_mesh_spec

LCSPC_PREFIX = "lcspc:"
BUILTIN_PREFIX = "builtin:"


@dataclass(frozen=True)
class Scene:
    label: str
    """As the sweep file names it."""
    source: str
    """What `protocol.mesh_io.load_mesh_spec` loads: `builtin:NAME` or an absolute path."""
    digest: str
    """sha256 of the loaded mesh's vertices (float64, metres) and faces (int64)."""

    def record(self) -> dict:
        return {"name": self.label, "mesh_sha256": self.digest}


def resolve_source(label: str, sweep_dir: Path, lcspc_root: Path | None) -> str:
    """The mesh source of a scene label (see the module docstring)."""
    if label.startswith(BUILTIN_PREFIX):
        return label
    if label.startswith(LCSPC_PREFIX):
        name = label[len(LCSPC_PREFIX):]
        if not name or "/" in name or name in (".", ".."):
            raise ConfigError(f"scene {label!r}: name an LCSPCData simulated scene, e.g. lcspc:bunny")
        if lcspc_root is None:
            raise ConfigError(f"scene {label!r} is in the LCSPCData dataset: give its folder with --lcspc DIR (the "
                              f"folder that holds simulated/)")
        path = Path(lcspc_root) / "simulated" / name / f"{name}.obj"
        if not path.is_file():
            raise ConfigError(f"scene {label!r}: {path} is missing (is --lcspc {lcspc_root} the dataset's folder, "
                              f"the one that holds simulated/?)")
        return str(path.resolve())
    path = Path(label)
    if not path.is_absolute():
        path = sweep_dir / path
    return str(path.resolve())


def mesh_digest(mesh) -> str:
    """sha256 of a mesh's vertices and faces, as loaded."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def load_scene(label: str, sweep_dir: Path, lcspc_root: Path | None) -> Scene:
    """Resolve and load a scene once (on the machine that plans the sweep) to learn its digest."""
    source = resolve_source(label, sweep_dir, lcspc_root)
    try:
        mesh, _ = load_mesh_spec(source)
    except MeshError as exc:
        raise ConfigError(f"scene {label!r}: {exc}") from None
    return Scene(label, source, mesh_digest(mesh))


def scene_mesh(scene: Scene):
    """(mesh, the scene record a capture stores) of a scene, checked against its digest (on a worker)."""
    mesh, record = load_mesh_spec(scene.source)
    if mesh_digest(mesh) != scene.digest:
        raise MeshError(f"scene {scene.label!r}: the mesh at {scene.source} differs from the one the sweep was "
                        f"planned with (another file on this machine, or changed since)")
    return mesh, record


__all__ = ["Scene", "load_scene", "scene_mesh", "resolve_source", "mesh_digest"]
