"""The `fast` preset's model: a hull-bounded SDF grid fitted to photon counts, with its mechanisms as parts.

The core is short: each step renders a batch of views (every zone) with hull-hitting rays and crossing-centred
samples, bins the returns, applies the shared sensor model (pulse, gains, crosstalk, background, pile-up) and scores
the counts with the photon likelihood, adds finite-difference Eikonal and smoothness terms on the grid, and lets
Adam step the grid and the albedos. Everything else is a part (parts/, one module per mechanism) whose hooks
`FastModel.step` calls at fixed points; the list of what runs when is at `_step`. Meshes come from the grid (from
its moving average, where that part runs).
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np
import torch

from ..errors import ReconstructionError
from ..forward import choose_terms
from ..numerics import flush_denormals
from .albedo_start import albedo_for_total
from .config import FastConfig
from .grid_field import GridField, grid_shape
from .hull import HullConstraint
from .mesh import FLOATER_FRACTION, mesh_from_field
from .optim import Adam
from .parts import Part, StepRecord, build_parts
from .problem import FastProblem, build_problem
from .regularizers import band_nodes, grid_regularizers
from .render import render_returns
from .sampler import HullRays, around_crossing, hull_rays, pick_rays, stratified

RENDER_SEED_OFFSET = 0x5EED
"""The renders outside training draw from the run's seed plus this (any fixed offset: a stream apart from
training's)."""

ALBEDO_SEED_OFFSET = 0xA1BE
"""The albedo's estimate from the counts draws its rays from the run's seed plus this (a stream of its own)."""

KEPT_ON_RESTART = ("table", "dark_restart")
"""The parts `FastModel.restart` keeps as they are; every other part starts afresh."""

ALBEDO_VIEWS = 64
"""Views the albedo's estimate renders, spread over the capture: a total of photons needs no more, and a restart
pays for it once."""


def make_fast_model(scene, config: FastConfig, device, plan, keep_setup_views=None) -> "FastModel":
    """The `fast` preset's model factory: f(SceneData, FastConfig, device, RunPlan) -> FastModel. keep_setup_views:
    the views a large capture's set-up read last time, which it keeps reading where it can (a live fit's rebuild:
    `problem.build_problem`)."""
    config.check()
    device = torch.device(device)
    terms = choose_terms(scene)
    problem = build_problem(scene, config, device, terms, keep_setup_views=keep_setup_views)
    return FastModel(problem, config, seed=int(plan.seed), terms=terms)


class FastModel:
    """Implements model_api.ReconModel for the `fast` preset (see the module docstring), and `parts.Model` for its
    parts."""

    stochastic_render = True
    """Each render draws its rays and samples afresh (model_api.ReconModel)."""

    def __init__(self, problem: FastProblem, config: FastConfig, *, seed: int = 0, terms=None):
        self.problem, self.config, self.terms, self.seed = problem, config, terms, int(seed)
        self.sc = config.schedule
        dev = problem.counts.device
        self.device = dev
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(self.seed)
        # Renders outside training (the budget's probe, the fit check, the pictures) draw from their own stream: how
        # often the probe renders depends on the machine's speed, and training's draws must not.
        self.render_gen = torch.Generator(device=dev)
        self.render_gen.manual_seed(self.seed + RENDER_SEED_OFFSET)
        self.constraint = HullConstraint(problem.hull, config.field.hull_margin_m, problem.floor_z)
        counts, voxel = grid_shape(problem.box[0], problem.box[1], config.field.resolution)
        self.field = self.constraint.start_field(problem.box[0], voxel, counts, dev, torch.float32)
        self.on_table = problem.table_plane is not None
        inside = self.field.sdf.detach()[0, 0] < 0
        self.rays: HullRays = hull_rays(inside, self.field.origin, voxel, problem.poses, problem.zone_dirs,
                                        problem.zone_weights, pad_m=self.sc.segment_pad_voxels * voxel,
                                        keep_missed=self.on_table and config.parts.table.enabled)
        self.log_albedo = torch.zeros((), device=dev, requires_grad=True)
        self.n_views, self.n_zones, self.n_bins = problem.counts.shape
        self.views_per_step = self.sc.views_per_step
        solid = float(problem.zone_weights.sum(dim=1).mean())
        self.per_hist = max(self.sc.min_rays, int(round(self.sc.rays_per_sr * solid)))
        self._order = torch.empty(0, dtype=torch.long, device=dev)
        self.steps, self.level_steps, self.level = 0, 0, 0
        self.warm_started = False
        """Whether the field came from another fit (`warm_start`): a run of few steps then polishes, not starts."""
        self.last_level = not config.parts.refinement.enabled  # one level only: it is the last from the start
        self._band: torch.Tensor | None = None
        self.parts, self.left_out = build_parts(config.parts, self)
        self._by_name: dict[str, Part] = {part.name: part for part in self.parts}
        if terms is not None:
            # The report lists the terms the fit used: this preset has no TV term (its smoothness, loss.smooth_weight,
            # acts on every capture), and renders the table only where its part runs (parts.table.enabled=false on a
            # table scene: no plane). The forward model keeps the capture's terms (pile-up, crosstalk).
            self.terms = replace(terms, tv=False, table=self.table is not None)
        self._make_optimizer()

    def part(self, name: str) -> Part | None:
        """The running part called `name`, or None where it is switched off or does not apply to the scene."""
        return self._by_name.get(name)

    @property
    def table(self):
        """The table plane rendered under a real object (`parts.table.TableModel`), or None."""
        part = self.part("table")
        return None if part is None else part.table

    # ---- one step ---------------------------------------------------------------------------------------------
    def step(self) -> dict:
        """One optimiser step; returns the loss and its parts (data, eikonal, smooth), albedos, grid size, and
        `converged` (the plateau part's test on the last level)."""
        with flush_denormals(self.device):
            return self._step()

    def _step(self) -> dict:
        """One step, top down. The parts' hooks run in the order of `parts.PARTS`; with every part on:

        1. before_step      refinement (once, after the coarse level), cavities (every few steps: fill pockets, and
                            on a table the space under the object), thin_sheets (on a table, last level: curtains)
        2. render           the step's views -> photon rates (with the table plane), data term = deviance per bin
        3. before_loss      coarse_smoothing (keep the coarse level's smoothness near the floor), openings and
                            erosion (gather the returns' photon ratios, simulated captures)
        4. regularisers     Eikonal and smoothness on the band of nodes near the surface
        5. data gradient    backward of the data term alone, then after_gradient: blur, unseen (its moving average
                            of the gradient; without a table), empty_space
        6. regulariser gradient added, Adam steps the grid and the albedos; the step is counted
        7. after_step       hull_projection (clamp into the hull), openings (a round every few steps; a kept one
                            is a jump: `jumped`), erosion (every few steps), unseen (relax the air side of surface
                            no ray reaches, last level; after the clamp, so that a relaxed node may lie below the
                            hull's bound until the next step's clamp), average, plateau, dark_restart (a dark
                            object's fit started again from the hull, once)
        """
        for part in self.parts:
            part.before_step(self)
        views = self._next_views()
        rates, hits = self._rates(views, record_hits=any(part.wants_returns for part in self.parts))
        nll = self.problem.forward.nll(rates, self.problem.counts[views], self.problem.cycles[views],
                                       self.problem.valid[views])
        data = nll / self.n_bins  # deviance per bin: ~0.5 when the fit reaches the photon noise
        step = StepRecord(views, rates.detach(), hits, data)
        for part in self.parts:
            part.before_loss(self, step)
        eik, smooth = self._regularizers(step.smooth_layers)
        loss_cfg = self.config.loss
        reg = loss_cfg.eikonal_weight * eik + loss_cfg.smooth_weight * smooth
        loss = data + reg
        self.opt.zero_grad()
        if data.requires_grad:  # a batch whose rays all miss the hull has no data gradient
            data.backward()
        if self.field.sdf.grad is not None:
            grad = self.field.sdf.grad
            for part in self.parts:
                grad = part.after_gradient(self, grad)
            self.field.sdf.grad = grad
        if reg.requires_grad:
            reg.backward()
        self.opt.set_lr(0, self._grid_lr())
        self.opt.set_floor(0, self._grid_floor())
        self.opt.step()
        self.steps += 1
        self.level_steps += 1
        for part in self.parts:
            part.after_step(self, step)
        out = {"loss": float(loss.detach()), "data": float(data.detach()), "eikonal": float(eik.detach()),
               "smooth": float(smooth.detach()), "albedo": self.albedo(),
               "grid": max(self.field.counts), "converged": self.converged}
        if self.table is not None:
            out["table_albedo"] = self.table.albedo_value()
        if not math.isfinite(out["loss"]):
            raise ReconstructionError(f"the loss became {out['loss']} at step {self.steps} (diverged)")
        return out

    def _next_views(self) -> torch.Tensor:
        k = min(self.views_per_step, self.n_views)
        if self._order.numel() < k:
            perm = torch.randperm(self.n_views, device=self.device, generator=self.gen)
            self._order = torch.cat([self._order, perm])
        views, self._order = self._order[:k], self._order[k:]
        return views

    def _regularizers(self, smooth_layers: int | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(Eikonal, smoothness) on the band of nodes near the surface, refreshed every `band_refresh_steps` steps
        of a level; nodes the hull projection holds at its bound are left out."""
        sc = self.sc
        if self._band is None or self.level_steps % sc.band_refresh_steps == 0:
            bound = self.constraint.bound_for(self.field) if self.part("hull_projection") else None
            self._band = band_nodes(self.field.sdf, sc.band_voxels * self.field.voxel, bound)
        return grid_regularizers(self.field.sdf, self.field.voxel, self._band, sc.reg_points, self.gen, smooth_layers)

    # ---- optimiser and levels ---------------------------------------------------------------------------------
    def _make_optimizer(self) -> None:
        groups = [([self.field.sdf], self._grid_lr()), ([self.log_albedo], self.sc.albedo_lr)]
        table = self.part("table")
        if table is not None:
            groups += table.param_groups(self.sc.albedo_lr)
        # The floor on the grid (after the coarse level's first steps: `_grid_floor`); albedos and table: plain Adam.
        self.opt = Adam(groups, floor=(self._grid_floor(),) + (0.0,) * (len(groups) - 1))

    def fitted_scalars(self) -> list[torch.Tensor]:
        """The fitted numbers besides the grid, as the optimiser holds them: the object's log albedo, then the
        table's (its log albedo, its offset where fitted)."""
        table = self.part("table")
        extra = [t for tensors, _ in table.param_groups(0.0) for t in tensors] if table is not None else []
        return [self.log_albedo, *extra]

    def _grid_floor(self) -> float:
        """The grid's Adam floor (the config's `adam_floor` says why): none for the coarse level's first
        `adam_floor_after_steps` steps, and none on the whole coarse level of a scene on a table, `adam_floor` on
        the levels after it."""
        plain = self.level == 0 and (self.on_table or self.level_steps < self.sc.adam_floor_after_steps)
        return 0.0 if plain else self.sc.adam_floor

    def _grid_lr(self) -> float:
        """Learning rate of the grid (metres per step): constant before the last level, cosine-decayed on it."""
        lr = self.sc.lr_voxels * self.field.voxel
        if not self.last_level:
            return lr
        p = min(1.0, self.level_steps / max(1, self.sc.fine_steps))
        floor = self.sc.lr_final_fraction
        return lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * p)))

    def refine(self) -> None:
        """Refine the grid 2x (the refinement part's call): a new level, every part's `on_refine`, a new optimiser."""
        self.field = self.field.upsampled(2)
        self.level, self.last_level, self.level_steps, self._band = self.level + 1, True, 0, None
        for part in self.parts:
            part.on_refine(self)
        self._make_optimizer()

    def warm_start(self, field: GridField, level: int, level_steps: int = 0) -> None:
        """Start from another fit's field instead of the hull: a live reconstruction rebuilds its model as views
        arrive and continues from where the last model was. The grid is refined to `level` (where refinement runs),
        takes `field`'s values where that field's box covers it (the hull start elsewhere: the box may have grown),
        and never lies below this model's hull bound (more views carve a tighter hull: it is the start and the
        constraint both). The level goes on from `level_steps` steps (the last model's): its learning-rate decay
        and its refinement continue where they were. Every part then starts afresh from it, as after a jump."""
        while self.level < level and self.part("refinement") is not None:
            self.refine()
        if self.level == level:
            self.level_steps = int(level_steps)
        with torch.no_grad():
            own = self.field.sdf
            points = self.field.node_points().to(field.origin.dtype)
            lo, hi = field.origin, field.box_max
            covered = ((points >= lo) & (points <= hi)).all(dim=-1)
            values = field.sample(points.to(field.sdf.device)).to(own.device, own.dtype)
            start = torch.where(covered.to(own.device)[None, None], values[None, None], own)
            own.copy_(torch.maximum(start, self.constraint.bound_for(self.field)))
        self.warm_started = True
        self.jumped()

    def albedo(self) -> float:
        """The object's fitted albedo."""
        return float(torch.exp(self.log_albedo.detach()))

    def set_albedo(self, albedo: float) -> None:
        """Set the object's albedo (> 0), as the optimiser goes on from."""
        with torch.no_grad():
            self.log_albedo.fill_(math.log(albedo))

    def restart(self) -> None:
        """Start the fit again from the hull on the coarse grid (the dark-restart part's call): the grid, its level,
        the optimiser and every part as before the first step, but the table (what it learned of the plane) and the
        dark-restart part itself (its record); the albedos stay, and `steps` goes on counting (a part that keys its
        rounds on it, the openings, starts its schedule where the steps stand)."""
        box = self.problem.box
        counts, voxel = grid_shape(box[0], box[1], self.config.field.resolution)
        self.field = self.constraint.start_field(box[0], voxel, counts, self.device, torch.float32)
        self.level, self.level_steps, self._band = 0, 0, None
        self.last_level = not self.config.parts.refinement.enabled
        fresh, self.left_out = build_parts(self.config.parts, self)
        self.parts = [self._by_name.get(part.name, part) if part.name in KEPT_ON_RESTART else part for part in fresh]
        self._by_name = {part.name: part for part in self.parts}
        self._make_optimizer()

    def project(self) -> None:
        """Clamp the field into the hull's bound, where the hull projection part runs."""
        if self.part("hull_projection") is not None:
            self.constraint.project(self.field)

    def jumped(self) -> None:
        """The surface just moved in one jump (an opening): the band is found afresh and every part's `on_jump`
        drops what followed the old surface."""
        self._band = None
        for part in self.parts:
            part.on_jump(self)

    @property
    def converged(self) -> bool:
        """The plateau part's test: the data term has plateaued on the last level (False where it does not run)."""
        plateau = self.part("plateau")
        return plateau is not None and plateau.converged(self)

    # ---- rendering --------------------------------------------------------------------------------------------
    def _rates(self, views: torch.Tensor, record_hits: bool = False,
               gen: torch.Generator | None = None) -> tuple[torch.Tensor, tuple | None]:
        """(photon rates (n, Z, B) of the given views under the current field, albedos and table, hits). hits: with
        record_hits, the opaque returns (`_opaque_returns`) for the parts that read them, else None. gen: the
        generator that draws the rays and samples (default: the model's)."""
        transient, hits = self._transient(views, record_hits, gen)
        return self.problem.forward.rates(transient, self.problem.background[views]), hits

    def _transient(self, views: torch.Tensor, record_hits: bool = False, gen: torch.Generator | None = None,
                   albedo: float | None = None) -> tuple[torch.Tensor, tuple | None]:
        """(transients (n, Z, n_fine) of the given views, hits): `_rates` before the sensor model. albedo: the
        object's albedo to render with instead of the fitted one (the table keeps its own)."""
        hits = None
        gen = self.gen if gen is None else gen
        Z, fwd, table = self.n_zones, self.problem.forward, self.table
        n_hist = views.numel() * Z
        hist = (views[:, None] * Z + torch.arange(Z, device=self.device)).reshape(-1)
        has = self.rays.count[hist] > 0
        hist_ok, local = hist[has], torch.nonzero(has)[:, 0]
        transient = torch.zeros(n_hist, fwd.n_fine, device=self.device)
        vox = self.field.voxel
        if hist_ok.numel() > 0:
            idx, batch, o, d, w = pick_rays(self.rays, hist_ok, self.per_hist, gen, self.sc.ray_jitter)
            t_in, t_out = self.rays.t_in[idx], self.rays.t_out[idx]
            with torch.no_grad():
                tc = stratified(t_in, t_out, self.sc.coarse_samples, gen)
                fc = self.field.sample(o[:, None] + tc[..., None] * d[:, None])
            t = around_crossing(tc, fc, t_in, t_out, self.sc.fine_samples, self.sc.window_voxels * vox, gen)
            r, radiance, opacity = render_returns(self.field.sample, o, d, t, w,
                                                  self.config.field.sharpness_voxels / vox, 0.5 * vox)
            if record_hits:
                hits = _opaque_returns(o, d, r, radiance, opacity, local[batch])
            # The forward model's transient carries albedo / pi (see forward.py); render_returns gives cos/r^2 x sr.
            radiance = radiance * ((torch.exp(self.log_albedo) if albedo is None else albedo) / math.pi)
            hist_id = local[batch][:, None].expand_as(r)
            ranges, values, ids = [r.reshape(-1)], [radiance.reshape(-1)], [hist_id.reshape(-1)]
            if table is not None:
                tr, tv = table.returns(o, d, w, (1.0 - opacity).clamp(0.0, 1.0))
                ranges.append(tr)
                values.append(tv)
                ids.append(local[batch])
            transient = fwd.bin(torch.cat(ranges), torch.cat(values), torch.cat(ids), n_hist)
        if table is not None:
            transient = transient + table.open_transient(hist)
        return transient.reshape(views.numel(), Z, -1), hits

    def counts_albedo(self, max_views: int = ALBEDO_VIEWS) -> float | None:
        """The object's albedo at which the current field's expected counts, over up to `max_views` views spread
        evenly over the capture (of a large one, over those its set-up read), total the counts they measured
        (`albedo_start`); None where they hold no signal above their background. No gradient; its rays come from
        their own stream, so the training's draws stay as they were."""
        p, fwd = self.problem, self.problem.forward
        pool = p.setup_views if p.setup_views is not None else torch.arange(self.n_views, device=self.device)
        views = pool[torch.linspace(0, pool.numel() - 1, min(max_views, pool.numel()), device=self.device).long()]
        gen = torch.Generator(device=self.device)
        gen.manual_seed(self.seed + ALBEDO_SEED_OFFSET)
        batches, measured = [], 0.0
        with torch.no_grad(), flush_denormals(self.device):
            for batch in views.split(self.views_per_step):
                state = gen.get_state()
                lit, _ = self._transient(batch, gen=gen, albedo=1.0)
                base = torch.zeros_like(lit)
                if self.table is not None:  # the table's own returns, behind the object as it stands
                    gen.set_state(state)
                    base, _ = self._transient(batch, gen=gen, albedo=0.0)
                batches.append((batch, base, lit - base))
                measured += float((p.counts[batch] * p.valid[batch]).sum())

            def total_at(albedo: float) -> float:
                return sum(float((fwd.expected_counts(fwd.rates(base + albedo * own, p.background[v]), p.cycles[v])
                                  * p.valid[v]).sum()) for v, base, own in batches)

            return albedo_for_total(total_at, measured)

    def deviance_all_views(self, seed: int) -> float:
        """Deviance per bin over every view under the current field, with the rays that `seed` draws (so that two
        fields compare on the same rays). No gradient. Of a large capture, over the evenly spread views its set-up
        read (`problem.setup_views`): a per-bin mean, which they estimate, at a cost that does not grow with the
        views (the openings' round of proposals renders it up to four times: 49 s at 10,000 views over every view)."""
        gen = torch.Generator(device=self.device)
        gen.manual_seed(seed)
        total, fwd, p = 0.0, self.problem.forward, self.problem
        scored = p.setup_views if p.setup_views is not None else torch.arange(self.n_views, device=self.device)
        with torch.no_grad():
            for views in scored.split(self.views_per_step):
                lam, _ = self._rates(views, gen=gen)
                nll = fwd.nll(lam, p.counts[views], p.cycles[views], p.valid[views])  # mean over the histograms
                total += float(nll) * views.numel()
        return total / (scored.numel() * self.n_bins)

    def render_histograms(self, view_ids) -> np.ndarray:
        """Expected counts (n, Z, B) of the given views under the current fit (float64, no gradient)."""
        views = torch.as_tensor(np.asarray(list(view_ids)), device=self.device, dtype=torch.long).reshape(-1)
        out = []
        with torch.no_grad(), flush_denormals(self.device):
            for v in views.split(max(1, self.views_per_step)):
                lam, _ = self._rates(v, gen=self.render_gen)
                out.append(self.problem.forward.expected_counts(lam, self.problem.cycles[v]).double().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.n_zones, self.n_bins))

    # ---- meshes and the report --------------------------------------------------------------------------------
    def mesh_field(self) -> GridField:
        """The field meshes are extracted from: the average part's, where it runs, else the grid itself."""
        average = self.part("average")
        return self.field if average is None else average.mesh_field(self)

    def extract_mesh(self, resolution: int | None = None, averaged: bool = True):
        """The surface as a trimesh.Trimesh (world metres) with vertex normals from the grid's gradient, marching
        cubes on the grid resampled to `resolution` cells along its longest side (None: the grid's own). On a
        table, what lies under it is cut, (with the cavities part) the space under the object filled, and small
        pieces on the table removed (mesh.FLOATER_FRACTION); without one, every piece stays. Closed pockets are
        filled with the cavities part only: switched off, the mesh shows what the fit made of them.
        averaged=False: from the grid as it is now, not its average (what the fit would mesh without that part)."""
        field = self.mesh_field() if averaged else self.field
        cavities = self.part("cavities")
        if not self.on_table:
            return mesh_from_field(field, resolution, fill_pockets=cavities is not None)
        fill = cavities is not None and cavities.config.under_overhangs
        return mesh_from_field(field, resolution, self.problem.floor_z, fill_under=fill,
                               open_m=cavities.config.open_width_m if fill else 0.0, floater_fraction=FLOATER_FRACTION,
                               fill_pockets=cavities is not None)

    def summary(self) -> dict:
        """JSON-able state: grid, hull, rays, albedo, convergence, and each part that ran with its config and what
        it did (`parts`), and why the others did not run (`parts_left_out`)."""
        out = {"steps": self.steps, "grid_nodes": list(self.field.counts), "voxel_mm": self.field.voxel * 1e3,
               "sharpness_per_m": self.config.field.sharpness_voxels / self.field.voxel, "refined": self.level > 0,
               "converged": self.converged, "albedo": self.albedo(),
               "hull_rays": int(self.rays.count.sum()), "rays_per_histogram": self.per_hist,
               "floor_z_m": self.problem.floor_z, **self.problem.notes,
               "parts": {part.name: {"config": asdict(part.config), **part.summary()} for part in self.parts},
               "parts_left_out": dict(self.left_out)}
        return out


def _opaque_returns(o, d, r, radiance, opacity, hist):
    """(histogram (n,), point (n, 3), range (n,)) of the rays whose return is opaque (opacity > 0.5): the point at
    the radiance-weighted mean range along each ray. No gradient."""
    with torch.no_grad():
        rad = radiance.detach()
        t = (rad * r.detach()).sum(dim=1) / rad.sum(dim=1).clamp(min=1e-30)
        keep = (opacity.detach() > 0.5) & (rad.sum(dim=1) > 0)
        return hist[keep], o[keep] + t[keep, None] * d[keep], t[keep]


__all__ = ["FastModel", "make_fast_model"]
