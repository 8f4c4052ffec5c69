"""Signed distance functions of simple solids, for building test objects (numpy only, metres).

A shape here is a function `f(x, y, z) -> d` of coordinate arrays that broadcast together, negative inside, positive
outside, zero on the surface. The primitives are exact distances or close bounds near their surface (the ellipsoid),
which is all meshing needs: the surface is the zero level set, and a field that grows about as fast as the distance
(|grad f| near 1) lets `sdf_mesh.mesh_sdf` skip nodes far from it. Combinators build new shapes from old ones; a
smooth union blends two shapes with a fillet of size `k` (metres), the way clay parts are pressed together.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

Shape = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def _length(*parts):
    return np.sqrt(sum(p * p for p in parts))


def sphere(center, radius: float) -> Shape:
    cx, cy, cz = center
    return lambda x, y, z: _length(x - cx, y - cy, z - cz) - radius


def ellipsoid(center, radii) -> Shape:
    """Axis-aligned ellipsoid (rotate it with `rotated`), for axis ratios up to about 5.

    Near the surface the field is (k0 - 1) k0 / k1 with k0 = |p / r|, k1 = |p / r^2|: zero on the surface, its
    gradient of length exactly 1 there. Away from it that expression changes fast with direction on a stretched
    ellipsoid, and degenerates at the centre, so it is held within (k0 - 1) min(r) + min(r) / 2 outside (a bound that
    grows no faster than the distance) and above -min(r) / 2 inside: the field stays within 2x the distance's rate
    of change (sdf_mesh.LIPSCHITZ) and keeps its sign."""
    cx, cy, cz = center
    rx, ry, rz = radii
    r_min = float(min(radii))

    def f(x, y, z):
        u, v, w = (x - cx) / rx, (y - cy) / ry, (z - cz) / rz
        k0 = _length(u, v, w)
        k1 = _length(u / rx, v / ry, w / rz)
        scale = np.where(k1 > 1e-9, k0 / np.maximum(k1, 1e-9), r_min)  # k0 / k1: direction only, in [min r, max r]
        near = (k0 - 1.0) * scale
        return np.maximum(np.minimum(near, (k0 - 0.5) * r_min), -0.5 * r_min)
    return f


def capsule(a, b, radius: float) -> Shape:
    """All points within `radius` of the segment a-b."""
    a, ab = [float(v) for v in a], [float(q) - float(p) for p, q in zip(a, b)]
    den = sum(v * v for v in ab)

    def f(x, y, z):
        px, py, pz = x - a[0], y - a[1], z - a[2]
        t = np.clip((px * ab[0] + py * ab[1] + pz * ab[2]) / den, 0.0, 1.0)
        return _length(px - t * ab[0], py - t * ab[1], pz - t * ab[2]) - radius
    return f


def box(center, half, rounding: float = 0.0) -> Shape:
    """Axis-aligned box of half-sizes `half`, its edges rounded by `rounding` metres (the outer size stays)."""
    cx, cy, cz = center
    hx, hy, hz = (h - rounding for h in half)

    def f(x, y, z):
        qx, qy, qz = np.abs(x - cx) - hx, np.abs(y - cy) - hy, np.abs(z - cz) - hz
        outside = _length(np.maximum(qx, 0.0), np.maximum(qy, 0.0), np.maximum(qz, 0.0))
        inside = np.minimum(np.maximum(qx, np.maximum(qy, qz)), 0.0)
        return outside + inside - rounding
    return f


def cylinder(center_xy, radius: float, z0: float, z1: float, rounding: float = 0.0) -> Shape:
    """Vertical cylinder of `radius` from height z0 to z1, its rims rounded by `rounding` metres."""
    cx, cy = center_xy
    zc, hz = (z0 + z1) / 2, (z1 - z0) / 2 - rounding
    r = radius - rounding

    def f(x, y, z):
        dr = _length(x - cx, y - cy) - r
        dz = np.abs(z - zc) - hz
        outside = _length(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
        return outside + np.minimum(np.maximum(dr, dz), 0.0) - rounding
    return f


def torus(center, major: float, minor: float) -> Shape:
    """Torus about the z axis through `center` (rotate it with `rotated`)."""
    cx, cy, cz = center
    return lambda x, y, z: _length(_length(x - cx, y - cy) - major, z - cz) - minor


def rotated(shape: Shape, axis, angle_rad: float, about=(0.0, 0.0, 0.0)) -> Shape:
    """`shape` turned by `angle_rad` about `axis` through the point `about` (distances are kept)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)
    inv = rot.T.tolist()  # a point of the turned shape is the original shape's point turned back
    ox, oy, oz = (float(v) for v in about)

    def f(x, y, z):
        px, py, pz = x - ox, y - oy, z - oz
        return shape(inv[0][0] * px + inv[0][1] * py + inv[0][2] * pz + ox,
                     inv[1][0] * px + inv[1][1] * py + inv[1][2] * pz + oy,
                     inv[2][0] * px + inv[2][1] * py + inv[2][2] * pz + oz)
    return f


def union(*shapes: Shape) -> Shape:
    def f(x, y, z):
        out = shapes[0](x, y, z)
        for s in shapes[1:]:
            out = np.minimum(out, s(x, y, z))
        return out
    return f


def smooth_union(k: float, *shapes: Shape) -> Shape:
    """Union blended over a fillet of about `k` metres (polynomial smooth minimum; k = 0 is the plain union)."""
    def f(x, y, z):
        out = shapes[0](x, y, z)
        for s in shapes[1:]:
            d = s(x, y, z)
            if k <= 0:
                out = np.minimum(out, d)
                continue
            h = np.clip(0.5 + 0.5 * (d - out) / k, 0.0, 1.0)
            out = d + (out - d) * h - k * h * (1.0 - h)
        return out
    return f


def subtract(shape: Shape, *cutters: Shape) -> Shape:
    """`shape` with the cutters removed."""
    def f(x, y, z):
        out = shape(x, y, z)
        for c in cutters:
            out = np.maximum(out, -c(x, y, z))
        return out
    return f


def intersect(*shapes: Shape) -> Shape:
    def f(x, y, z):
        out = shapes[0](x, y, z)
        for s in shapes[1:]:
            out = np.maximum(out, s(x, y, z))
        return out
    return f


def shell(shape: Shape, thickness: float) -> Shape:
    """A wall of `thickness` metres on the inside of `shape`'s surface."""
    return lambda x, y, z: np.abs(shape(x, y, z) + thickness / 2) - thickness / 2


__all__ = ["Shape", "sphere", "ellipsoid", "capsule", "box", "cylinder", "torus", "rotated", "union",
           "smooth_union", "subtract", "intersect", "shell"]
