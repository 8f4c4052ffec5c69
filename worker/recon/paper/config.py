"""The `paper` preset's config: the reference method as published (docs/paper_preset.md), on the shared run
settings of `ReconConfig`."""

from __future__ import annotations

from dataclasses import dataclass, field
from operator import attrgetter
from typing import ClassVar

from spadscan.protocol.errors import ConfigError

from ..config import ReconConfig, check_int


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
    """How the paper's rendering is cut into chunks to bound memory."""

    chunk_points: int | None = None
    """Samples rendered with gradient at once; larger batches are rendered in chunks by a two-pass, exact
    back-propagation (first the histograms, then each chunk's share of the gradient) to bound memory. None: as many
    as fit in `memory_gb` (about 70 kB per sample for the 8 x 256 network in float32)."""
    memory_gb: float | None = None
    """Memory the rendering graph may take; None: 3 GB on CPU, half the free memory on a GPU."""


@dataclass
class RaysConfig:
    """How rays and samples are drawn."""

    rays_per_view: int = 512
    """Rays stratified uniformly in solid angle per view, split evenly over the zones of a multi-zone sensor."""
    importance_rays_per_view: int = 64
    """Extra rays per view drawn in the cells where the view's rays saw most signal the last time it was rendered
    for training (uniformly the first time); balance-heuristic weights keep the estimate unbiased."""
    min_rays_per_zone: int = 16
    """Floor on stratified rays per zone when `rays_per_view` is split over many zones."""
    samples_per_ray: int = 256
    """Stratified samples per ray between the ray's entry into and exit from the scene sphere (at least 2: the
    opacity lives on the intervals between samples)."""
    importance_samples: int = 32
    """Extra samples per ray drawn from the coarse opacity (inverse-CDF, no gradient)."""
    views_per_batch: int = 2
    """Views rendered per optimisation step."""
    near_m: float = 0.01
    """Samples closer than this to the sensor (metres) are never drawn."""


@dataclass
class PaperLossConfig:
    """What the optimiser minimises."""

    kind: str = "l2"
    """'l2': squared error between measured counts / cycles and predicted detections per cycle (the paper's loss);
    'nll': negative log-likelihood (multinomial with pile-up, or Poisson)."""
    eikonal_weight: float = 0.1
    """Weight of mean (|grad f| - 1)^2."""
    eikonal_points: int = 512
    """Random points in the scene sphere added to the ray samples for the Eikonal term (and where the TV term is
    taken); 0: the Eikonal term on the ray samples alone (measured data then needs tv_weight 0 too)."""
    tv_weight: float = 0.01
    """Weight of the normal-smoothness (total variation) term; used only where the terms say `tv` (real data)."""


@dataclass
class OptimConfig:
    """Adam with linear warm-up and cosine decay."""

    lr: float = 5e-4
    """Peak learning rate."""
    nominal_steps: int = 300_000
    """Steps the schedule is laid out for when the run gives no step count (the paper's 300K)."""
    warmup_steps: int = 5000
    """Linear warm-up steps (shortened to 2% of the horizon on short runs)."""
    lr_floor: float = 0.05
    """The cosine decays to this fraction of `lr`."""


@dataclass
class SharpnessConfig:
    """Opacity sharpness s of the NeuS-style renderer, in 1 / (scene half-size) units."""

    init: float = 20.0
    """Initial s."""
    learned: bool = True
    """Whether s is optimised (the paper) or fixed."""
    min: float = 1.0
    """Lower clamp."""
    max: float = 1.0e4
    """Upper clamp (the renderer stays finite far past it; see tests)."""
    upsample: float = 64.0
    """Sharpness floor used only to place importance samples."""


@dataclass
class PaperConfig(ReconConfig):
    """The `paper` preset's resolved config: the shared run settings, its MLP field, rays, loss, optimiser and
    sharpness."""

    rays: RaysConfig = field(default_factory=RaysConfig)
    """Ray and sample counts."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser and learning-rate schedule."""
    sharpness: SharpnessConfig = field(default_factory=SharpnessConfig)
    """Opacity sharpness."""
    dtype: str = "float32"
    """Tensor dtype of the optimisation ('float32' or 'float64')."""
    albedo_init: float = 1.0
    """Initial (learned) Lambertian albedo of the object and of the table."""

    inert: ClassVar[tuple[str, ...]] = ("early_stop",)  # the method runs its whole schedule: it never converges
    choices: ClassVar[dict[str, tuple]] = {"dtype": ("float32", "float64"), "loss.kind": ("l2", "nll")}

    def tensor_dtype(self) -> str:
        return self.dtype

    def check(self) -> None:
        """The shared checks, then one-line errors for values the model cannot run with (they would otherwise
        crash it with a traceback after the capture is loaded)."""
        super().check()
        # A ray needs two samples to hold one interval of opacity; the rest are counts of things a step needs.
        positive_ints = {"rays.rays_per_view": 1, "rays.min_rays_per_zone": 1, "rays.views_per_batch": 1,
                         "rays.samples_per_ray": 2, "field.layers": 1, "field.width": 1, "optim.nominal_steps": 1}
        for key, least in positive_ints.items():
            check_int(key, attrgetter(key)(self), least)
        # The sharpness and the albedos are learned as logarithms (0 has none); softplus divides by its beta; a zero
        # learning rate or initial sphere leaves nothing to fit.
        for key in ("sharpness.init", "sharpness.min", "albedo_init", "optim.lr", "field.softplus_beta",
                    "field.init_radius"):
            value = attrgetter(key)(self)
            if not value > 0:
                raise ConfigError(f"{key} {value!r} must be > 0")
        if self.sharpness.max < self.sharpness.min:
            raise ConfigError(f"sharpness.max {self.sharpness.max!r} must be >= sharpness.min {self.sharpness.min!r}")
        if not 0 <= self.optim.lr_floor <= 1:
            raise ConfigError(f"optim.lr_floor {self.optim.lr_floor!r} must be in [0, 1] (a fraction of optim.lr)")


def paper_config() -> PaperConfig:
    """The paper's settings: 512 + 64 rays and 256 + 32 samples per ray, 2 views per step, L2 on histograms
    normalised by cycles + 0.1 Eikonal (+ TV on real data), Adam 5e-4 with cosine decay over 300K steps."""
    return PaperConfig(
        preset="paper",
        field=MLPFieldConfig(),
        schedule=PaperSchedule(),
        loss=PaperLossConfig(kind="l2", eikonal_weight=0.1, eikonal_points=512, tv_weight=0.01),
        rays=RaysConfig(rays_per_view=512, importance_rays_per_view=64, samples_per_ray=256, importance_samples=32,
                        views_per_batch=2),
        optim=OptimConfig(lr=5e-4, nominal_steps=300_000, warmup_steps=5000, lr_floor=0.05),
        sharpness=SharpnessConfig(init=20.0, learned=True, min=1.0, max=1.0e4, upsample=64.0),
        mesh_resolution=256,
        default_steps=300_000,
    )


__all__ = ["MLPFieldConfig", "PaperSchedule", "RaysConfig", "PaperLossConfig", "OptimConfig", "SharpnessConfig",
           "PaperConfig", "paper_config"]
