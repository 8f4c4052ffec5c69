"""The empty-space bias: what no view can decide is left empty, not solid.

Space carving removes only what some zone proves empty: what lies in front of its first return. Two kinds of space
stay solid in the hull that the histograms cannot clear in a fit, and this part pushes the surface out of both.

On a table, a zone's first return is the object or the table, so the layer just above the table (within the
pulse's length of it, ~4 cm for the TMF8820) is never proven empty, and space near the edge of the views' fields
of view is barely looked at. That hull stays solid in the fit: the histograms cannot tell a low skirt on the table
from the table itself. Measured on LCSPCData's real pyramid, the skirt was most of the error (accuracy 23 mm against
completeness 4.6 mm). So on a table the push acts on the surface nodes that few views look at (`coverage` below
`full_coverage`): the data term holds a surface it sees, and what it cannot see melts away. Nodes that most views
look at get no push (their surface is the data's to place), which also keeps the bias from digging into the object's
unseen interior; pockets the solid closes are filled, and so is the space under the solid, which no view from above
sees into (cavities.py). What the push leaves of the skirt are thin curtains standing on the table, which
thin_sheets.py empties.

Without a table, a zone that looks past the object proves its field of view empty only up to the object's nearest
point; a wide zone (the dataset's 30-degree cone) leaves everything behind that range. Views that all look down (30
degrees of elevation and up) leave a ring of floor-level space around the object that every view containing it
sees only beyond the object: the fit kept it as a ring 25-33 cm from the bunny (60 mm Chamfer). Coverage cannot tell
that ring from the object's own far parts (16% of the dataset bunny's surface, its ears, lies where under 10% of the
views look). Whether a view *heard* anything at a node's range can: a node is heard by a view whose field of view
holds it and whose histogram has a return within a voxel of its range; the object's surface is heard by every view
that sees it, the ring by none. So without a table the push acts on the surface nodes that no view hears (fading to
nothing at `heard_views` views).

The push acts on the data term's gradient after its blur (blur.py), before the regularisers' gradient is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_model import in_any_zone, zone_masks

from ....carving.returns import matched_filter_z
from ....carving.views import summed_by_cycles
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
    heard_views: float = 2.0
    """Without a table: the push is full on nodes that no view hears a return at (see the module docstring) and fades
    to nothing where this many views do."""
    heard_threshold: float = 3.0
    """A return is heard where the matched-filtered histogram clears this many noise deviations (lower than the
    carving's 5: a weak return that the carving would not trust still holds the surface against the push)."""

    def check(self, key: str) -> None:
        super().check(key)
        if not self.pressure > 0:
            raise ConfigError(f"{key}.pressure {self.pressure} must be > 0 ({key}.enabled=false: off)")
        if not 0 < self.coverage <= 1:
            raise ConfigError(f"{key}.coverage {self.coverage} must be in (0, 1]")
        if not self.heard_views > 0:
            raise ConfigError(f"{key}.heard_views {self.heard_views} must be > 0")
        if not self.heard_threshold > 0:
            raise ConfigError(f"{key}.heard_threshold {self.heard_threshold} must be > 0 (noise deviations)")


class EmptySpacePush(Part):
    """Adds the push to the data term's gradient: on a table where few views look, without one where none hears."""

    name = "empty_space"

    def __init__(self, config: EmptySpaceConfig, model: Model):
        super().__init__(config, model)
        self._weight: torch.Tensor | None = None

    def after_gradient(self, model: Model, grad: torch.Tensor) -> torch.Tensor:
        push_to_empty(grad, model.field.sdf, model.field.voxel, self.weight(model), self.config.pressure)
        return grad

    def weight(self, model: Model) -> torch.Tensor:
        """The push's weight on the current grid's nodes (1, 1, nz, ny, nx): from the views' coverage (on a table)
        or the views that hear each node (without one), computed once on the coarse level's nodes and interpolated
        onto a refined grid (a model warm-started at the fine level, as a live job's are, takes every second node:
        the fine grid's 8x nodes took 35 s on a TMF8820 capture of 128 views, the coarse one's 4 s; 1.4 s now, idle,
        in the first step of every fit without a table). Only nodes the hull projection lets the surface reach are
        computed (the others are never surface nodes: weight 0)."""
        shape = tuple(model.field.sdf.shape)
        if self._weight is None:
            p = model.problem
            stride = 2 ** model.level  # refinement maps n nodes to 2 (n - 1) + 1: every second one is a coarse node
            points = model.field.node_points()[::stride, ::stride, ::stride]
            voxel = float(model.field.voxel) * stride
            with torch.no_grad():
                reach = torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
                if model.part("hull_projection") is not None:  # its bound on the grid is cached by the projection
                    bound = model.constraint.bound_for(model.field)[0, 0, ::stride, ::stride, ::stride]
                    reach = bound.to(points.device) <= 2 * voxel
                w = torch.zeros(points.shape[:-1], dtype=points.dtype, device=points.device)
                # A large capture's weights are those of its evenly spread set-up views (problem.setup_views): the
                # work is O(views x nodes), and the coverage share and the count of views that hear are then those
                # of the capture sizes these rules were tuned on.
                views = p.setup_views
                poses = p.poses if views is None else p.poses[views]
                if model.on_table:
                    looked = p.valid.any(dim=-1)
                    cov = view_coverage(points[reach], poses, p.forward.sensor.zones,
                                        looked=looked if views is None else looked[views])
                    w[reach] = pressure_weight(cov, self.config.coverage).to(w.dtype)
                else:
                    counts = p.counts if views is None else p.counts[views]
                    cycles = p.cycles if views is None else p.cycles[views]
                    loud = heard_view_bins(counts, cycles, p.forward.sensor, self.config.heard_threshold)
                    heard = views_hearing(points[reach], poses, p.forward.sensor, loud, voxel)
                    w[reach] = (1.0 - heard / self.config.heard_views).clamp(0.0, 1.0).to(w.dtype)
            self._weight = w[None, None].to(model.field.sdf.dtype).contiguous()
        if tuple(self._weight.shape) != shape:
            self._weight = torch.nn.functional.interpolate(self._weight, size=shape[2:], mode="trilinear",
                                                           align_corners=True)
        return self._weight


def view_coverage(points: torch.Tensor, poses: torch.Tensor, zones, chunk: int = 1 << 16,
                  looked: torch.Tensor | None = None) -> torch.Tensor:
    """Fraction of the views whose field of view (the union of its zones, occlusion ignored) holds each point.

    points (..., 3) and poses (V, 4, 4) sensor-to-world, metres; zones: the sensor model's Zone records (+z is the
    boresight). looked (V, Z) bool, or None for all: the zones whose histograms hold data. A zone that holds none (a
    dropped frame) looked at nothing, and a view none of whose zones did counts as no view: the coverage is the one
    without it. Returns (...) in [0, 1].
    """
    flat = points.reshape(-1, 3)
    rot, org = poses[:, :3, :3].to(flat.dtype), poses[:, :3, 3].to(flat.dtype)
    out = torch.zeros(flat.shape[0], dtype=flat.dtype, device=flat.device)
    if looked is not None:
        looked = looked.to(device=flat.device, dtype=torch.bool)
        if bool(looked.all()):
            looked = None
    views = poses.shape[0] if looked is None else int(looked.any(dim=1).sum())
    if views == 0:
        return out.reshape(points.shape[:-1])
    for i in range(0, flat.shape[0], chunk):
        rel = torch.einsum("vji,pvj->pvi", rot, flat[i: i + chunk, None, :] - org[None])  # sensor frame (P, V, 3)
        if looked is None:
            seen = in_any_zone(zones, rel)
        else:
            seen = torch.zeros(rel.shape[:2], dtype=torch.bool, device=flat.device)
            for z, held in enumerate(zone_masks(zones, rel)):
                seen |= held & looked[None, :, z]
        out[i: i + chunk] = seen.to(flat.dtype).sum(dim=1) / views
    return out.reshape(points.shape[:-1])


def heard_bins(counts: torch.Tensor, sensor, threshold: float) -> torch.Tensor:
    """(V, Z, B) bool: bins whose matched-filtered signal clears `threshold` noise deviations (a return is heard
    there), and the sensor's unreliable bins (never taken for silence)."""
    z = matched_filter_z(counts.detach().double().cpu().numpy(), sensor, "matched")
    loud = z > threshold
    loud[..., list(sensor.ignore_bins)] = True
    return torch.as_tensor(loud, device=counts.device)


def heard_view_bins(counts: torch.Tensor, cycles: torch.Tensor, sensor, threshold: float) -> torch.Tensor:
    """`heard_bins` of views that may each hold several frames: counts (V, Z, B) summed over a view's frames,
    cycles (V,) its laser cycles (frames x the sensor's cycles a frame). Read as carving reads them
    (`carving.views.summed_views`): taken for one frame's cycles, a view of 8 frames ran out of cycles early in the
    noise model and read nearly every bin as a return, so no node went unheard and the push never acted."""
    summed, view_sensor = summed_by_cycles(counts.detach().double().cpu().numpy(),
                                           cycles.detach().double().cpu().numpy(), sensor)
    return heard_bins(torch.as_tensor(summed), view_sensor, threshold).to(counts.device)


def views_hearing(points: torch.Tensor, poses: torch.Tensor, sensor, loud: torch.Tensor, half_width_m: float,
                  chunk: int = 1 << 12) -> torch.Tensor:
    """How many views hear a return at each point: the point lies in one of the view's zones (occlusion ignored)
    and that zone's histogram has a loud bin within `half_width_m` (metres) of the point's range.

    points (..., 3) and poses (V, 4, 4) sensor-to-world, metres; loud (V, Z, B) bool (`heard_bins`). Returns (...)."""
    flat = points.reshape(-1, 3)
    V, Z, B = loud.shape
    # Loud bins within the window, by a running count: any loud bin in [lo, hi] <=> cum[hi + 1] > cum[lo]. The
    # counts lie flat, zone by zone and view by view, so that one gather reads each (point, view)'s own zone.
    cum = torch.zeros((Z, V, B + 1), dtype=torch.int32, device=flat.device)
    cum[..., 1:] = torch.cumsum(loud.to(flat.device).to(torch.int32).permute(1, 0, 2), dim=-1)
    cum = cum.reshape(-1)
    rot, org = poses[:, :3, :3].to(flat.dtype), poses[:, :3, 3].to(flat.dtype)
    out = torch.empty(flat.shape[0], dtype=flat.dtype, device=flat.device)
    row = torch.arange(V, device=flat.device)[None] * (B + 1)
    zone_size = V * (B + 1)
    for i in range(0, flat.shape[0], chunk):
        rel = torch.einsum("vji,pvj->pvi", rot, flat[i: i + chunk, None, :] - org[None])  # sensor frame (P, V, 3)
        rng = rel.norm(dim=-1)
        lo = torch.floor(sensor.bin_of_range(rng - half_width_m)).long().clamp(0, B)
        hi = torch.floor(sensor.bin_of_range(rng + half_width_m)).long().clamp(-1, B - 1)
        first, past = row + lo, row + (hi + 1).clamp(0, B)
        held = torch.stack(zone_masks(sensor.zones, rel), dim=-1) & (hi >= lo)[..., None]  # (P, V, Z)
        # A (point, view) lies in one zone of a tiling (the TMF8820's): read the first zone that holds it, then
        # the others only for the few that more than one holds (overlapping zones, shared edges).
        count = held.sum(dim=-1)
        offset = held.to(torch.uint8).argmax(dim=-1) * zone_size
        heard = (count > 0) & (cum.take(offset + past) > cum.take(offset + first))
        several = count > 1
        if bool(several.any()):
            for z in range(1, Z):
                pick = (several & held[..., z]).nonzero(as_tuple=True)
                start = z * zone_size
                heard[pick] |= cum.take(start + past[pick]) > cum.take(start + first[pick])
        out[i: i + chunk] = heard.to(flat.dtype).sum(dim=1)
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


__all__ = ["EmptySpacePush", "EmptySpaceConfig", "view_coverage", "views_hearing", "heard_bins", "heard_view_bins",
           "pressure_weight", "push_to_empty"]
