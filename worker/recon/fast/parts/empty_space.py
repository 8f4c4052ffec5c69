"""The empty-space bias of scenes on a table: what no view can decide is left empty, not solid.

Space carving removes only what some zone proves empty. With no table behind the object (the simulated scenes), a
zone that looks past the object sees nothing and proves its whole field of view empty, so the hull hugs the object.
On a table it does not: a zone's first return is the object or the table, so the layer just above the table (within
the pulse's length of it, ~4 cm for the TMF8820) is never proven empty, and space near the edge of the views' fields
of view is barely looked at. That hull stays solid in the fit: the histograms cannot tell a low skirt on the table
from the table itself. Measured on LCSPCData's real pyramid, the skirt was most of the error (accuracy 23 mm against
completeness 4.6 mm).

So, with a table, every step pushes the surface inward on the surface nodes that few views look at (`coverage`
below `full_coverage`), by a fraction of the data gradient's rms: the data term holds a surface it sees, and what it
cannot see melts away. Nodes that most views look at get no push (their surface is the data's to place), which also
keeps the bias from digging into the object's unseen interior; pockets the solid closes are filled, and so is the
space under the solid, which no view from above sees into (cavities.py). What the push leaves of the skirt are thin
curtains standing on the table, which thin_sheets.py empties.

The push acts on the data term's gradient after its blur (blur.py), before the regularisers' gradient is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from spadscan.protocol.errors import ConfigError

from .part import Model, Part, PartConfig


@dataclass
class EmptySpaceConfig(PartConfig):
    """How hard the push is, and where it fades out."""

    pressure: float = 0.2
    """The push on a surface node no view looks at, as a fraction of the data gradient's rms over the surface."""
    coverage: float = 0.6
    """The push is full where no view looks and fades to nothing where this fraction of the views (or more) has the
    node in its field of view. (On LCSPCData's real pyramid the surface 1 cm or more off the object after a fit lay
    where a median 31% of the views look; the object's own faces, where a median 59% do: the data holds those against
    the push.)"""

    def check(self, key: str) -> None:
        super().check(key)
        if not self.pressure > 0:
            raise ConfigError(f"{key}.pressure {self.pressure} must be > 0 ({key}.enabled=false: off)")
        if not 0 < self.coverage <= 1:
            raise ConfigError(f"{key}.coverage {self.coverage} must be in (0, 1]")


class EmptySpacePush(Part):
    """Adds the push to the data term's gradient on scenes on a table."""

    name = "empty_space"

    def __init__(self, config: EmptySpaceConfig, model: Model):
        super().__init__(config, model)
        self._weight: torch.Tensor | None = None

    @classmethod
    def left_out(cls, config: EmptySpaceConfig, model: Model) -> str | None:
        if not model.on_table:
            return "no table under the object: every zone that looks past it proves its view empty"
        return None

    def after_gradient(self, model: Model, grad: torch.Tensor) -> torch.Tensor:
        push_to_empty(grad, model.field.sdf, model.field.voxel, self.weight(model), self.config.pressure)
        return grad

    def weight(self, model: Model) -> torch.Tensor:
        """The push's weight on the current grid's nodes (1, 1, nz, ny, nx): from the views' coverage, computed once
        on the coarse grid (a second on 64^3 nodes x 128 views) and interpolated onto a refined one."""
        shape = tuple(model.field.sdf.shape)
        if self._weight is None:
            with torch.no_grad():
                cov = view_coverage(model.field.node_points(), model.problem.poses, model.problem.forward.sensor.zones)
            self._weight = pressure_weight(cov, self.config.coverage)[None, None].contiguous()
        if tuple(self._weight.shape) != shape:
            self._weight = torch.nn.functional.interpolate(self._weight, size=shape[2:], mode="trilinear",
                                                           align_corners=True)
        return self._weight


def view_coverage(points: torch.Tensor, poses: torch.Tensor, zones, chunk: int = 1 << 16) -> torch.Tensor:
    """Fraction of the views whose field of view (the union of its zones, occlusion ignored) holds each point.

    points (..., 3) and poses (V, 4, 4) sensor-to-world, metres; zones: the sensor model's Zone records (+z is the
    boresight). Returns (...) in [0, 1].
    """
    flat = points.reshape(-1, 3)
    rot, org = poses[:, :3, :3].to(flat.dtype), poses[:, :3, 3].to(flat.dtype)
    out = torch.empty(flat.shape[0], dtype=flat.dtype, device=flat.device)
    for i in range(0, flat.shape[0], chunk):
        rel = torch.einsum("vji,pvj->pvi", rot, flat[i: i + chunk, None, :] - org[None])  # sensor frame (P, V, 3)
        z = rel[..., 2]
        front = z > 1e-9
        tz = torch.where(front, z, torch.ones_like(z))
        seen = torch.zeros(z.shape, dtype=torch.bool, device=flat.device)
        for zone in zones:
            if zone.kind == "rect":
                tx, ty = rel[..., 0] / tz, rel[..., 1] / tz
                seen |= (front & (tx >= zone.tan_x[0]) & (tx <= zone.tan_x[1]) & (ty >= zone.tan_y[0])
                         & (ty <= zone.tan_y[1]))
            else:
                axis = torch.as_tensor(zone.axis, dtype=rel.dtype, device=rel.device)
                cos = (rel @ axis) / rel.norm(dim=-1).clamp(min=1e-12)
                seen |= cos >= float(np.cos(zone.half_angle_rad))
        out[i: i + chunk] = seen.to(flat.dtype).mean(dim=1)
    return out.reshape(points.shape[:-1])


def pressure_weight(coverage: torch.Tensor, full_coverage: float) -> torch.Tensor:
    """1 where no view looks, falling linearly to 0 where `full_coverage` (a fraction of the views) or more look."""
    if not 0 < full_coverage <= 1:
        raise ConfigError(f"pressure coverage {full_coverage} must be in (0, 1]")
    return (1.0 - coverage / full_coverage).clamp(0.0, 1.0)


def push_to_empty(grad: torch.Tensor, sdf: torch.Tensor, voxel: float, weight: torch.Tensor, strength: float) -> None:
    """Add the empty-space push to a grid's gradient in place: on surface nodes (|sdf| < one voxel), minus
    `strength` x the gradient's rms over those nodes x `weight` (a descent step then raises the SDF: less solid).

    grad, sdf, weight: grids of one shape (1, 1, nz, ny, nx); voxel in metres."""
    surf = sdf.detach().abs() < voxel
    if not bool(surf.any()):
        return
    rms = torch.sqrt((grad[surf] ** 2).mean())
    if not bool(torch.isfinite(rms)) or float(rms) == 0.0:
        return
    grad -= strength * rms * surf.to(grad.dtype) * weight


__all__ = ["EmptySpacePush", "EmptySpaceConfig", "view_coverage", "pressure_weight", "push_to_empty"]
