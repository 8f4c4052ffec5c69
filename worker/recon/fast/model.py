"""The `fast` preset's model: a hull-bounded SDF grid fitted to photon counts.

Each step renders a batch of views (every zone) with hull-hitting rays and crossing-centred samples, bins the
returns, applies the shared sensor model (pulse, gains, crosstalk, background, pile-up) and scores the counts with
the photon likelihood, plus finite-difference Eikonal and smoothness terms on the grid (and, on a table, the
empty-space push of empty_space.py); Adam steps the grid and the albedos, and the grid is projected back inside the
hull. Without a table, the coarse level smooths only near the floor (`schedule.coarse_smooth_height_m`). On
simulated captures, surface whose returns the histograms do not show is eroded every few steps (phantoms.py), and
every `schedule.open_every_steps` the solid behind it is opened in one jump wherever the likelihood over all views
prefers that (openings.py). The grid is refined 2x once; after that the learning rate decays and the run reports
`converged` when the windowed data term stops improving. Meshes come from a moving average of the grid over the
last steps.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..forward import TransientForward, choose_terms
from ..numerics import flush_denormals
from .blur import blur3
from .empty_space import pressure_weight, push_to_empty, thin_near_table, under_overhangs, view_coverage
from .grid_field import GridField, grid_shape
from .hull import HullConstraint
from .optim import Adam
from .openings import opened_field, opening_distances, surface_classes
from .phantoms import ReturnEvidence, erode_at, return_ratios
from .plateau import Plateau
from .problem import FastProblem, build_problem
from .regularizers import band_nodes, grid_regularizers
from .render import render_returns
from .sampler import HullRays, around_crossing, hull_rays, pick_rays, stratified
from .table import TableModel


def make_fast_model(scene, config, device, plan) -> "FastModel":
    """The model factory named by the `fast` preset: f(SceneData, ReconConfig, device, RunPlan) -> FastModel."""
    device = torch.device(device)
    terms = choose_terms(scene)
    problem = build_problem(scene, config, device, terms)
    return FastModel(problem, config, seed=int(plan.seed), terms=terms)


class FastModel:
    """Implements model_api.ReconModel for the `fast` preset (see the module docstring)."""

    def __init__(self, problem: FastProblem, config, *, seed: int = 0, terms=None):
        self.p, self.config = problem, config
        self.fc, self.sc = config.field, config.schedule
        self.terms = terms
        dev = problem.counts.device
        self.device = dev
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(seed)
        self.constraint = HullConstraint(problem.hull, self.fc.hull_margin_m, problem.floor_z)
        counts, voxel = grid_shape(problem.box[0], problem.box[1], self.fc.resolution)
        self.field = self.constraint.start_field(problem.box[0], voxel, counts, dev, torch.float32)
        inside = self.field.sdf.detach()[0, 0] < 0
        plane = problem.table_plane
        self.rays: HullRays = hull_rays(inside, self.field.origin, voxel, problem.poses, problem.zone_dirs,
                                        problem.zone_weights, pad_m=self.sc.segment_pad_voxels * voxel,
                                        keep_missed=plane is not None)
        self.table: TableModel | None = None
        if plane is not None:
            self.table = TableModel(plane[0], plane[1], self.fc.table_albedo_init, plane[2], self.rays.missed,
                                    problem.forward, dev)
        self.log_albedo = torch.zeros((), device=dev, requires_grad=True)
        self.n_views, self.n_zones, self.n_bins = problem.counts.shape
        solid = float(problem.zone_weights.sum(dim=1).mean())
        self.per_hist = max(self.sc.min_rays, int(round(self.sc.rays_per_sr * solid)))
        self._order = torch.empty(0, dtype=torch.long, device=dev)
        self.steps, self.level_steps = 0, 0
        self.refined = self.fc.refine_after_steps <= 0
        self._plateau = Plateau(self.sc.patience_steps, self.sc.min_rel_improvement)
        self._band: torch.Tensor | None = None
        # The empty-space bias (empty_space.py) of scenes on a table, and its per-node weight (None until used).
        self.empty_space = self.table is not None and self.sc.empty_pressure > 0
        self._push_weight: torch.Tensor | None = None
        from spadscan.protocol.errors import ConfigError

        h = self.sc.coarse_smooth_height_m
        if h is not None and not (isinstance(h, (int, float)) and 0.0 <= h <= 1.0):  # also refuses NaN
            raise ConfigError(f"schedule.coarse_smooth_height_m {h} must be in [0, 1] metres or None")
        # The coarse level's smoothness near the floor only (schedule.coarse_smooth_height_m): its z layers.
        self.coarse_smooth_top_z: float | None = None
        self._coarse_smooth_layers: int | None = None
        if h is not None and self.table is None and problem.floor_z is not None:
            from .mesh import node_heights

            self.coarse_smooth_top_z = problem.floor_z + h
            rows = node_heights(self.field.counts[2], float(self.field.origin[2]), self.field.voxel)
            self._coarse_smooth_layers = int((rows < self.coarse_smooth_top_z).sum())

        if self.fc.thin_sheet_voxels < 0:
            raise ConfigError(f"field.thin_sheet_voxels {self.fc.thin_sheet_voxels} must be >= 0 (0: off)")
        if not 0.0 <= self.fc.thin_sheet_band_m <= 1.0:  # also refuses NaN
            raise ConfigError(f"field.thin_sheet_band_m {self.fc.thin_sheet_band_m} must be in [0, 1] metres")
        if not 0.0 <= self.sc.average_decay < 1.0:
            raise ConfigError(f"schedule.average_decay {self.sc.average_decay} must be in [0, 1) (0: off)")
        if not 0.0 <= self.sc.phantom_ratio < 1.0:
            raise ConfigError(f"schedule.phantom_ratio {self.sc.phantom_ratio} must be in [0, 1) (0: off)")
        if self.sc.phantom_every_steps < 1 or self.sc.phantom_min_hits < 1 or self.sc.phantom_window_bins < 0:
            raise ConfigError("schedule.phantom_every_steps and phantom_min_hits must be >= 1 and "
                              "phantom_window_bins >= 0")
        # Erosion of surface the histograms do not show (phantoms.py): simulated captures only, where the sensor
        # model predicts a surface's photons well enough for the test.
        self.phantoms = self.sc.phantom_ratio > 0 and not problem.measured
        self._evidence: ReturnEvidence | None = None
        self.eroded_nodes = 0
        # Opening of the solid behind phantom surface (openings.py), with the same evidence: simulated captures only.
        bad = _opening_settings_error(self.sc)
        if bad:
            raise ConfigError(bad)
        self.seed = int(seed)
        self._opening = self.phantoms and self.sc.open_every_steps > 0 and len(self.sc.open_depths_m) > 0
        self._open_misses = 0
        # A round's evidence: the returns of the training steps of its last `open_passes` passes' worth of views.
        self._open_window = min(self.sc.open_every_steps,
                                self.sc.open_passes * math.ceil(self.n_views / max(1, self.sc.views_per_step)))
        self._open_evidence: ReturnEvidence | None = None
        self.opened_nodes = 0
        self.openings: list[dict] = []
        # The moving average of the grid that meshes are extracted from (schedule.average_decay); restarted at
        # refinement, where the grid changes shape.
        self._average: torch.Tensor | None = None
        self._make_optimizer()

    # ---- optimiser and schedule -------------------------------------------------------------------------------
    def _params(self):
        groups = [([self.field.sdf], self._grid_lr()), ([self.log_albedo], self.sc.albedo_lr)]
        if self.table is not None:
            groups.append(([self.table.log_albedo], self.sc.albedo_lr))
            if self.table.fit_offset:
                groups.append(([self.table.offset], self.sc.table_lr_m))
        return groups

    def _make_optimizer(self) -> None:
        groups = self._params()
        self.opt = Adam(groups, shared=(self.sc.shared_adam,) + (False,) * (len(groups) - 1))

    def _grid_lr(self) -> float:
        """Learning rate of the grid (metres per step): constant on the coarse level, cosine-decayed on the fine."""
        lr = self.sc.lr_voxels * self.field.voxel
        if not self.refined:
            return lr
        p = min(1.0, self.level_steps / max(1, self.sc.fine_steps))
        floor = self.sc.lr_final_fraction
        return lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * p)))

    def _next_views(self) -> torch.Tensor:
        k = min(self.sc.views_per_step, self.n_views)
        if self._order.numel() < k:
            perm = torch.randperm(self.n_views, device=self.device, generator=self.gen)
            self._order = torch.cat([self._order, perm])
        views, self._order = self._order[:k], self._order[k:]
        return views

    # ---- rendering --------------------------------------------------------------------------------------------
    def _rates(self, views: torch.Tensor, record_hits: bool = False,
               gen: torch.Generator | None = None) -> tuple[torch.Tensor, tuple | None]:
        """(photon rates (n, Z, B) of the given views under the current field, albedos and table, hits). hits: with
        record_hits, the opaque returns (`_opaque_returns`) for the step's evidence (phantoms.py), else None. gen:
        the generator that draws the rays and samples (default: the model's)."""
        hits = None
        gen = self.gen if gen is None else gen
        Z, fwd = self.n_zones, self.p.forward
        n_hist = views.numel() * Z
        hist = (views[:, None] * Z + torch.arange(Z, device=self.device)).reshape(-1)
        has = self.rays.count[hist] > 0
        hist_ok, local = hist[has], torch.nonzero(has)[:, 0]
        transient = torch.zeros(n_hist, fwd.n_fine, device=self.device)
        vox = self.field.voxel
        if hist_ok.numel() > 0:
            idx, batch, o, d, w = pick_rays(self.rays, hist_ok, self.per_hist, gen)
            t_in, t_out = self.rays.t_in[idx], self.rays.t_out[idx]
            with torch.no_grad():
                tc = stratified(t_in, t_out, self.sc.coarse_samples, gen)
                fc = self.field.sample(o[:, None] + tc[..., None] * d[:, None])
            t = around_crossing(tc, fc, t_in, t_out, self.sc.fine_samples, self.sc.window_voxels * vox, gen)
            r, radiance, opacity = render_returns(self.field.sample, o, d, t, w, self.fc.sharpness_voxels / vox,
                                                  0.5 * vox)
            if record_hits:
                hits = _opaque_returns(o, d, r, radiance, opacity, local[batch])
            # The forward model's transient carries albedo / pi (see forward.py); render_returns gives cos/r^2 x sr.
            radiance = radiance * (torch.exp(self.log_albedo) / math.pi)
            hist_id = local[batch][:, None].expand_as(r)
            ranges, values, ids = [r.reshape(-1)], [radiance.reshape(-1)], [hist_id.reshape(-1)]
            if self.table is not None:
                tr, tv = self.table.returns(o, d, w, (1.0 - opacity).clamp(0.0, 1.0))
                ranges.append(tr)
                values.append(tv)
                ids.append(local[batch])
            transient = fwd.bin(torch.cat(ranges), torch.cat(values), torch.cat(ids), n_hist)
        if self.table is not None:
            transient = transient + self.table.open_transient(hist)
        return fwd.rates(transient.reshape(views.numel(), Z, -1), self.p.background[views]), hits

    # ---- the Model protocol -----------------------------------------------------------------------------------
    def step(self) -> dict:
        """One optimiser step; returns the loss and its parts (data, eikonal, smooth), albedos, grid size, and
        `converged` (the windowed data term has stopped improving after the last refinement)."""
        with flush_denormals(self.device):
            return self._step()

    def _step(self) -> dict:
        sc, lc = self.sc, self.config.loss
        if not self.refined and self.level_steps >= self.fc.refine_after_steps:
            self._refine()
        if self.level_steps % sc.band_refresh_steps == 0:
            self._fill_cavities()
            self._empty_thin_sheets()
        views = self._next_views()
        lam, hits = self._rates(views, record_hits=self.phantoms)
        nll = self.p.forward.nll(lam, self.p.counts[views], self.p.cycles[views], self.p.valid[views])
        if self.phantoms:
            self._gather_evidence(views, lam.detach(), hits, self._evidence_targets())
        data = nll / self.n_bins  # deviance per bin: ~0.5 when the fit reaches the photon noise
        if self._band is None or self.level_steps % sc.band_refresh_steps == 0:
            self._band = band_nodes(self.field.sdf, sc.band_voxels * self.field.voxel,
                                    self.constraint.bound_for(self.field))
        eik, smooth = grid_regularizers(self.field.sdf, self.field.voxel, self._band, sc.reg_points, self.gen,
                                        None if self.refined else self._coarse_smooth_layers)
        reg = lc.eikonal_weight * eik + lc.tv_weight * smooth
        loss = data + reg
        self.opt.zero_grad()
        if sc.grad_blur_passes > 0:
            # Blur only the data term's gradient: the regularisers' gradients are what removes roughness, and a
            # blur would take exactly that away. (A batch whose rays all miss the hull has no data gradient.)
            if data.requires_grad:
                data.backward()
            if self.field.sdf.grad is not None:
                # The same physical reach at every level: a 2x finer grid needs 4x the passes (variances add).
                passes = sc.grad_blur_passes * (4 if self.refined and self.fc.refine_after_steps > 0 and
                                                sc.blur_physical else 1)
                self.field.sdf.grad = blur3(self.field.sdf.grad, passes)
                if self.empty_space:
                    push_to_empty(self.field.sdf.grad, self.field.sdf, self.field.voxel, self._pressure_weight(),
                                  sc.empty_pressure)
            if reg.requires_grad:
                reg.backward()
        else:
            loss.backward()
        self.opt.set_lr(0, self._grid_lr())
        self.opt.step()
        self.constraint.project(self.field)
        # A round of openings before the erosion: its evidence is on the surface as these steps rendered it, and
        # the erosion would first move exactly the flagged nodes a voxel away from it.
        if self._opening and (self.steps + 1) % sc.open_every_steps == 0:
            self._open_phantoms(self.steps + 1)
        if self.phantoms and (self.level_steps + 1) % sc.phantom_every_steps == 0:
            self._erode_phantoms()
        self._update_average()
        self.steps += 1
        self.level_steps += 1
        self._plateau.update(float(data.detach()))
        out = {"loss": float(loss.detach()), "data": float(data.detach()), "eikonal": float(eik.detach()),
               "smooth": float(smooth.detach()), "albedo": float(torch.exp(self.log_albedo.detach())),
               "grid": max(self.field.counts), "converged": self.converged}
        if self.table is not None:
            out["table_albedo"] = self.table.albedo_value()
        if not math.isfinite(out["loss"]):
            from ..errors import ReconstructionError

            raise ReconstructionError(f"the loss became {out['loss']} at step {self.steps} (diverged)")
        return out

    def _evidence_targets(self) -> list[ReturnEvidence]:
        """The evidence this step's returns go to: the erosion's, and in the last `_open_window` steps before a round
        of openings, the round's (each made afresh where it is missing or the grid changed shape since)."""
        shape = tuple(self.field.sdf.shape[2:])
        if self._evidence is None or self._evidence.shape != shape:
            self._evidence = ReturnEvidence(shape, self.device)
        targets = [self._evidence]
        if self._opening:
            into, start = self.steps % self.sc.open_every_steps, self.sc.open_every_steps - self._open_window
            if into >= start:  # in the window before the next round: nothing is gathered for it outside that
                if into == start or self._open_evidence is None or self._open_evidence.shape != shape:
                    self._open_evidence = ReturnEvidence(shape, self.device)
                targets.append(self._open_evidence)
        return targets

    def _gather_evidence(self, views: torch.Tensor, lam: torch.Tensor, hits: tuple | None,
                         targets: list[ReturnEvidence]) -> None:
        """Add the opaque returns (`_rates`' hits) of these views to each per-node evidence of `targets`
        (phantoms.py): the log of measured over expected signal photons around each return's bin, where the expected
        signal is well above the noise."""
        if hits is None or hits[0].numel() == 0:
            return
        p, fwd = self.p, self.p.forward
        cycles = p.cycles[views]
        expected = fwd.expected_counts(lam, cycles).reshape(-1, self.n_bins)
        bg = (p.background[views] * cycles[:, None]).reshape(-1)
        ratio, significant = return_ratios(expected, p.counts[views].reshape(-1, self.n_bins), bg,
                                           p.valid[views].reshape(-1, self.n_bins), self.sc.phantom_window_bins)
        hist, points, ranges = hits
        s = fwd.sensor
        b = torch.floor(s.zero_bin + ranges / s.bin_width_m).long().clamp(0, self.n_bins - 1)
        keep = significant[hist, b]
        points, log_ratio = points[keep], torch.log(ratio[hist, b][keep])
        for evidence in targets:
            evidence.add(points, log_ratio, self.field.origin, self.field.voxel)

    def _erode_phantoms(self) -> None:
        nodes = self._evidence.take(self.sc.phantom_min_hits, self.sc.phantom_ratio)
        self.eroded_nodes += erode_at(self.field.sdf.detach()[0, 0], nodes, self.field.voxel)

    def _all_views_deviance(self, seed: int) -> float:
        """Deviance per bin over every view under the current field, with the rays that `seed` draws (so that two
        fields compare on the same rays). No gradient."""
        gen = torch.Generator(device=self.device)
        gen.manual_seed(seed)
        total, fwd, p = 0.0, self.p.forward, self.p
        with torch.no_grad():
            for views in torch.arange(self.n_views, device=self.device).split(self.sc.views_per_step):
                lam, _ = self._rates(views, gen=gen)
                nll = fwd.nll(lam, p.counts[views], p.cycles[views], p.valid[views])  # mean over the histograms
                total += float(nll) * views.numel()
        return total / (self.n_views * self.n_bins)

    def _opening_distances(self, flagged: torch.Tensor, supported: torch.Tensor):
        """`opening_distances`, with the floor counted as supported surface: the object's base rests on it, where no
        view sees it, and an opening that reaches the floor leaves a hole through the base that nothing in the data
        closes again (the built-in cup's 8 mm base, opened from above at step 300)."""
        d_flagged, d_supported = opening_distances(flagged, supported, self.field.voxel)
        if self.p.floor_z is not None:
            from .mesh import node_heights

            rows = node_heights(flagged.shape[0], float(self.field.origin[2]), self.field.voxel) - self.p.floor_z
            above = torch.as_tensor(rows, dtype=d_supported.dtype, device=d_supported.device).clamp(min=0.0)
            d_supported = torch.minimum(d_supported, above[:, None, None].expand_as(d_supported))
        return d_flagged, d_supported

    def _open_phantoms(self, step: int) -> None:
        """One round of proposals (openings.py) at the end of step `step`: open the solid behind phantom surface at
        the depth the likelihood prefers, if any; records the round in `openings`."""
        started = time.perf_counter()
        sc = self.sc
        evidence, self._open_evidence = self._open_evidence, None
        flagged = supported = None
        sdf = self.field.sdf.detach()[0, 0]
        if evidence is not None and evidence.shape == tuple(sdf.shape):
            flagged, supported = surface_classes(evidence, sdf, self.field.voxel, sc.phantom_min_hits,
                                                 sc.phantom_ratio, sc.open_keep_ratio)
        record = {"step": step, "flagged": 0 if flagged is None else int(flagged.sum())}
        kept = None
        if record["flagged"] >= sc.open_min_flagged:  # a handful of flagged nodes is noise, not a lid
            seed = self.seed * 1_000_003 + step
            before = self._all_views_deviance(seed)
            record["deviance"] = round(before, 5)
            kept = self._best_opening(seed, before, flagged, supported)
        if kept is None:
            self._open_misses += 1
            self._opening = self._open_misses < sc.open_patience
        else:
            depth, opened, after = kept
            self._open_misses = 0
            self.opened_nodes += opened
            record.update(depth_m=depth, opened=opened, deviance_after=round(after, 5))
            # The average and the band follow the jump at once: averaging it in over ~100 steps would mesh the old
            # lid and the new cavity blended.
            self._average = self.field.sdf.detach().clone()
            self._band = None
            # The erosion's returns so far lay on the surface the jump removed.
            self._evidence = ReturnEvidence(tuple(sdf.shape), self.device)
        record["seconds"] = round(time.perf_counter() - started, 2)
        self.openings.append(record)

    def _best_opening(self, seed: int, before: float, flagged: torch.Tensor,
                      supported: torch.Tensor) -> tuple[float, int, float] | None:
        """Try each depth of `open_depths_m` on the same rays as `before`; leave the field opened at the best one
        that gains at least `open_min_gain` per bin and return (depth, nodes opened, deviance), or leave the field
        as it was and return None."""
        sc, field = self.sc, self.field
        current = field.sdf.detach().clone()
        distances = self._opening_distances(flagged, supported)
        best, best_grid = None, None
        for depth in sc.open_depths_m:
            grid, opened = opened_field(current[0, 0], flagged, distances, depth, sc.open_keep_m)
            if opened == 0:
                continue
            with torch.no_grad():
                field.sdf[0, 0] = grid
            after = self._all_views_deviance(seed)
            if after < (before - sc.open_min_gain if best is None else best[2]):
                best, best_grid = (depth, opened, after), grid
        with torch.no_grad():  # an opening only raises the field, so it stays within the hull's bound
            field.sdf[0, 0] = current[0, 0] if best_grid is None else best_grid
        return best

    def _update_average(self) -> None:
        if self.sc.average_decay <= 0:
            return
        sdf = self.field.sdf.detach()
        n = self.level_steps  # this level's earlier updates (the step is counted after this)
        if n == 0:  # a new level (or the first step): the grid has a new shape
            self._average = sdf.clone()
            return
        # A short memory while the level is young and the grid still moves fast, growing to the configured one
        # (the num_updates warm-up of TensorFlow's ExponentialMovingAverage): a 100-step average lagged a fresh
        # level by up to 0.9 mm (the bunny at 30 s).
        decay = min(self.sc.average_decay, (1.0 + n) / (10.0 + n))
        self._average.lerp_(sdf, 1.0 - decay)

    def mesh_field(self) -> GridField:
        """The field meshes are extracted from: the grid's moving average (`schedule.average_decay`) once a step has
        been taken, else the grid itself."""
        if self._average is None or self._average.shape != self.field.sdf.shape:
            return self.field
        return GridField(self.field.origin.cpu().numpy(), self.field.voxel, self._average[0, 0])

    def _pressure_weight(self) -> torch.Tensor:
        """The empty-space push's weight on the current grid's nodes: from the views' coverage, computed once on the
        coarse grid (a second on 64^3 nodes x 128 views) and interpolated onto the refined one."""
        shape = tuple(self.field.sdf.shape)
        if self._push_weight is None:
            with torch.no_grad():
                cov = view_coverage(self.field.node_points(), self.p.poses, self.p.forward.sensor.zones)
            self._push_weight = pressure_weight(cov, self.sc.pressure_coverage)[None, None].contiguous()
        if tuple(self._push_weight.shape) != shape:
            self._push_weight = torch.nn.functional.interpolate(self._push_weight, size=shape[2:], mode="trilinear",
                                                                align_corners=True)
        return self._push_weight

    def _fill_cavities(self) -> None:
        """Make solid every empty pocket closed by the solid (and the floor), every few steps: no sensor outside sees
        into one, so nothing in the data holds the nodes around it. Without this, bubbles grew inside the dataset's
        soap after ~3,000 steps (Chamfer 1.8 mm -> 8.7 mm by 180 s on an idle machine), and on a table the
        empty-space push hollowed the object out.

        On a table (with `field.fill_under_overhangs`), the space under the solid is filled first, as the mesh is
        (every view looks from above). A hollow that a hole opens to the outside is no pocket: on LCSPCData's real
        pyramid the fit became a shell, hollow inside and open near the table. The mesh filled the hollow from the
        top down, but not under the pinholes in the shell: shafts down to the table, 1-2 cm off the object's faces
        (step-based, two threads: 5.27 mm after 3,400 steps; with this fill, 4.45 mm after 2,400)."""
        from .mesh import below_floor, cavities, node_heights

        sdf = self.field.sdf.detach()[0, 0]
        solid = (sdf < 0).cpu().numpy()
        below = below_floor(solid.shape, float(self.field.origin[2]), self.field.voxel, self.p.floor_z)
        fill = np.zeros_like(solid)
        if below is not None and self.table is not None and self.fc.fill_under_overhangs:
            z = node_heights(solid.shape[0], float(self.field.origin[2]), self.field.voxel)
            fill = under_overhangs(solid, z, self.p.floor_z)
        fill |= cavities(solid | fill, below)
        if fill.any():
            with torch.no_grad():
                sdf[torch.as_tensor(fill, device=sdf.device)] = -0.5 * self.field.voxel
            self.constraint.project(self.field)

    def _empty_thin_sheets(self) -> None:
        """Empty the thin sheets just above the table (`empty_space.thin_near_table`), every few steps on the refined
        grid of a scene on a table."""
        if self.table is None or self.p.floor_z is None or not self.refined or self.fc.thin_sheet_voxels <= 0:
            return
        from .mesh import node_heights

        sdf = self.field.sdf.detach()[0, 0]
        z = node_heights(sdf.shape[0], float(self.field.origin[2]), self.field.voxel)
        thin = thin_near_table((sdf < 0).cpu().numpy(), z, self.p.floor_z, self.fc.thin_sheet_band_m,
                               self.fc.thin_sheet_voxels)
        if thin.any():
            with torch.no_grad():
                sdf[torch.as_tensor(thin, device=sdf.device)] = 0.5 * self.field.voxel

    def _refine(self) -> None:
        self.field = self.field.upsampled(2)
        self.constraint.project(self.field)
        self.refined, self.level_steps, self._band = True, 0, None
        self._plateau = Plateau(self.sc.patience_steps, self.sc.min_rel_improvement)
        self._make_optimizer()

    @property
    def converged(self) -> bool:
        """The data term has plateaued (`plateau.Plateau`) on the last level: the test starts afresh at refinement."""
        return self.refined and self._plateau.reached

    def extract_mesh(self, resolution: int | None = None):
        """The surface as a trimesh.Trimesh (world metres) with vertex normals from the grid's gradient, marching
        cubes on the grid resampled to `resolution` cells along its longest side (None: the grid's own)."""
        from .mesh import mesh_from_field

        field = self.mesh_field()
        if self.table is None:  # the hidden-space fills are the table's (empty_space.py)
            return mesh_from_field(field, resolution)
        return mesh_from_field(field, resolution, self.p.floor_z, fill_under=self.fc.fill_under_overhangs)

    def render_histograms(self, view_ids) -> np.ndarray:
        """Expected counts (n, Z, B) of the given views under the current fit (float64, no gradient)."""
        views = torch.as_tensor(np.asarray(list(view_ids)), device=self.device, dtype=torch.long).reshape(-1)
        out = []
        with torch.no_grad(), flush_denormals(self.device):
            for v in views.split(max(1, self.sc.views_per_step)):
                lam, _ = self._rates(v)
                out.append(self.p.forward.expected_counts(lam, self.p.cycles[v]).double().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.n_zones, self.n_bins))

    def summary(self) -> dict:
        """JSON-able state: grid, hull, rays, albedos, table, convergence."""
        out = {"steps": self.steps, "grid_nodes": list(self.field.counts), "voxel_mm": self.field.voxel * 1e3,
               "sharpness_per_m": self.fc.sharpness_voxels / self.field.voxel, "refined": self.refined,
               "converged": self.converged, "albedo": float(torch.exp(self.log_albedo.detach())),
               "hull_rays": int(self.rays.count.sum()), "rays_per_histogram": self.per_hist,
               "floor_z_m": self.p.floor_z, "coarse_smooth_below_z_m": self.coarse_smooth_top_z,
               "empty_space_push": self.empty_space,
               "mesh_average_decay": self.sc.average_decay, "phantom_erosion": self.phantoms,
               "eroded_nodes": self.eroded_nodes, "opened_nodes": self.opened_nodes, "openings": self.openings,
               **self.p.notes}
        if self.table is not None:
            out.update(self.table.summary())
        return out


def _opening_settings_error(sc) -> str | None:
    """A one-line reason why the schedule's opening settings (openings.py) are unusable, or None."""
    depths = sc.open_depths_m
    if not (isinstance(sc.open_every_steps, int) and sc.open_every_steps >= 0):
        return f"schedule.open_every_steps {sc.open_every_steps} must be an integer >= 0 (0: off)"
    if not all(isinstance(d, (int, float)) and 0 < d <= 1 for d in depths):
        return f"schedule.open_depths_m {list(depths)} must be depths in (0, 1] metres"
    if not 0 <= sc.open_keep_m <= 0.1:
        return f"schedule.open_keep_m {sc.open_keep_m} must be in [0, 0.1] metres"
    if not sc.phantom_ratio <= sc.open_keep_ratio:
        return f"schedule.open_keep_ratio {sc.open_keep_ratio} must be >= phantom_ratio {sc.phantom_ratio}"
    if sc.open_passes < 1 or sc.open_patience < 1 or not sc.open_min_gain >= 0 or sc.open_min_flagged < 1:
        return "schedule.open_passes, open_patience and open_min_flagged must be >= 1 and open_min_gain >= 0"
    return None


def _opaque_returns(o, d, r, radiance, opacity, hist):
    """(histogram (n,), point (n, 3), range (n,)) of the rays whose return is opaque (opacity > 0.5): the point at
    the radiance-weighted mean range along each ray. No gradient."""
    with torch.no_grad():
        rad = radiance.detach()
        t = (rad * r.detach()).sum(dim=1) / rad.sum(dim=1).clamp(min=1e-30)
        keep = (opacity.detach() > 0.5) & (rad.sum(dim=1) > 0)
        return hist[keep], o[keep] + t[keep, None] * d[keep], t[keep]


__all__ = ["FastModel", "make_fast_model", "FastProblem", "TransientForward"]
