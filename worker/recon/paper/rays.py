"""Rays stratified uniformly in solid angle over each zone's field of view, and importance resampling.

Each zone's field of view is cut into C cells (the same C for every zone): a cone into rings equal in cos(theta)
times sectors equal in azimuth (every cell the same solid angle), a rectangular zone into a grid in (tan x, tan y)
(each cell's exact solid angle computed from its corners). One ray per cell, jittered inside it, carries the cell's
solid angle as its weight: `sum(weight * f(dir))` estimates the integral of f over the zone in steradians.

Importance rays are drawn in cells chosen with probabilities pi_k and weighted by the balance heuristic over the two
sampling strategies, `Omega_k / (1 + n_imp * pi_k)`, for stratified and importance rays alike, which keeps the sum
unbiased for any pi that does not depend on the rays it weights (pi taken from those same rays gives a cell whose ray
hit a small weight: biased low at hard edges; the model takes pi from an earlier render of the view).
"""

from __future__ import annotations

import math

import torch

from spadscan.protocol.sensor_model import SensorModel

from ..errors import ReconstructionError


class ZoneGrid:
    """Cells over every zone of a sensor, in the sensor frame (+z is the boresight).

    lo, hi: (Z, C, 2) cell bounds in the zone's parameters ((cos theta, azimuth) for cones, (tan x, tan y) for
    rectangles); cell_weight: (Z, C) solid angle of each cell (sr), summing to each zone's solid angle.
    """

    def __init__(self, sensor: SensorModel, n_per_zone: int, device="cpu", dtype=torch.float32):
        if not (isinstance(n_per_zone, int) and 1 <= n_per_zone <= 1_000_000):
            raise ReconstructionError(f"rays per zone {n_per_zone} must be an integer in [1, 1e6]")
        zones = sensor.zones
        na, nb = _grid_shape(zones[0], n_per_zone)
        los, his, weights, rots, cone = [], [], [], [], []
        for zone in zones:
            if zone.kind == "cone":
                a = (math.cos(zone.half_angle_rad), 1.0)
                b = (0.0, 2 * math.pi)
            else:
                a, b = zone.tan_x, zone.tan_y
            ea = torch.linspace(a[0], a[1], na + 1, dtype=torch.float64)
            eb = torch.linspace(b[0], b[1], nb + 1, dtype=torch.float64)
            a0, b0 = torch.meshgrid(ea[:-1], eb[:-1], indexing="ij")
            a1, b1 = torch.meshgrid(ea[1:], eb[1:], indexing="ij")
            lo = torch.stack([a0.reshape(-1), b0.reshape(-1)], -1)
            hi = torch.stack([a1.reshape(-1), b1.reshape(-1)], -1)
            if zone.kind == "cone":
                w = (hi[:, 0] - lo[:, 0]) * (hi[:, 1] - lo[:, 1])
            else:
                w = (_rect_corner(hi[:, 0], hi[:, 1]) - _rect_corner(lo[:, 0], hi[:, 1])
                     - _rect_corner(hi[:, 0], lo[:, 1]) + _rect_corner(lo[:, 0], lo[:, 1]))
            los.append(lo)
            his.append(hi)
            weights.append(w)
            rots.append(_rotation_z_to(torch.tensor(zone.axis, dtype=torch.float64)))
            cone.append(zone.kind == "cone")
        kw = dict(device=device, dtype=dtype)
        self.lo = torch.stack(los).to(**kw)
        self.hi = torch.stack(his).to(**kw)
        self.cell_weight = torch.stack(weights).to(**kw)
        self.rotation = torch.stack(rots).to(**kw)
        self.is_cone = torch.tensor(cone, device=device)

    @property
    def n_zones(self) -> int:
        return int(self.lo.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.lo.shape[1])

    def directions(self, cells: torch.Tensor, *, jitter: bool, generator: torch.Generator | None = None):
        """Unit directions (Z, M, 3) of one ray in each named cell. cells: (Z, M) long indices into the C cells.

        jitter=False puts each ray at its cell's centre (in the cell's parameters)."""
        lo = torch.gather(self.lo, 1, cells[..., None].expand(-1, -1, 2))
        hi = torch.gather(self.hi, 1, cells[..., None].expand(-1, -1, 2))
        if jitter:
            u = torch.rand(cells.shape + (2,), generator=generator, dtype=torch.float64).to(lo)
        else:
            u = torch.full(cells.shape + (2,), 0.5, dtype=lo.dtype, device=lo.device)
        p = lo + (hi - lo) * u
        # Cone: (cos theta, azimuth) about +z, then rotated onto the zone's axis.
        c = p[..., 0].clamp(-1.0, 1.0)
        s = torch.sqrt((1.0 - c * c).clamp_min(0.0))
        cone = torch.stack([s * torch.cos(p[..., 1]), s * torch.sin(p[..., 1]), c], -1)
        cone = torch.einsum("zij,zmj->zmi", self.rotation, cone)
        rect = torch.stack([p[..., 0], p[..., 1], torch.ones_like(c)], -1)
        rect = rect / rect.norm(dim=-1, keepdim=True)
        return torch.where(self.is_cone[:, None, None], cone, rect)

    def all_cells(self) -> torch.Tensor:
        """(Z, C) indices of every cell."""
        return torch.arange(self.n_cells, device=self.lo.device).expand(self.n_zones, -1)

    def draw_cells(self, prob: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """(..., n) cells drawn with replacement from prob (..., C) (rows need not be normalised, must be >= 0)."""
        flat = prob.reshape(-1, prob.shape[-1]).double().cpu()
        flat = flat.clamp_min(0) + 1e-300
        idx = torch.multinomial(flat / flat.sum(-1, keepdim=True), n, replacement=True, generator=generator)
        return idx.reshape(prob.shape[:-1] + (n,)).to(self.lo.device)


def zone_rays(sensor: SensorModel, n_per_zone: int, *, jitter: bool, generator: torch.Generator | None = None,
              device="cpu", dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays over every zone: (dirs (Z, R, 3) unit, sensor frame; weights (Z, R) sr, summing to each zone's solid
    angle). R is close to n_per_zone (the cells form a grid)."""
    grid = ZoneGrid(sensor, n_per_zone, device, dtype)
    return grid.directions(grid.all_cells(), jitter=jitter, generator=generator), grid.cell_weight.clone()


def mixture_weights(cell_weight: torch.Tensor, prob: torch.Tensor, n_importance: int) -> torch.Tensor:
    """Balance-heuristic weight of a ray in each cell (..., C) when every cell has one stratified ray and
    `n_importance` more rays fall in cells drawn with probabilities `prob` (..., C), normalised here."""
    pi = prob / prob.sum(-1, keepdim=True).clamp_min(1e-30)
    return cell_weight / (1.0 + n_importance * pi)


def _grid_shape(zone, n: int) -> tuple[int, int]:
    """(cells along the first parameter, along the second) with about n cells, roughly square in angle."""
    if zone.kind == "cone":
        # Ring width ~ half_angle / na, ring length ~ 2 pi sin(half_angle / 2): ~pi times longer than wide.
        na = max(1, int(round(math.sqrt(n / math.pi))))
    else:
        aspect = (zone.tan_x[1] - zone.tan_x[0]) / (zone.tan_y[1] - zone.tan_y[0])
        na = max(1, int(round(math.sqrt(n * aspect))))
    return na, max(1, int(round(n / na)))


def _rect_corner(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Solid angle of the rectangle [0, x] x [0, y] on the z = 1 plane (signed)."""
    return torch.atan(x * y / torch.sqrt(1.0 + x * x + y * y))


def _rotation_z_to(axis: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation taking +z onto the unit vector `axis` by the shortest path."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=axis.dtype)
    v = torch.linalg.cross(z, axis)
    c = float(axis @ z)
    if float(v.norm()) < 1e-12:
        return torch.eye(3, dtype=axis.dtype) * (1.0 if c > 0 else -1.0)
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=axis.dtype)
    return torch.eye(3, dtype=axis.dtype) + vx + vx @ vx / (1.0 + c)
