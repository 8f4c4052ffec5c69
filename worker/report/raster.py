"""A headless mesh renderer: dense surface samples splatted into a z-buffer, Lambertian-shaded or colour-mapped.

Meshes from marching cubes have hundreds of thousands of faces, too many for matplotlib's 3D polygons; samples
splatted at pixel size render them in well under a second with numpy alone.
"""

from __future__ import annotations

import numpy as np


def view_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3, 3) world-to-camera rotation of an orbit view: camera x right, y up, z toward the viewer."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])  # from object to camera
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(up, toward)
    if np.linalg.norm(right) < 1e-9:
        right = np.array([0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(toward, right), toward])


def surface_samples(mesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (n, 3), unit normals (n, 3), face index (n,)) uniformly by area; normals interpolated from the
    mesh's vertex normals (the SDF gradient for our meshes)."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(mesh.triangles)
    area = np.asarray(mesh.area_faces, np.float64)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    w = np.stack([1 - u - v, u, v], 1)
    pts = np.einsum("nk,nkj->nj", w, tri[face])
    vn = np.asarray(mesh.vertex_normals)[np.asarray(mesh.faces)[face]]
    nrm = np.einsum("nk,nkj->nj", w, vn)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return pts, nrm, face


def splat(points: np.ndarray, values: np.ndarray, rotation: np.ndarray, center: np.ndarray, half_size: float,
          pixels: int, radius_px: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic z-buffer: (image (pixels, pixels, C) of the front-most sample's values (C,), mask).

    points (n, 3) world; values (n, C); the view spans center +- half_size metres; each sample covers a square of
    (2 radius_px + 1) pixels."""
    cam = (points - center) @ rotation.T
    px = ((cam[:, 0] / half_size + 1) * 0.5 * (pixels - 1)).round().astype(np.int64)
    py = ((1 - cam[:, 1] / half_size) * 0.5 * (pixels - 1)).round().astype(np.int64)
    depth = cam[:, 2]
    zbuf = np.full(pixels * pixels, -np.inf)
    owner = np.full(pixels * pixels, -1, np.int64)
    for dx in range(-radius_px, radius_px + 1):
        for dy in range(-radius_px, radius_px + 1):
            x, y = px + dx, py + dy
            ok = (x >= 0) & (x < pixels) & (y >= 0) & (y < pixels)
            idx = y[ok] * pixels + x[ok]
            np.maximum.at(zbuf, idx, depth[ok])
    # Owner: among samples whose depth equals the buffer at their own pixel footprint, the nearest wins.
    for dx in range(-radius_px, radius_px + 1):
        for dy in range(-radius_px, radius_px + 1):
            x, y = px + dx, py + dy
            ok = (x >= 0) & (x < pixels) & (y >= 0) & (y < pixels)
            sel = np.flatnonzero(ok)
            idx = y[sel] * pixels + x[sel]
            win = depth[sel] >= zbuf[idx]
            owner[idx[win]] = sel[win]
    mask = owner >= 0
    img = np.ones((pixels * pixels, values.shape[1]))
    img[mask] = values[owner[mask]]
    return img.reshape(pixels, pixels, -1), mask.reshape(pixels, pixels)


def shade(normals: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Grey level (n,) of a headlight Lambertian shading with some ambient light (two-sided)."""
    toward = rotation[2]
    light = toward + 0.4 * rotation[1]
    light /= np.linalg.norm(light)
    return 0.25 + 0.75 * np.abs(normals @ light)
