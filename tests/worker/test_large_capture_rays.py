"""The candidate rays of every view are marched through the hull (fast/sampler.hull_rays), since training reads every
view: the march finds each ray's first and last hull sample from its ends, with jumps, and must find the very samples
a march through every step finds (a capture of up to 256 views fits step for step as before)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from spadscan.worker.recon.fast import sampler
from spadscan.worker.recon.fast.sampler import hull_rays

pytestmark = pytest.mark.usefixtures("one_thread")


def every_step(inside, origin, voxel, poses, zone_dirs, *, pad_m):
    """(t_in, t_out) (V * Z * D,) of a march through every step of every ray: the plain rule hull_rays keeps (inf and
    -inf where a ray misses the dilated hull)."""
    V, Z, D = poses.shape[0], zone_dirs.shape[0], zone_dirs.shape[1]
    dt = poses.dtype
    occ = torch.nn.functional.max_pool3d(inside.float()[None, None], 3, 1, 1)[0, 0] > 0
    nz, ny, nx = occ.shape
    origin = origin.to(dt)
    lo, hi = origin, origin + (torch.tensor([nx, ny, nz], dtype=dt) - 1) * voxel
    dirs = torch.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs).reshape(-1, 3)
    origins = poses[:, None, None, :3, 3].expand(V, Z, D, 3).reshape(-1, 3)
    t0, t1 = sampler._box_interval(origins, dirs, lo, hi)
    ramp = torch.arange(int(math.ceil(float((hi - lo).norm()) / voxel)) + 2, dtype=dt) * voxel
    t = t0[:, None] + ramp[None]
    node = torch.zeros(t.shape, dtype=torch.long)
    for axis, (size, stride) in enumerate(((nx, 1), (ny, nx), (nz, nx * ny))):
        i = torch.round((origins[:, axis, None] + t * dirs[:, axis, None] - origin[axis]) / voxel).long()
        node += i.clamp_(0, size - 1) * stride
    hit = occ.reshape(-1)[node] & (t <= t1[:, None]) & (t1 > t0)[:, None]
    first = torch.where(hit, t, torch.full_like(t, math.inf)).amin(dim=1)
    last = torch.where(hit, t, torch.full_like(t, -math.inf)).amax(dim=1)
    found = hit.any(dim=1)
    t_in = torch.where(found, (first - pad_m).clamp(min=1e-3), torch.full_like(first, math.inf))
    return t_in, torch.where(found, last + pad_m, torch.full_like(last, -math.inf))


def looking_at(eyes: np.ndarray, target) -> np.ndarray:
    """(n, 4, 4) sensor-to-world poses at `eyes` (n, 3) whose +z boresight points at `target`."""
    poses = np.tile(np.eye(4), (len(eyes), 1, 1))
    for k, eye in enumerate(eyes):
        fwd = np.asarray(target, float) - eye
        fwd /= np.linalg.norm(fwd)
        side = np.cross(fwd, [0.0, 0.0, 1.0] if abs(fwd[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        poses[k, :3, :3] = np.stack([side, np.cross(fwd, side), fwd], axis=1)
        poses[k, :3, 3] = eye
    return poses


def cone_dirs(rng, zones: int, per_zone: int, half_angle_deg: float) -> torch.Tensor:
    """(zones, per_zone, 3) unit sensor-frame directions spread in a cone about +z."""
    half = math.radians(half_angle_deg)
    cos = rng.uniform(math.cos(half), 1.0, (zones, per_zone))
    phi = rng.uniform(0, 2 * math.pi, (zones, per_zone))
    sin = np.sqrt(1 - cos ** 2)
    return torch.as_tensor(np.stack([sin * np.cos(phi), sin * np.sin(phi), cos], axis=-1))


def hulls(shape=(30, 34, 38)) -> dict[str, torch.Tensor]:
    """Hull grids (nz, ny, nx) bool: a ball, a thin shell, a ring (rays pass through its hole and graze it), scattered
    specks, a slab along the grid's wall, one node."""
    z, y, x = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    c = np.array(shape) / 2.0
    r = np.sqrt((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2)
    rho = np.sqrt((y - c[1]) ** 2 + (x - c[2]) ** 2)
    specks = np.random.default_rng(7).random(shape) < 0.004
    one = np.zeros(shape, bool)
    one[5, 20, 9] = True
    wall = np.zeros(shape, bool)
    wall[:, :, :2] = True
    grids = {"ball": r < 9, "shell": (r > 11) & (r < 12), "ring": (np.abs(rho - 10) < 1.5) & (np.abs(z - c[0]) < 2),
             "specks": specks, "wall": wall, "one node": one}
    return {name: torch.as_tensor(g) for name, g in grids.items()}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(hulls()))
def test_the_jumping_march_finds_the_samples_every_step_finds(name, dtype):
    inside = hulls()[name]
    rng = np.random.default_rng(3)
    voxel = 0.0075
    origin = torch.tensor([-0.13, -0.12, -0.10], dtype=dtype)
    centre = origin.numpy() + voxel * (np.array(inside.shape[::-1]) - 1) / 2
    # Views all round at 0.5 m, a few inside the grid's box (a sensor in the hull's box) and some looking past it.
    direction = rng.normal(size=(40, 3))
    eyes = centre + 0.5 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    eyes[:4] = centre + rng.uniform(-0.08, 0.08, (4, 3))
    targets = centre + rng.uniform(-0.15, 0.15, (40, 3))
    poses = torch.as_tensor(np.stack([looking_at(e[None], t)[0] for e, t in zip(eyes, targets)]), dtype=dtype)
    dirs = cone_dirs(rng, 3, 60, 20.0).to(dtype)
    weights = torch.full(dirs.shape[:2], 1e-3, dtype=dtype)
    pad = 2 * voxel
    rays = hull_rays(inside, origin, voxel, poses, dirs, weights, pad_m=pad, keep_missed=True)
    t_in, t_out = every_step(inside, origin, voxel, poses, dirs, pad_m=pad)
    keep = torch.isfinite(t_in) & torch.isfinite(t_out) & (t_out > t_in)
    assert 0 < int(keep.sum()) < keep.numel() or name == "wall"
    assert torch.equal(rays.t_in, t_in[keep]) and torch.equal(rays.t_out, t_out[keep])
    assert int(rays.count.sum()) + int(rays.missed.count.sum()) == keep.numel()


def test_an_empty_hull_is_missed_by_every_ray():
    inside = torch.zeros((10, 10, 10), dtype=torch.bool)
    poses = torch.as_tensor(looking_at(np.array([[0.0, 0.0, 0.5]]), (0, 0, 0)), dtype=torch.float32)
    dirs = torch.tensor([[[0.0, 0.0, 1.0]]])
    rays = hull_rays(inside, torch.full((3,), -0.05), 0.01, poses, dirs, torch.ones((1, 1)), pad_m=0.01,
                     keep_missed=True)
    assert int(rays.count.sum()) == 0 and int(rays.missed.count.sum()) == 1


def test_the_march_tests_a_few_samples_a_ray_not_the_grids_diagonal(monkeypatch):
    """At 3 ms a view, the march of every step made the candidate rays a large capture's largest set-up stage (30 s
    at 10,000 views); the jumps test a few samples a ray wherever the ray meets the hull."""
    z, y, x = np.meshgrid(*[np.arange(64)] * 3, indexing="ij")
    inside = torch.as_tensor((z - 31.5) ** 2 + (y - 31.5) ** 2 + (x - 31.5) ** 2 < 24 ** 2)  # a ball 12 cm across
    rng = np.random.default_rng(5)
    voxel = 0.005
    origin = torch.full((3,), -0.16, dtype=torch.float32)
    direction = rng.normal(size=(30, 3))
    eyes = 0.5 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    poses = torch.as_tensor(looking_at(eyes, (0, 0, 0)), dtype=torch.float32)
    dirs = cone_dirs(rng, 9, 100, 10.0).to(torch.float32)
    tested = []
    real = sampler._HullGrid._nodes

    def counting(self, o, d, t):
        tested.append(t.numel())
        return real(self, o, d, t)

    monkeypatch.setattr(sampler._HullGrid, "_nodes", counting)
    rays = hull_rays(inside, origin, voxel, poses, dirs, torch.full((9, 100), 1e-4), pad_m=0.01)
    n = poses.shape[0] * dirs.shape[0] * dirs.shape[1]
    diagonal = math.sqrt(3) * 64
    assert int(rays.count.sum()) > 0.5 * n
    assert sum(tested) / n < 0.25 * diagonal, f"{sum(tested) / n:.1f} samples a ray, the diagonal {diagonal:.0f}"


def test_directions_longer_than_unit_jump_no_sample_of_the_hull():
    """Samples lie a voxel apart along a unit direction, farther apart along a longer one: the jumps shorten by as
    much (a thin shell, which a jump of the unit length would step over)."""
    inside = hulls()["shell"]
    rng = np.random.default_rng(11)
    voxel, origin = 0.0075, torch.tensor([-0.13, -0.12, -0.10], dtype=torch.float64)
    centre = origin.numpy() + voxel * (np.array(inside.shape[::-1]) - 1) / 2
    direction = rng.normal(size=(20, 3))
    eyes = centre + 0.5 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    poses = torch.as_tensor(looking_at(eyes, centre), dtype=torch.float64)
    dirs = 1.7 * cone_dirs(rng, 2, 80, 15.0)
    rays = hull_rays(inside, origin, voxel, poses, dirs, torch.full((2, 80), 1e-3, dtype=torch.float64), pad_m=0.0)
    t_in, t_out = every_step(inside, origin, voxel, poses, dirs, pad_m=0.0)
    keep = torch.isfinite(t_in) & torch.isfinite(t_out) & (t_out > t_in)
    assert int(keep.sum()) > 0
    assert torch.equal(rays.t_in, t_in[keep]) and torch.equal(rays.t_out, t_out[keep])
