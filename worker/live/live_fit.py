"""The live model of a scan: fitted on the views published so far, rebuilt as views arrive, never from scratch.

Each rebuild loads the capture as it stands (every published view), builds the `fast` problem on it (a new space
carving: more views carve a tighter hull) and a new model, and warm-starts that model from the previous one's field
(`FastModel.warm_start`): the old surface where the old grid covers the new one, never outside the new hull, at the
old model's level of refinement. So the views in use grow while the fit goes on from where it was.

While the scan is young, a rebuild goes back to the coarse level instead (warm, from the live surface) each time the
views have grown enough (`recoarse.RecoarsePolicy`: the first views see the object from one side only).

A scan of more than MAX_SETUP_VIEWS views is carved from a spread subset of them (`carving.view_subset`); each rebuild
keeps the views the last one carved from where it can, so that the hull changes with the views that arrived, not
with a new choice of views.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from spadscan.protocol.errors import SpadscanError

from ..recon.config import ReconConfig
from ..recon.errors import ReconstructionError
from ..recon.model_api import RunPlan
from ..recon.presets import make_model, preset
from ..recon.scene_data import SceneData, load_scene
from ..reconstruct import check_returns
from .keep import LiveState, scalars_of
from .recoarse import RecoarsePolicy
from .snapshot import FieldSnapshot, GridSnapshot, LiveSnapshot

HISTORY = 3
"""Field snapshots kept for ranking views (the disagreement between recent fields)."""
RATE_WINDOW = 10
"""Training calls the recent step rate is measured over (`LiveFit.recent_steps_per_s`)."""


def grid_snapshot(field) -> GridSnapshot:
    """A GridField's values as plain numpy (float32 (nz, ny, nx), origin (3,), voxel)."""
    return GridSnapshot(sdf=field.sdf.detach()[0, 0].float().cpu().numpy().copy(),
                        origin=field.origin.detach().double().cpu().numpy().copy(), voxel_m=float(field.voxel))


class LiveFit:
    """A growing fit of one capture. `rebuild()` refits on every published view (warm), `train(until)` steps."""

    def __init__(self, capture: Path, config: ReconConfig, device: torch.device, seed: int,
                 log: Callable[[str], None], recoarse: RecoarsePolicy = RecoarsePolicy()):
        self.capture, self.config, self.device, self.seed, self.log = Path(capture), config, device, int(seed), log
        self.recoarse = recoarse
        self.coarse_views = 0
        """Views the coarse level last began with."""
        self.recoarsened = 0
        """Rebuilds that re-entered the coarse level."""
        self.dtype = torch.float64 if config.tensor_dtype() == "float64" else torch.float32
        self.model = None
        self.scene: SceneData | None = None
        self.steps = 0
        """Steps over every model of this fit."""
        self.rebuilds = 0
        self.rebuild_s = 0.0
        """Wall seconds spent loading the capture and building models."""
        self.train_s = 0.0
        self.recent: deque[tuple[int, float]] = deque(maxlen=RATE_WINDOW)
        """(steps, wall seconds) of the last training calls: the rate at the model's current level."""
        self.history: deque[FieldSnapshot] = deque(maxlen=HISTORY)
        self.not_yet: str | None = None
        """Why the last rebuild could not fit the views so far (None once one did), for the live status."""
        self.diverged_views = -1
        """Views in use when the live fit last diverged (`restart`); -1 before."""

    @property
    def views_used(self) -> int:
        return 0 if self.scene is None else self.scene.n_views

    def rebuild(self, views_planned: int | None = None) -> bool:
        """Refit on every view published now, warm from the current model (at its level, or back at the coarse
        level: `RecoarsePolicy`; `views_planned` is the scan's plan, None when unknown). False (the current model
        kept, the reason logged) when the views so far cannot be fitted yet (too few to carve a hull, say)."""
        t0 = time.perf_counter()
        try:
            scene = load_scene(self.capture, self.device, self.dtype)
            # The final run's own test: views that hold nothing above the noise would be fitted as a noise mesh,
            # published as "following the scan" and ranked views from, for a capture the final run then refuses.
            check_returns(self.capture, scene)
            plan = RunPlan(steps=None, budget_s=None, seed=self.seed)
            kept = self.setup_views()
            # A large capture's set-up reads a spread subset of its views: kept from the last rebuild where it can,
            # so that each rebuild carves from nearly the same views (view_subset.spread_views).
            model = (make_model(scene, self.config, self.device, plan) if kept is None else
                     preset(self.config.preset).make_model(scene, self.config, self.device, plan,
                                                           keep_setup_views=kept))
            recoarse = self.model is None or self.recoarse.due(self.coarse_views, scene.n_views, views_planned)
            if self.model is not None:
                level, level_steps = (0, 0) if recoarse else (self.model.level, self.model.level_steps)
                model.warm_start(self.model.mesh_field(), level, level_steps)
        except SpadscanError as exc:
            self.not_yet = f"no live fit yet: {exc}"
            self.log(f"live: cannot fit the views so far yet ({exc}); trying again with more")
            return False
        finally:
            self.rebuild_s += time.perf_counter() - t0
        if recoarse:
            self.coarse_views = scene.n_views
            self.recoarsened += self.model is not None
        self.model, self.scene, self.not_yet = model, scene, None
        self.rebuilds += 1
        return True

    def setup_views(self) -> np.ndarray | None:
        """Indices of the views the current model's set-up read (every view of a capture of up to MAX_SETUP_VIEWS
        views, else its spread subset: `FastProblem.setup_views`), or None before a model or for a model without
        that set-up."""
        problem = getattr(self.model, "problem", None)
        if self.scene is None or problem is None or not hasattr(problem, "setup_views"):
            return None
        views = problem.setup_views
        return np.arange(self.scene.n_views) if views is None else views.detach().cpu().numpy()

    def train(self, until: float) -> int:
        """Step the model until `time.monotonic()` reaches `until` (at least one step); returns the steps taken."""
        if self.model is None:
            return 0
        n = 0
        t0 = time.perf_counter()
        while self._step():
            n += 1
            if time.monotonic() >= until:
                break
        seconds = time.perf_counter() - t0
        self.train_s += seconds
        self.recent.append((n, seconds))
        self.steps += n
        return n

    def train_steps(self, n: int) -> int:
        """Up to `n` steps, fewer once the model has converged (a live job trains no further then); returns the steps
        taken. For benchmarks, which count steps where a live job counts seconds."""
        if self.model is None:
            return 0
        t0 = time.perf_counter()
        taken = 0
        while taken < n and not self.model.converged and self._step():
            taken += 1
        self.train_s += time.perf_counter() - t0
        self.steps += taken
        return taken

    def _step(self) -> bool:
        """One step of the model; False when it diverged (a non-finite loss), after `restart`."""
        try:
            self.model.step()
        except ReconstructionError as exc:
            self.restart(exc)
            return False
        return True

    def restart(self, exc: ReconstructionError) -> None:
        """After a diverged step: the live fit starts again, cold, from the carved hull of the same views, rather than
        failing the live job (the scan still gets its final run). Diverged again on those views, the live model is
        dropped (`not_yet` says why) until a refit on more views; the final run then starts from the hull."""
        self.history.clear()
        again = self.diverged_views == self.views_used
        self.diverged_views = self.views_used
        self.model = None
        if again:
            self.not_yet = f"no live fit: it diverged twice on {self.views_used} views ({exc})"
            self.log(f"live: {self.not_yet}; fitting again when more views arrive")
            return
        self.log(f"live: the live fit diverged ({exc}): starting it again from the carved hull")
        self.rebuild()

    @property
    def converged(self) -> bool:
        return self.model is not None and bool(self.model.converged)

    def steps_per_s(self) -> float | None:
        return self.steps / self.train_s if self.train_s > 0 and self.steps else None

    def recent_steps_per_s(self) -> float | None:
        """Steps per wall second over the last RATE_WINDOW training calls (the current level's rate: a fine step
        costs several coarse ones), or None before any."""
        steps, seconds = sum(n for n, _ in self.recent), sum(s for _, s in self.recent)
        return steps / seconds if seconds > 0 and steps else None

    def mesh(self, resolution: int):
        """The current surface (trimesh, world metres); SpadscanError when there is none yet."""
        return self.model.extract_mesh(resolution)

    def remember(self) -> None:
        """Keep a snapshot of the current field for `snapshot` (the last HISTORY are kept)."""
        if self.model is not None:
            self.history.append(FieldSnapshot(grid_snapshot(self.model.mesh_field()), self.steps, self.views_used))

    def snapshot(self) -> LiveSnapshot | None:
        """The state handed to view ranking, or None before the first model."""
        if self.model is None:
            return None
        if not self.history or self.history[-1].step != self.steps:
            self.remember()
        p = self.model.problem
        return LiveSnapshot(fields=list(self.history), hull=grid_snapshot(p.hull),
                            poses=self.scene.poses.detach().double().cpu().numpy().copy(), sensor=self.scene.sensor,
                            floor_z=p.floor_z, converged=self.converged,
                            notes={"steps": self.steps, "views_used": self.views_used})

    @property
    def continuable(self) -> bool:
        """Whether the final run should continue from this fit: it has left the coarse level (`last_level`) and
        made as many steps on its last level as the coarse level takes. Before that it is no better a start than
        the carved hull (below), and a polish of a few seconds cannot finish it."""
        model = self.model
        if model is None or not model.last_level:
            return False
        refinement = model.part("refinement")
        return refinement is None or model.level_steps >= refinement.config.after_steps

    def warm_factory(self, from_live: bool) -> Callable:
        """A model factory (scene, config, device, plan) -> model for the final reconstruction: the preset's model
        of the complete capture, warm-started from this fit where `from_live` (the final run continues from the live
        state; only a `continuable` fit can), else that model as it starts, from the carved hull.

        A fit still on its coarse level is a worse start than the hull: the demo's simulated scan takes 4 s, in
        which the live fit took 6-8 coarse steps, and the final runs that continued from them ended shredded (the
        demo goblet 1.87, 1.99 and 2.14 mm, in two and three pieces, 28-29 % of the surface apart), where the same
        capture from the hull came out in one piece at 1.31 mm. Scored on every view of the complete capture, those
        live fields read better than the hull (deviance per bin 1.18 against 2.49), so the likelihood cannot make
        this choice: the hull's phantom surfaces cost it more than the live field's shreds. So is a fit that has only
        just left its coarse level: a demo scan of 26 s ended 30 steps after the live fit refined (385 steps in all,
        the last coarse ones on 113 of its 128 views), and the final run that continued from it came out in 13
        pieces at 6.65 mm, where the hull's gives 1.2."""
        field, level, level_steps = self.live_field(), self.model.level, self.model.level_steps
        continued = from_live and self.continuable

        def make(scene, config, device, plan):
            model = make_model(scene, config, device, plan)
            if continued:
                model.warm_start(field, level, level_steps)
            return model

        return make

    def live_field(self):
        """A copy of the field the live mesh comes from (a GridField that later steps leave as it is)."""
        field = self.model.mesh_field()
        return type(field)(field.origin.detach().cpu().numpy(), field.voxel, field.sdf.detach()[0, 0].clone())

    def live_state(self) -> LiveState:
        """What the final run's choice of field (`keep.py`) needs of this fit: a copy of its field, its level, and
        copies of its fitted numbers besides the grid."""
        return LiveState(self.live_field(), self.model.level, scalars_of(self.model))

    def report(self) -> dict:
        """What the live phase did, for the final report."""
        rate = self.steps_per_s()
        return {"views_used": self.views_used, "steps": self.steps, "rebuilds": self.rebuilds,
                "rebuild_seconds": round(self.rebuild_s, 2),
                "coarse_restarts": self.recoarsened, "train_seconds": round(self.train_s, 2),
                "steps_per_s": None if rate is None else round(rate, 2), "level": getattr(self.model, "level", None)}


__all__ = ["LiveFit", "grid_snapshot"]
