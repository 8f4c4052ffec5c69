"""The `paper` preset: the reference method as published (docs/paper_preset.md), on the shared parts."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import LossConfig, OptimConfig, RaysConfig, ReconConfig, SharpnessConfig


@dataclass
class MLPFieldConfig:
    """An MLP signed distance field with positional encoding and geometric (sphere) initialisation."""

    layers: int = 8
    """Hidden layers."""
    width: int = 256
    """Units per hidden layer."""
    frequencies: int = 6
    """Positional-encoding octaves: sin and cos of 2^k x for k < frequencies, besides x itself."""
    skip_layers: tuple[int, ...] = (4,)
    """Layers whose input is concatenated with the encoded point again."""
    softplus_beta: float = 100.0
    """Sharpness of the softplus activations."""
    weight_norm: bool = True
    """Weight normalisation of every linear layer."""
    init_radius: float = 0.5
    """Radius of the initial sphere, as a fraction of the scene sphere's radius."""


@dataclass
class PaperSchedule:
    """How the paper's run is laid out in time."""

    chunk_points: int | None = None
    """Samples rendered with gradient at once; larger batches are rendered in chunks by a two-pass, exact
    back-propagation (first the histograms, then each chunk's share of the gradient) to bound memory. None: as many
    as fit in `memory_gb` (about 70 kB per sample for the 8 x 256 network in float32)."""
    memory_gb: float | None = None
    """Memory the rendering graph may take; None: 3 GB on CPU, half the free memory on a GPU."""


def paper_config() -> ReconConfig:
    """The paper's settings: 512 + 64 rays and 256 + 32 samples per ray, 2 views per step, L2 on histograms
    normalised by cycles + 0.1 Eikonal (+ TV on real data), Adam 5e-4 with cosine decay over 300K steps."""
    return ReconConfig(
        preset="paper",
        model_factory="spadscan.worker.recon.paper.model:make_paper_model",
        field=MLPFieldConfig(),
        schedule=PaperSchedule(),
        rays=RaysConfig(rays_per_view=512, importance_rays_per_view=64, samples_per_ray=256, importance_samples=32,
                        views_per_batch=2),
        loss=LossConfig(kind="l2", eikonal_weight=0.1, tv_weight=0.01),
        optim=OptimConfig(lr=5e-4, nominal_steps=300_000, warmup_steps=5000, lr_floor=0.05),
        sharpness=SharpnessConfig(init=20.0, learned=True, min=1.0, max=1.0e4, upsample=64.0),
        mesh_resolution=256,
        default_steps=300_000,
        unused_fields=("early_stop",),  # the paper's method runs its whole schedule: it never reports converged
    )
