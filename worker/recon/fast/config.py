"""Configuration of the `fast` preset: an explicit SDF grid started and bounded by the space-carving hull.

`fast_config()` returns a `FastConfig`: the shared run settings of `ReconConfig` with this preset's sections, `field`
(`FastFieldConfig`: hull, grid, rendering), `schedule` (`FastScheduleConfig`: rays, samples, optimiser), `loss`
(`FastLossConfig`: the grid's regulariser weights) and `parts` (`parts.FastPartsConfig`: one section per mechanism,
each with `enabled`). One set of defaults serves every scene: lengths that should follow the grid are in voxels,
physical ones in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from spadscan.protocol.errors import ConfigError

from ..config import ReconConfig, check_in_range, check_int
from .parts import FastPartsConfig


@dataclass
class FastFieldConfig:
    """The SDF grid, the hull that starts and bounds it, and how it is rendered."""

    resolution: int = 64
    """Grid nodes along the longest side of the hull's box at the coarse level."""
    box_pad_voxels: float = 3.0
    """Empty margin between the hull's bounding box and the grid's walls: this many times the box's longest side /
    (resolution - 1), plus `hull_margin_m` (how far the solid may leave the hull)."""
    hull_resolution: int = 128
    """Cells along the longest side of the space-carving grid."""
    carve_threshold: float = 5.0
    """Detection threshold of the carving's first returns, in noise standard deviations (lower carves less and is
    safer for faint, thin parts)."""
    carve_weak_threshold: float = 4.0
    """A run of bins above this (noise standard deviations) that ends before the signal clears `carve_threshold` is a
    faint return in front of the strong one, and carving stops at it; a strong return's own leading edge still sets
    the onset at `carve_threshold`. One zone that misses a return proves its space empty: at 5 alone, some of the
    256 views of the check split's coat rack saw its 12 mm pole at 4-5 deviations and carving removed the pole from
    8 cm up (the fit 49.7 mm). With 4 here the hull keeps all of it and the other scenes' hulls grow by 0-2.1 %
    (4 as the threshold itself: by 0.1-4.5 %, every leading edge moving out). Not on a table
    (`problem.carve_weak_threshold`)."""
    carve_margin_m: float = 0.002
    """Range (metres) left uncarved in front of every first return."""
    carve_keep_returns_m: float = 0.06
    """Space up to this far (metres) beyond a zone's first return stays in the hull however few views see it. Views
    aim at the object's middle, so the top of a tall object lies in the fields of view of only the few views above
    it; without this, carving drops it as unscanned space (fewer than 3 views) and the fit may not grow back there:
    a 35 cm lamp's shade lost its top 6 cm (0: the old rule). Simulated captures only (problem.carve_keep_returns_m:
    on the real pyramid it kept air above the object)."""
    hull_min_votes: float = 0.2
    """Pieces of the carved hull into which fewer first returns land than this share of the best piece's are
    dropped (`hull.object_hull`): space the views barely looked at, a skirt along the box's walls, specks beside the
    sensors. 0: every piece stays. Not on a table, where it bought nothing (benchmarks/RESULTS.md, "The hull's piece
    vote and the rays' jitter, each switched off alone")."""
    hull_returns_pad_m: float | None = 0.02
    """The hull is cut to the box of its cells that first returns land in, grown by this much (metres), before the
    SDF grid's box is taken around it (`hull.returns_box`): views aimed at the object's middle leave its shadow
    uncarved, and the grid grew to hold it. None: the whole hull. Not on a table, as `hull_min_votes`."""
    hull_margin_m: float = 0.004
    """How far (metres) the surface may grow outside the carved hull: keeps thin parts that carving shaved (the field
    starts on the hull grown by this much, and `parts.hull_projection` holds it there)."""
    sharpness_voxels: float = 2.0
    """Fixed NeuS opacity sharpness s = sharpness_voxels / voxel (1/metres): the surface is about a voxel thick at
    every level of the grid. Never learned: sharpening past the sample spacing makes runs drift."""
    floor_z: float | None = 0.0
    """Height (metres, world z) below which nothing is solid: the floor the object stands on, which no histogram
    shows (world z = 0 by the convention of the simulator and of LCSPCData's simulated scenes, as for the space-carving
    baseline). Without it the carved hull keeps the object's whole unobservable shadow below it. A `floor_z` in the
    capture's scene record, or a table (named by the capture or detected in a measured one), takes precedence;
    None: no floor."""


@dataclass
class FastScheduleConfig:
    """Rays, samples and the optimiser of the fast preset."""

    candidate_rays_per_sr: float = 5000.0
    """Candidate directions per steradian of each zone, marched once through the hull; those that enter it form the
    pool each step draws from."""
    rays_per_sr: float = 900.0
    """Hull-hitting rays drawn per histogram per step, per steradian of the zone (at least `min_rays`)."""
    min_rays: int = 32
    """Floor on rays per histogram per step."""
    ray_jitter: bool = True
    """Turn each drawn ray by a random angle about half the candidates' spacing, every step: over the steps the
    rays cover the zone, not only the candidates' fixed directions (false: the candidates as they are)."""
    views_per_step: int = 16
    """Views (all their zones) rendered per step."""
    coarse_samples: int = 48
    """Samples per ray, without gradient, spread over its hull segment to find the first zero crossing."""
    fine_samples: int = 16
    """Samples per ray, with gradient, around the first zero crossing."""
    window_voxels: float = 3.0
    """Half-width of the fine window around the crossing, in voxels."""
    segment_pad_voxels: float = 1.5
    """Padding of each ray's hull segment at both ends, in voxels."""
    lr_voxels: float = 0.4
    """Adam learning rate of the SDF values, in voxels per step."""
    lr_final_fraction: float = 0.25
    """On the last level, the grid's learning rate decays (cosine, over `fine_steps`) to this fraction."""
    fine_steps: int = 1200
    """Steps the last level's learning-rate decay is laid out over."""
    adam_floor: float = 1.0
    """Each grid node's Adam second moment is taken as at least this many times the grid's mean (`optim.Adam`'s
    floor): nodes whose gradients are smaller than the grid's typical one step in proportion to them, not a full
    step, so the noise of the few rays that reach a surface moves it less (0: plain Adam). On every level, after
    the coarse level's first `adam_floor_after_steps` steps; on a table, on the levels after the coarse one only:
    there the empty-space push clears the carved hull's skirt and the space over the table at full steps, and with
    the floor on the coarse level phantom lumps stayed on the table 10-20 cm from a simulated head on a can (1.22 ->
    22.4 mm)."""
    adam_floor_after_steps: int = 50
    """Plain Adam for this many steps of the coarse level before the floor sets in: they carve the hull down to the
    object, which the floor slows (the tuning lamp 1.03 -> 1.83 mm and the mug 1.15 -> 5.05 with the floor from the
    first step; plain Adam on the whole coarse level left phantom blobs on a head, 3.80 mm, and the mushroom's
    underside filled, 2.11; benchmarks/RESULTS.md)."""
    albedo_lr: float = 0.02
    """Adam learning rate of the log albedos (object and table)."""
    band_voxels: float = 4.0
    """The Eikonal and smoothness terms act on nodes within this many voxels of the surface."""
    reg_points: int = 65536
    """Band nodes drawn per step for the Eikonal and smoothness terms (all of them when the band is smaller)."""
    band_refresh_steps: int = 10
    """Steps of a level between updates of the band of nodes near the surface."""


@dataclass
class FastLossConfig:
    """The weights of the grid's regularisers beside the photon likelihood (its deviance per bin)."""

    eikonal_weight: float = 0.1
    """Weight of the finite-difference Eikonal term, mean (|grad f| - 1)^2 on the band's nodes."""
    smooth_weight: float = 0.05
    """Weight of the smoothness term, mean (voxel x Laplacian f)^2 on the band's nodes: the squared change of the
    unit normal across one voxel."""


MOVED = {
    "field.refine_after_steps": "parts.refinement.after_steps (parts.refinement.enabled=false: never refine)",
    "field.fill_under_overhangs": "parts.cavities.under_overhangs",
    "field.thin_sheet_voxels": "parts.thin_sheets.voxels (parts.thin_sheets.enabled=false: off)",
    "field.thin_sheet_band_m": "parts.thin_sheets.band_m",
    "field.table_albedo_init": "parts.table.albedo_init",
    "schedule.table_lr_m": "parts.table.lr_m",
    "schedule.average_decay": "parts.average.decay (parts.average.enabled=false: mesh the current grid)",
    "schedule.grad_blur_passes": "parts.blur.passes (parts.blur.enabled=false: off)",
    "schedule.blur_physical": "parts.blur.physical",
    "schedule.coarse_smooth_height_m": "parts.coarse_smoothing.height_m (parts.coarse_smoothing.enabled=false: "
                                       "smooth everywhere)",
    "schedule.empty_pressure": "parts.empty_space.pressure (parts.empty_space.enabled=false: off)",
    "schedule.pressure_coverage": "parts.empty_space.coverage",
    "schedule.phantom_ratio": "parts.erosion.ratio and parts.openings.flag_ratio (parts.erosion.enabled=false: off)",
    "schedule.phantom_every_steps": "parts.erosion.every_steps",
    "schedule.phantom_min_hits": "parts.erosion.min_hits and parts.openings.min_hits",
    "schedule.phantom_window_bins": "parts.erosion.window_bins and parts.openings.window_bins",
    "schedule.open_every_steps": "parts.openings.every_steps (parts.openings.enabled=false: off)",
    "schedule.open_depths_m": "parts.openings.depths_m",
    "schedule.open_keep_m": "parts.openings.keep_m",
    "schedule.open_keep_ratio": "parts.openings.keep_ratio",
    "schedule.open_passes": "parts.openings.passes",
    "schedule.open_min_gain": "parts.openings.min_gain",
    "schedule.open_min_flagged": "parts.openings.min_flagged",
    "schedule.open_patience": "parts.openings.patience",
    "schedule.patience_steps": "parts.plateau.patience_steps",
    "schedule.min_rel_improvement": "parts.plateau.min_rel_improvement",
    "schedule.shared_adam": "schedule.adam_floor (a large floor steps every node in proportion to its gradient)",
    "loss.tv_weight": "loss.smooth_weight (the grid's smoothness; tv_weight is the paper preset's normal TV)",
}
"""Keys of earlier versions -> where the setting lives now (an override of an old key names the new one)."""


@dataclass
class FastConfig(ReconConfig):
    """The `fast` preset's resolved config (see the module)."""

    parts: FastPartsConfig = field(default_factory=FastPartsConfig)
    """One section per mechanism (`parts/`), each switched off by `parts.NAME.enabled=false`."""

    moved: ClassVar[dict[str, str]] = MOVED

    def check(self) -> None:
        super().check()
        for key in ("resolution", "hull_resolution"):
            check_int(f"field.{key}", getattr(self.field, key), 4, 1024)
        for key in ("carve_margin_m", "carve_keep_returns_m"):
            check_in_range(f"field.{key}", getattr(self.field, key), 0.0, 1.0)
        if self.field.hull_returns_pad_m is not None:
            check_in_range("field.hull_returns_pad_m", self.field.hull_returns_pad_m, 0.0, 1.0,
                           hint="none: the whole hull")
        check_in_range("field.hull_min_votes", self.field.hull_min_votes, 0.0, 1.0, unit="of the best piece's votes",
                       hint="0: every piece stays")
        check_in_range("field.carve_weak_threshold", self.field.carve_weak_threshold, 1.0,
                       max(1.0, self.field.carve_threshold), unit="noise standard deviations",
                       hint="at most field.carve_threshold")
        check_in_range("schedule.adam_floor", self.schedule.adam_floor, 0.0, 1e6, unit="times the mean",
                       hint="0: plain Adam")
        check_int("schedule.adam_floor_after_steps", self.schedule.adam_floor_after_steps, 0,
                  hint="0: the floor from the first step")
        for key in ("views_per_step", "band_refresh_steps", "min_rays", "reg_points"):
            check_int(f"schedule.{key}", getattr(self.schedule, key), 1)
        self._check_rendering()
        self.parts.check()

    def _check_rendering(self) -> None:
        """Values with which the fit renders nothing, or a step cannot be held in memory: each used to be accepted,
        and the run then either "succeeded" with its data term never moving (the mesh was the carved hull) or ended
        in a traceback."""
        sc, fd = self.schedule, self.field
        # Two samples make one section of opacity; a zero crossing lies between two coarse samples.
        for key in ("coarse_samples", "fine_samples"):
            check_int(f"schedule.{key}", getattr(sc, key), 2,
                      hint="sections and zero crossings lie between two samples")
        # Counted per steradian, the rays a step renders scale with the zones' solid angle and views_per_step: 1e5
        # (111 x the default) is some 1 GB of samples a step on LCSPCData's 0.21 sr zone at 16 views (3.3 kB a ray,
        # measured at 1e4); 1e9 asked 13.8 GB and failed in the first step. The candidates of every view are kept
        # for the whole run: 1e5 is 5 M of them for 256 views of that zone.
        for key in ("rays_per_sr", "candidate_rays_per_sr"):
            check_in_range(f"schedule.{key}", getattr(sc, key), 0.0, 1e5, unit="per steradian",
                           hint="the memory grows with it")
        # Past the grid's own side, padding puts the coarse samples in space no surface can reach (1e9: none met it).
        check_in_range("schedule.segment_pad_voxels", sc.segment_pad_voxels, 0.0, float(fd.resolution),
                       unit="voxels", hint="at most field.resolution")
        positive = {"field.sharpness_voxels": (fd.sharpness_voxels, "0: no opacity anywhere"),
                    "schedule.window_voxels": (sc.window_voxels, "0: the fine samples all on one point"),
                    "schedule.lr_voxels": (sc.lr_voxels, "0: the grid never moves")}
        for key, (value, why) in positive.items():
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0):
                raise ConfigError(f"{key} {value!r} must be > 0 ({why})")
        # Across the fine window (+-window_voxels around the crossing) the SDF changes by at most window_voxels
        # voxels either side, so a surface met head-on reaches at most the opacity 1 - Phi(-k) / Phi(k) = 1 - e^-k,
        # k = sharpness_voxels x window_voxels (render.section_weights' product telescopes). Below ln 2 no ray is
        # ever an opaque return (opacity > 0.5, as the parts count them) and most of the light is never rendered.
        k = fd.sharpness_voxels * sc.window_voxels
        if k < math.log(2.0):
            raise ConfigError(f"field.sharpness_voxels x schedule.window_voxels = {k:g} must be >= ln 2 = 0.693: a "
                              f"surface met head-on would reach an opacity of only {1 - math.exp(-k):.2g} inside the "
                              f"fine window (the defaults: 2 x 3, 0.998)")


def fast_config() -> FastConfig:
    """The resolved config of the `fast` preset."""
    return FastConfig(
        preset="fast",
        field=FastFieldConfig(),
        schedule=FastScheduleConfig(),
        loss=FastLossConfig(eikonal_weight=0.1, smooth_weight=0.05),
        parts=FastPartsConfig(),
        default_budget_s=120.0,
        time_oversample=1,
        mesh_resolution=256,
        trace_mesh_resolution=128,
    )


__all__ = ["FastFieldConfig", "FastScheduleConfig", "FastLossConfig", "FastConfig", "fast_config", "MOVED"]
