"""Scenes and model pieces that several of the worker's test modules build the same way."""

from __future__ import annotations

import torch

from spadscan.worker.recon.forward import ModelTerms, TransientForward
from spadscan.worker.pulse import pulse_kernel

PAPER_SMALL = {"rays.rays_per_view": 48, "rays.importance_rays_per_view": 16, "rays.samples_per_ray": 32,
               "rays.importance_samples": 16, "field.width": 64, "field.layers": 4, "field.skip_layers": [2],
               "optim.lr": 1e-3}
"""The paper's method at a size a unit test can afford (the network and the ray counts shrink, nothing else)."""

FAST_SMALL = {"field.resolution": 24, "field.hull_resolution": 48, "parts.refinement.after_steps": 4,
              "schedule.views_per_step": 4, "schedule.rays_per_sr": 300.0, "schedule.candidate_rays_per_sr": 2000.0}
"""The fast preset at a size a unit test can afford (a coarse grid refined after 4 steps, few views and rays)."""

CUDA_CLI_SMALL = {"field.resolution": 32, "parts.refinement.after_steps": 60}
"""The CUDA command line test's --set overrides: a finer coarse grid, refined after 60 steps."""

CUDA_SMALL = {**FAST_SMALL, **CUDA_CLI_SMALL}
"""The CUDA tests' fast preset: FAST_SMALL with the command line test's grid and refinement."""


def blank_histograms(model) -> None:
    """Replace a fast model's histograms with background alone (Poisson, seed 0): every return it renders is then
    one the histograms do not show."""
    bg = model.problem.background[..., None] * model.problem.cycles[:, None, None]
    model.problem.counts = torch.poisson(bg.expand_as(model.problem.counts),
                                         generator=torch.Generator().manual_seed(0))


def cylinder_mesh():
    """A cylinder of radius 4 cm and height 8 cm standing on z = 0, a little off the axis."""
    import trimesh

    mesh = trimesh.creation.cylinder(radius=0.04, height=0.08, sections=48)
    mesh.apply_translation([0.005, -0.004, 0.04])
    return mesh


def sensor_forward(sensor, dtype=torch.float64, pileup=True, oversample=2, crosstalk=None) -> TransientForward:
    """The sensor model with the preset's own pulse; crosstalk on for multi-zone sensors unless told otherwise."""
    terms = ModelTerms(pileup=pileup, crosstalk=sensor.n_zones > 1 if crosstalk is None else crosstalk,
                       table=False, tv=False, reference_pulse=False)
    kernel, origin, _ = pulse_kernel(sensor, None, oversample)
    return TransientForward(sensor, terms, torch.tensor(kernel, dtype=dtype), origin, oversample)
