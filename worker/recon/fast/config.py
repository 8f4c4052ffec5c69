"""Configuration of the `fast` preset: an explicit SDF grid started and bounded by the space-carving hull.

`fast_config()` returns the shared `ReconConfig` with this preset's own sections: `field` (`FastFieldConfig`: hull,
grid, rendering) and `schedule` (`FastScheduleConfig`: rays, samples, optimiser, stopping). Of the shared sections it
uses `loss.eikonal_weight` and `loss.tv_weight` (the grid's Eikonal and smoothness weights), `time_oversample` and
the mesh and trace settings; `rays`, `optim` and `sharpness` belong to the paper preset and are not read, nor are
`dtype` (the grid is float32), `loss.kind` (its own likelihood), `loss.eikonal_points` and `albedo_init`. One set of defaults serves every scene: lengths that should follow the grid are in voxels, physical ones
in metres.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FastFieldConfig:
    """The SDF grid, the hull that starts and bounds it, and how it is rendered."""

    resolution: int = 64
    """Grid nodes along the longest side of the hull's box at the coarse level."""
    refine_after_steps: int = 300
    """Steps at the coarse level before the grid is refined 2x (0: never refine)."""
    box_pad_voxels: float = 3.0
    """Empty margin (coarse voxels) between the hull's bounding box and the grid's walls."""
    hull_resolution: int = 128
    """Cells along the longest side of the space-carving grid."""
    carve_threshold: float = 5.0
    """Detection threshold of the carving's first returns, in noise standard deviations (lower carves less and is
    safer for faint, thin parts)."""
    carve_margin_m: float = 0.002
    """Range (metres) left uncarved in front of every first return."""
    hull_margin_m: float = 0.004
    """How far (metres) the surface may grow outside the carved hull: keeps thin parts that carving shaved."""
    sharpness_voxels: float = 2.0
    """Fixed NeuS opacity sharpness s = sharpness_voxels / voxel (1/metres): the surface is about a voxel thick at
    every level of the grid. Never learned: sharpening past the sample spacing makes runs drift."""
    floor_z: float | None = 0.0
    """Height (metres, world z) below which nothing is solid: the floor the object stands on, which no histogram
    shows (world z = 0 by the convention of the simulator and of LCSPCData's simulated scenes, as for the space-carving
    baseline). Without it the carved hull keeps the object's whole unobservable shadow below it. A `floor_z` in the
    capture's scene record, or a table (named by the capture or detected in a measured one), takes precedence;
    None: no floor."""
    fill_under_overhangs: bool = True
    """Scenes on a table only: the fit (every `band_refresh_steps`, with the cavities) and the mesh fill the hidden
    space between the object's underside and the table (`empty_space.under_overhangs`). Filled in the mesh alone,
    the real pyramid's fit became a hollow shell and its mesh kept shafts under the shell's pinholes (5.27 mm against
    4.37 mm in the 300 s benchmark, benchmarks/RESULTS.md)."""
    thin_sheet_voxels: int = 2
    """Scenes on a table only, on the refined grid: every `band_refresh_steps`, solid sheets thinner than about twice
    this many voxels less than `thin_sheet_band_m` above the table are emptied (`empty_space.thin_near_table`);
    0: off."""
    thin_sheet_band_m: float = 0.09
    """Height (metres) above the table within which thin sheets are emptied. Views from above see a sheet standing on
    the table edge on, and near the table no histogram tells it from the table behind it: on the real pyramid such
    curtains stood up to 8 cm high. A band of one pulse width (41 mm) left them standing; 12 cm began to erode the
    object itself (benchmarks/RESULTS.md)."""
    table_albedo_init: float = 1.0
    """Initial albedo of the table plane (real scenes), relative to the sensor model's signal scale."""


@dataclass
class FastScheduleConfig:
    """Rays, samples, optimiser and stopping rule of the fast preset."""

    candidate_rays_per_sr: float = 5000.0
    """Candidate directions per steradian of each zone, marched once through the hull; those that enter it form the
    pool each step draws from."""
    rays_per_sr: float = 900.0
    """Hull-hitting rays drawn per histogram per step, per steradian of the zone (at least `min_rays`)."""
    min_rays: int = 32
    """Floor on rays per histogram per step."""
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
    """The grid's learning rate decays (cosine, over the fine level's expected steps) to this fraction."""
    fine_steps: int = 1200
    """Steps the fine level's learning-rate decay is laid out over."""
    average_decay: float = 0.99
    """The mesh is extracted from an exponential moving average of the grid, updated after every step with this
    decay (0: the current grid; a level's first steps use a shorter memory, min(decay, (1 + n) / (10 + n)) at its
    n-th update). Averaging over the last ~1 / (1 - decay) steps removes the jitter that the sparse, noisy ray
    gradients leave on the surface at a learning rate still high enough to move it far. Measured on the same fits
    (step-based, one thread), current grid -> average: sphere 1.63 -> 1.56 mm (3,000 steps), cup 3.43 -> 3.36
    (2,400), real pyramid 5.22 -> 5.16 (2,250, learning-rate floor 0.1); the average lags a fast-moving fit (demo
    goblet 3.07 -> 3.48 at 1,200 steps) and catches up once it settles (1.53 -> 1.53 at 2,400)."""
    grad_blur_passes: int = 1
    """Passes of a [1, 2, 1] / 4 filter along each axis over the grid's gradient before the Adam step (a Sobolev-
    type preconditioner: neighbouring nodes move together, so the sparse, noisy ray gradients do not roughen the
    field)."""
    blur_physical: bool = False
    """Keep the blur's physical reach on the refined grid (4x the passes there)."""
    shared_adam: bool = False
    """One second moment for the whole grid instead of one per node (updates stay proportional to the gradient)."""
    albedo_lr: float = 0.02
    """Adam learning rate of the log albedos (object and table)."""
    table_lr_m: float = 2e-4
    """Adam learning rate of a fitted table's height (metres per step)."""
    band_voxels: float = 4.0
    """The Eikonal and smoothness terms act on nodes within this many voxels of the surface."""
    coarse_smooth_height_m: float | None = 0.06
    """Scenes without a table: on the coarse level the smoothness term acts only on nodes less than this height
    (metres) above the floor (`field.floor_z`); the fine level smooths everywhere. None: everywhere on both levels.
    The coarse level decides what the hull leaves unobserved. Near the floor that is the object's base, which only
    the lowest views see, at grazing angles: the smoothness keeps it (without it LCSPCData's sphere has its bottom
    cap cut flat at 2-3 cm). Higher up it is hull left over under overhangs and in openings, which the smoothness
    holds against the data (the built-in lamp's cone of solid under its shade). The 180 s benchmark, everywhere ->
    below 6 cm (benchmarks/RESULTS.md): built-in lamp 2.25 -> 1.24 mm, cup 2.85 -> 2.57, goblet 0.89 -> 0.82,
    sphere 1.23 -> 1.21, pyramid 0.98 -> 0.97; LCSPCData's bunny 1.28 -> 1.36, soap 1.59 -> 1.81, sphere 1.47 ->
    1.46. The 6 cm is a length chosen on these scenes. On a table the empty-space push does this job, and the real
    pyramid lost 0.2 mm with the band (step-based), so table scenes smooth everywhere."""
    reg_points: int = 65536
    """Band nodes drawn per step for the Eikonal and smoothness terms (all of them when the band is smaller)."""
    band_refresh_steps: int = 10
    """Steps between updates of the band of nodes near the surface."""
    empty_pressure: float = 0.2
    """Scenes on a table only (see empty_space.py): each step pushes the surface inward on surface nodes that few
    views look at, by this fraction of the data gradient's rms there (0: off)."""
    pressure_coverage: float = 0.6
    """The push is full where no view looks and fades to nothing where this fraction of the views (or more) has the
    node in its field of view. (On LCSPCData's real pyramid the surface 1 cm or more off the object after a fit
    lay where a median 31% of the views look; the object's own faces, where a median 59% do: the data holds those
    against the push.)"""
    phantom_ratio: float = 0.6
    """Simulated captures (see phantoms.py): surface nodes where the measured photons around the rays' returns are
    below this fraction of the model's, on average over at least `phantom_min_hits` returns, are eroded by one voxel
    every `phantom_every_steps` steps (0: off). On the built-in cup (step-based, one thread) 3.05 mm at 1,200 steps
    against 3.70 mm without it; on the built-in goblet 1.47 mm against 3.48 mm."""
    phantom_every_steps: int = 30
    """Steps over which returns are gathered before each erosion."""
    phantom_min_hits: int = 3
    """Returns a node needs in that time before it can be eroded."""
    phantom_window_bins: int = 3
    """Photons are compared within this many bins either side of a return's bin."""
    open_every_steps: int = 150
    """Simulated captures (see openings.py): every this many steps, propose opening the solid behind the surface
    that the erosion's evidence flags, at each of `open_depths_m`, and keep the best proposal that lowers the
    deviance over all views by `open_min_gain` per bin (0: off). The built-in cup, 600 steps (step-based, one
    thread): 2.71 -> 1.49 mm; its lid, left at 8-11 cm by the erosion alone, goes at step 150."""
    open_depths_m: tuple = (0.02, 0.04, 0.08)
    """How deep (metres) behind the flagged surface each proposal opens the solid."""
    open_keep_m: float = 0.006
    """Solid within this distance (metres) of surface the data supports, or of the floor (`field.floor_z`), is never
    opened (walls behind a lid; a base standing on the floor, which no view sees from below)."""
    open_keep_ratio: float = 0.8
    """Surface nodes whose returns measure at least this fraction of the model's photons are supported."""
    open_passes: int = 3
    """A round's evidence is the returns of the training steps just before it: the last this many passes' worth of
    views (each view about this many times; 48 steps at 256 views and 16 views a step), at most `open_every_steps`."""
    open_min_gain: float = 0.005
    """A proposal is kept only if it lowers the deviance over all views by at least this much per bin. The lids of
    the built-in cup and goblet gain 0.025-0.035 (at 64 and at 256 views); on scenes without phantom surface, proposals
    gained up to 0.0013, and kept, they cut into the object: the top of the built-in lamp's stem (0.0001-0.0002
    per bin), 2 cm into the built-in sphere at step 150 (0.0013; 1.21 -> 1.94 mm at 180 s)."""
    open_min_flagged: int = 50
    """Rounds with fewer flagged nodes than this make no proposals, and render nothing (they count as rounds without
    a kept one). In the 180 s benchmark the scenes without phantom surface flagged 5-46 nodes at step 150 (the
    built-in sphere 160: its proposals gained too little to be kept) and 3-45 later; the cup's and the goblet's lids
    507 and 584. On the lamp, proposals from 4-16 nodes took off the top of its stem."""
    open_patience: int = 2
    """Rounds in a row without a kept proposal after which no more are made (a round with proposals costs about 25
    steps, one without them nothing)."""
    patience_steps: int = 600
    """After the last refinement, the run reports `converged` (and, with `early_stop`, ends) once the data term,
    averaged over windows of patience/6 steps, has not beaten its best window by `min_rel_improvement` for this
    many steps (`plateau.Plateau`). Measured on LCSPCData's simulated scenes (step-based runs): the bunny stops near
    2,400 steps with the Chamfer it ends a 3,000-step run with; the soap near 2,250 steps at 1.9 mm, where a 4,500-step
    run drifts to 2.2 mm."""
    min_rel_improvement: float = 0.001
    """Relative improvement of the windowed data term that counts as progress."""


def fast_config():
    """The resolved `ReconConfig` of the `fast` preset."""
    from spadscan.worker.recon.config import LossConfig, ReconConfig

    return ReconConfig(
        preset="fast",
        model_factory="spadscan.worker.recon.fast.model:make_fast_model",
        field=FastFieldConfig(),
        schedule=FastScheduleConfig(),
        loss=LossConfig(kind="nll", eikonal_weight=0.1, eikonal_points=0, tv_weight=0.05),
        default_budget_s=120.0,
        time_oversample=1,
        mesh_resolution=256,
        trace_mesh_resolution=128,
        unused_sections=("rays", "optim", "sharpness"),
        # The grid is fitted in float32 (its sums that need more are float64 inside), by its own likelihood.
        unused_fields=("dtype", "loss.kind", "loss.eikonal_points", "albedo_init"),
    )


__all__ = ["FastFieldConfig", "FastScheduleConfig", "fast_config"]
