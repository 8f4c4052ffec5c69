"""The carved hull as a constraint: after every optimiser step (and every refinement) the field is clamped onto

    field >= max(hull_sdf - margin, floor_z - z)

(`hull.HullConstraint`): the solid stays inside the hull grown by `field.hull_margin_m` and above the floor. Carving
keeps everything no histogram proves empty, so the object lies inside the hull, and what the data cannot decide
never grows outside it; the margin keeps thin parts that carving shaved. (The field also starts on that bound,
whether this part runs or not.) Nodes held at the bound are left out of the regularisers' band: the projection
decides them, and the kink where the bound takes over is no roughness of the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

from .part import Model, Part, PartConfig, StepRecord


@dataclass
class HullProjectionConfig(PartConfig):
    """Whether the field is held inside the carved hull (its margin is `field.hull_margin_m`)."""


class HullProjection(Part):
    """Projects the field onto the hull's bound after every step and after refinement (`Model.project`)."""

    name = "hull_projection"

    def after_step(self, model: Model, step: StepRecord) -> None:
        model.project()

    def on_refine(self, model: Model) -> None:
        model.project()


__all__ = ["HullProjection", "HullProjectionConfig"]
