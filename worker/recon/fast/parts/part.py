"""What a mechanism of the `fast` preset is: a `Part` with its own config, the scenes it applies to, and hooks that
`FastModel.step` calls at fixed points of every step (see the model for the loop, and `parts/__init__.py` for the
parts in the order their hooks run).

A part sees the model through `Model` below: it reads the grid, the step counters and the problem being fitted,
and changes the model only in its hooks and through the model's services (`project`, `refine`, `jumped`,
`restart`, `set_albedo`, `counts_albedo`, `deviance_all_views`). State that a mechanism must drop when the surface
jumps is dropped by that part's own `on_jump`, never by the part that made the jump.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import torch

from spadscan.protocol.errors import ConfigError

from ..grid_field import GridField
from ..hull import HullConstraint
from ..problem import FastProblem
from ..sampler import HullRays


class Model(Protocol):
    """What a part may use of the model it is registered with (`FastModel`)."""

    problem: FastProblem
    """What is fitted: counts, poses, sensor model, hull, floor, table plane."""
    config: object
    """The run's `FastConfig` (every part's settings, under `parts`)."""
    field: GridField
    """The SDF grid being fitted (a new object after each refinement)."""
    constraint: HullConstraint
    """The carved hull's bound on the field (the field starts on it)."""
    rays: HullRays
    """The candidate rays that enter the hull (`rays.missed`: those that miss it, on a table)."""
    on_table: bool
    """The object stands on a table (the scene has a table plane; the floor is its top)."""
    device: torch.device
    seed: int
    """The run's seed."""
    n_views: int
    views_per_step: int
    steps: int
    """Steps taken (during a step: before it; in `after_step`: including it)."""
    level_steps: int
    """Steps taken on the current level of the grid, counted like `steps`."""
    level: int
    """Refinements done so far (0: the coarse grid)."""
    last_level: bool
    """The grid is at its last level (refined, or never to be refined)."""

    def project(self) -> None:
        """Clamp the field into the hull, where the hull projection part runs (after any edit that may leave it)."""

    def refine(self) -> None:
        """Refine the grid 2x now (calls every part's `on_refine`)."""

    def jumped(self) -> None:
        """Tell every part (and the regularisers' band) that the surface just moved in one jump."""

    warm_started: bool
    """The field came from another fit (a live fit's rebuild), not from the hull."""

    def albedo(self) -> float:
        """The object's fitted albedo."""

    def set_albedo(self, albedo: float) -> None:
        """Set the object's albedo (> 0)."""

    def restart(self) -> None:
        """Start the fit again from the hull on the coarse grid, with the parts made afresh (see FastModel)."""

    def counts_albedo(self) -> float | None:
        """The albedo at which the current field renders as many photons as the views measured (None: no signal)."""

    def deviance_all_views(self, seed: int) -> float:
        """Deviance per bin over every view (of a capture of more than 256, its 256 spread set-up views) under the
        current field, with the rays that `seed` draws."""


@dataclass
class PartConfig:
    """What every part's config holds: whether it runs (where it applies to the scene)."""

    enabled: bool = True
    """Run this part where it applies (false: switch the mechanism off, e.g. for an ablation)."""

    def check(self, key: str) -> None:
        """Raise ConfigError naming `key`.FIELD for settings the part cannot use; a part adds its own checks."""
        if not isinstance(self.enabled, bool):
            raise ConfigError(f"{key}.enabled {self.enabled!r} must be true or false")


@dataclass
class StepRecord:
    """What one step has rendered, for the hooks that run after the rendering.

    views (n,): the step's views; rates (n, Z, B): their photon rates (no gradient); hits: the opaque returns of the
    rendered rays (histogram (m,), point (m, 3) world metres, range (m,) metres) when a part asked for them, else
    None; data: the data term (deviance per bin, with gradient); smooth_layers: the regularisers' smoothness counts
    only in the lowest this many z layers of the grid (None: everywhere), as a part may set it."""

    views: torch.Tensor
    rates: torch.Tensor
    hits: tuple | None
    data: torch.Tensor
    smooth_layers: int | None = None
    cache: dict = field(default_factory=dict)
    """Per-step results that several parts read (e.g. the returns' photon ratios, by window)."""


class Part:
    """One mechanism of the fast preset (see the module). Subclasses set `name` (their key under `parts.` in the
    config) and override the hooks they need; the others do nothing."""

    name: ClassVar[str] = ""
    wants_returns: bool = False
    """Whether this step's rendering must record the opaque returns (`StepRecord.hits`) for this part."""

    def __init__(self, config: PartConfig, model: Model):
        self.config = config

    @classmethod
    def left_out(cls, config: PartConfig, model: Model) -> str | None:
        """Why the part does not apply to the model's scene (one line), or None where it does."""
        return None

    # ---- the hooks, in the order a step calls them -----------------------------------------------------------
    def before_step(self, model: Model) -> None:
        """Before the step draws its views: changes of the grid itself (a finer level, fills)."""

    def before_loss(self, model: Model, step: StepRecord) -> None:
        """The step's views are rendered and its data term computed: read what the rendering shows, or shape the
        regularisers (`step.smooth_layers`)."""

    def after_gradient(self, model: Model, grad: torch.Tensor) -> torch.Tensor:
        """The data term's gradient on the grid (1, 1, nz, ny, nx), before the regularisers' gradient is added and
        the optimiser steps: return it, changed or replaced."""
        return grad

    def after_step(self, model: Model, step: StepRecord) -> None:
        """The optimiser has stepped and the step is counted (`model.steps`, `model.level_steps` include it)."""

    # ---- events ----------------------------------------------------------------------------------------------
    def on_refine(self, model: Model) -> None:
        """The grid has just been refined 2x (`model.field` is the new one, `model.level_steps` is 0)."""

    def on_jump(self, model: Model) -> None:
        """The surface has moved in one jump, not by a gradient step: drop state that followed the old surface."""

    # ---- the report ------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """JSON-able figures of what the part did, for report.json (its config is reported beside them)."""
        return {}


__all__ = ["Part", "PartConfig", "StepRecord"]
