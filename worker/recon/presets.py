"""The one registry of reconstruction presets: name -> its resolved config and its model factory.

Every preset is imported here, at the top; nothing else looks a preset up by name. (`config.PRESET_NAMES` repeats the
names for code that must not import torch; a test keeps the two in step.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from .config import ReconConfig
from .errors import ReconstructionError
from .fast.config import fast_config
from .fast.model import make_fast_model
from .paper.config import paper_config
from .paper.model import make_paper_model


@dataclass(frozen=True)
class Preset:
    """A reconstruction method: its resolved config and the function that builds its model."""

    name: str
    config: Callable[[], ReconConfig]
    """() -> the preset's resolved config (a fresh copy each call)."""
    make_model: Callable
    """(scene: SceneData, config, device, plan: RunPlan) -> a model implementing `model_api.ReconModel`."""
    summary: str
    """One line for --help and the report."""


PRESETS: dict[str, Preset] = {
    "paper": Preset("paper", paper_config, make_paper_model,
                    "the published method: an MLP SDF, 300K steps nominal (hours on a GPU)"),
    "fast": Preset("fast", fast_config, make_fast_model,
                   "an SDF grid started and bounded by the space-carving hull: good meshes in minutes on a CPU"),
}


def preset(name: str) -> Preset:
    """The preset called `name`; a one-line error lists the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ReconstructionError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})") from None


def preset_config(name: str) -> ReconConfig:
    """The resolved config of preset `name` (a fresh copy)."""
    return preset(name).config()


def make_model(scene, config: ReconConfig, device, plan):
    """The model of `config`'s preset for a loaded capture."""
    return preset(config.preset).make_model(scene, config, device, plan)


__all__ = ["Preset", "PRESETS", "preset", "preset_config", "make_model"]
