"""The protocol every preset's model implements, and what a run tells it.

`reconstruct_capture` builds a model with the preset's factory (`presets.PRESETS[name].make_model`):

    make_model(scene: SceneData, config: ReconConfig, device: torch.device, plan: RunPlan) -> ReconModel

then `trainer.train` calls `step()` until the step count or the time budget runs out, `extract_mesh` at trace
checkpoints and at the end, and `render_histograms` for the fit picture. The model owns its field, sampler,
renderer, optimiser and schedule; the capture's tensors (scene_data) and the sensor model (forward) are shared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class RunPlan:
    """How long the run will be, so that a model can lay out its schedule (learning rate, coarse-to-fine)."""

    steps: int | None
    """Steps the run will take at most (None: bounded by time only)."""
    budget_s: float | None
    """Training seconds the run may take at most (None: bounded by steps only)."""
    seed: int = 0
    """Seed for every random choice of the model (rays, samples, initialisation)."""

    def progress(self, step: int, elapsed_s: float) -> float:
        """Fraction of the run done, in [0, 1]: the larger of the step and time fractions that apply (0 when
        neither bound is given)."""
        fractions = [0.0]
        if self.steps:
            fractions.append(step / self.steps)
        if self.budget_s:
            fractions.append(elapsed_s / self.budget_s)
        return float(min(1.0, max(fractions)))


@runtime_checkable
class ReconModel(Protocol):
    """A reconstruction in progress."""

    terms: "object"
    """The ModelTerms used (listed in the report)."""

    stochastic_render: bool
    """Whether `render_histograms` samples rays at random (renders differ; the fit check averages several) or is
    deterministic (one render is all there is). A model that does not say is taken for random."""

    def step(self) -> dict:
        """One optimisation step. Returns at least {'loss': float} (the total), plus any named parts."""

    def extract_mesh(self, resolution: int):
        """The current surface as a trimesh.Trimesh in world metres with per-vertex normals from the SDF gradient
        (`vertex_normals` set); `resolution` cells along the longest side of the scene box. Raises
        ReconstructionError when there is no surface."""

    def render_histograms(self, view_ids: Sequence[int]) -> np.ndarray:
        """Expected counts (len(view_ids), Z, B) of the current model for those views (float64, no gradient)."""

    def summary(self) -> dict:
        """JSON-able state worth reporting (e.g. sharpness, albedo, table height)."""
