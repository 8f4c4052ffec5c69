"""The mechanisms of the `fast` preset, one module each: its config, the scenes it applies to, and its hooks.

`PARTS` lists them in the order their hooks run within a step (FastModel.step calls every hook of every part it
holds in this order; see `part.Part` for the hooks):

  refinement        before_step   refine the grid 2x once, after the coarse level's steps
  hull_projection   after_step    clamp the field into the carved hull (and after refinement)
  table             (renderer)    on a table, render its plane under the object, fit its albedo and height
  cavities          before_step   every few steps, fill pockets no view sees into (on a table: also under the object)
  thin_sheets       before_step   on a table, every few steps of the last level, empty thin curtains near the table
  coarse_smoothing  before_loss   without a table, the coarse level smooths only near the floor (with refinement)
  openings          before_loss   gather returns before a round, then every few steps open the solid behind phantom
                    after_step    surface where the likelihood over all views prefers it (before the erosion moves it)
  erosion           before_loss   gather the returns' photon ratios, and every few steps erode surface they do not
                    after_step    show (simulated captures)
  blur              after_gradient  blur the data term's gradient
  unseen            after_gradient  without a table, keep the data gradient's moving average (after the blur); on
                    after_step    the last level relax the air side of surface no ray reaches towards its neighbours
  empty_space       after_gradient  every scene: push surface inward where the data cannot hold it (after the blur):
                                  on a table where few views look, without one where no view hears a return
  average           after_step    keep the moving average of the grid that meshes come from
  plateau           after_step    test whether the data term has stopped improving on the last level
  dark_restart      after_step    once, on the coarse level: an albedo fallen low marks a dark object, whose fit
                                  starts again from the hull with its albedo read from the counts

Each part's config is `parts.NAME` in the preset's config (`FastPartsConfig`); `parts.NAME.enabled=false` switches
it off. A part that is enabled but does not apply to the scene (say, erosion on a measured capture) says why in the
report, as one switched off does.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from .average import Average, AverageConfig
from .blur import BlurConfig, GradientBlur
from .cavities import Cavities, CavitiesConfig
from .coarse_smoothing import CoarseSmoothing, CoarseSmoothingConfig
from .dark_restart import DarkRestart, DarkRestartConfig
from .empty_space import EmptySpaceConfig, EmptySpacePush
from .erosion import Erosion, ErosionConfig
from .hull_projection import HullProjection, HullProjectionConfig
from .openings import Openings, OpeningsConfig
from .part import Model, Part, PartConfig, StepRecord
from .plateau import PlateauConfig, PlateauPart
from .refinement import Refinement, RefinementConfig
from .table import TableConfig, TableFit
from .thin_sheets import ThinSheets, ThinSheetsConfig
from .unseen import UnseenConfig, UnseenRelaxation

PARTS: tuple[type[Part], ...] = (Refinement, HullProjection, TableFit, Cavities, ThinSheets, CoarseSmoothing, Openings,
                                 Erosion, GradientBlur, UnseenRelaxation, EmptySpacePush, Average, PlateauPart,
                                 DarkRestart)
"""Every part, in the order its hooks run."""


@dataclass
class FastPartsConfig:
    """One section per part of the fast preset (see the parts' modules), in the order their hooks run."""

    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    hull_projection: HullProjectionConfig = field(default_factory=HullProjectionConfig)
    table: TableConfig = field(default_factory=TableConfig)
    cavities: CavitiesConfig = field(default_factory=CavitiesConfig)
    thin_sheets: ThinSheetsConfig = field(default_factory=ThinSheetsConfig)
    coarse_smoothing: CoarseSmoothingConfig = field(default_factory=CoarseSmoothingConfig)
    openings: OpeningsConfig = field(default_factory=OpeningsConfig)
    erosion: ErosionConfig = field(default_factory=ErosionConfig)
    blur: BlurConfig = field(default_factory=BlurConfig)
    unseen: UnseenConfig = field(default_factory=UnseenConfig)
    empty_space: EmptySpaceConfig = field(default_factory=EmptySpaceConfig)
    average: AverageConfig = field(default_factory=AverageConfig)
    plateau: PlateauConfig = field(default_factory=PlateauConfig)
    dark_restart: DarkRestartConfig = field(default_factory=DarkRestartConfig)

    def check(self) -> None:
        """Each part's config checked, errors naming `parts.NAME.FIELD`."""
        for f in fields(self):
            getattr(self, f.name).check(f"parts.{f.name}")


def build_parts(config: FastPartsConfig, model: Model) -> tuple[list[Part], dict[str, str]]:
    """(the parts that run on this model's scene, in hook order; {name: why} for the others)."""
    parts, left_out = [], {}
    for cls in PARTS:
        cfg = getattr(config, cls.name)
        why = f"switched off (parts.{cls.name}.enabled=false)" if not cfg.enabled else cls.left_out(cfg, model)
        if why:
            left_out[cls.name] = why
        else:
            parts.append(cls(cfg, model))
    return parts, left_out


__all__ = ["PARTS", "FastPartsConfig", "build_parts", "Part", "PartConfig", "StepRecord", "Model"]
