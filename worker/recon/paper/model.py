"""The paper's model: an MLP SDF rendered NeuS-style through the shared sensor model, trained with Adam.

One step: pick `views_per_batch` views; cast one jittered ray per solid-angle cell of every zone, sample each ray
stratified inside the scene sphere (stopping at the table), evaluate the field there without gradient, add
importance rays in the cells that returned most the last time the view was rendered and importance samples where the
coarse opacity lies (a ray that misses the sphere but meets the table returns the table's light); render every
ray with gradient, bin by range, convolve with the pulse, add gains, crosstalk and background, and compare with the
measured histograms (L2 on counts / cycles, as published), plus 0.1 x Eikonal and, on measured data, TV.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import torch

from ..errors import ReconstructionError
from ..forward import TransientForward, choose_terms
from ..model_api import RunPlan
from ..numerics import flush_denormals
from ..scene_data import SceneData
from .batch import RayBatch, backprop_batch, batch_transient
from .config import PaperConfig
from .field import MLPField
from .loss import eikonal, hist_l2, hist_nll, hist_scale, normal_tv
from .mesh import marching_cubes_mesh
from .rays import ZoneGrid, mixture_weights
from .render import Table, table_hit
from .sampler import importance, merge, sphere_interval, stratified


def make_paper_model(scene: SceneData, config: PaperConfig, device, plan: RunPlan) -> "PaperModel":
    """The model factory named by the `paper` preset."""
    return PaperModel(scene, config, torch.device(device), plan)


def cosine_lr(progress: float, warmup: float, floor: float) -> float:
    """Learning-rate factor: linear warm-up over the first `warmup` of the run, then a cosine from 1 to `floor`."""
    if progress < warmup:
        return max(progress / warmup, 1e-3)
    p = (progress - warmup) / max(1.0 - warmup, 1e-9)
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * min(p, 1.0)))


class PaperModel:
    """Implements model_api.ReconModel for the `paper` preset."""

    stochastic_render = False
    """render_histograms casts cell-centre rays with unjittered importance samples and no importance rays: two
    renders of a view are identical, so the end-of-run fit check renders each view once."""

    def __init__(self, scene: SceneData, config: PaperConfig, device: torch.device, plan: RunPlan):
        self.scene, self.config, self.device, self.plan = scene, config, device, plan
        self.dtype = {"float32": torch.float32, "float64": torch.float64}.get(config.dtype)
        if self.dtype is None:
            raise ReconstructionError(f"dtype {config.dtype!r} must be 'float32' or 'float64'")
        terms = choose_terms(scene)
        # The report lists the terms the fit used: TV only where it has a weight (loss.tv_weight=0 leaves it out).
        self.terms = replace(terms, tv=terms.tv and config.loss.tv_weight > 0)
        if self.terms.tv and config.loss.eikonal_points == 0:
            raise ReconstructionError(f"loss.eikonal_points 0 leaves the TV term of measured data (loss.tv_weight "
                                      f"{config.loss.tv_weight:g}) no points to act on: set loss.tv_weight=0 too, "
                                      f"or eikonal_points >= 1")
        self.gen = torch.Generator().manual_seed(int(plan.seed))
        torch.manual_seed(int(plan.seed))
        kw = dict(device=device, dtype=self.dtype)
        self.center = scene.center.to(**kw)
        self.radius = scene.radius
        self.field = MLPField(config.field, self.center, self.radius).to(**kw)
        sc = config.sharpness
        self.log_s = torch.nn.Parameter(torch.tensor(math.log(sc.init), **kw), requires_grad=sc.learned)
        self.log_albedo = torch.nn.Parameter(torch.tensor(math.log(config.albedo_init), **kw))
        params = [{"params": list(self.field.parameters()) + [self.log_albedo]}]
        if sc.learned:
            params.append({"params": [self.log_s]})
        self.table = None
        if scene.table is not None:
            self.table_albedo = torch.nn.Parameter(torch.tensor(math.log(config.albedo_init), **kw))
            self.table_offset = torch.nn.Parameter(torch.tensor(scene.table.offset, **kw),
                                                   requires_grad=scene.table.fitted)
            self.table_normal = torch.as_tensor(scene.table.normal, **kw)
            params.append({"params": [self.table_albedo] + ([self.table_offset] if scene.table.fitted else [])})
        self.optim = torch.optim.Adam(params, lr=config.optim.lr)
        kernel, origin = scene.pulse(config.time_oversample)
        self.forward = TransientForward(scene.sensor, self.terms, torch.as_tensor(kernel, dtype=self.dtype), origin,
                                        config.time_oversample).to(device)
        z = scene.sensor.n_zones
        rc = config.rays
        self.grid = ZoneGrid(scene.sensor, max(rc.min_rays_per_zone, rc.rays_per_view // z), device, self.dtype)
        self.n_imp_rays = int(math.ceil(rc.importance_rays_per_view / z)) if rc.importance_rays_per_view > 0 else 0
        # Per view and cell, where the view's rays last saw signal: the importance rays' probabilities (make_batch).
        self.view_prob = torch.ones((scene.n_views, z, self.grid.n_cells), **kw)
        self.counts = scene.counts.to(**kw)
        self.cycles = scene.cycles.to(**kw)
        self.valid = scene.valid.to(device)
        self.background = scene.background.to(**kw)
        self.scale = hist_scale(self.counts, self.cycles, self.valid, self.background)
        self.chunk_points = self._chunk_points()
        self.steps_done = 0
        self.train_s = 0.0

    def _chunk_points(self) -> int:
        """Samples per rendering chunk: the config's, or what fits the memory budget. Measured: a sample of the
        8 x 256 float32 network holds ~70 kB of graph (activations of the field, its gradient and their backward)."""
        sched = self.config.schedule
        if sched.chunk_points:
            return int(sched.chunk_points)
        f = self.config.field
        per_point = 8 * f.width * (f.layers + 1) * (torch.finfo(self.dtype).bits // 8)
        if sched.memory_gb:
            budget = sched.memory_gb * 1e9
        elif self.device.type == "cuda":
            budget = 0.5 * torch.cuda.mem_get_info(self.device)[0]
        else:
            budget = 3e9
        return int(max(4096, budget // per_point))

    # ---- parameters ----------------------------------------------------------------------------------------------
    @property
    def sharpness(self) -> torch.Tensor:
        """s in 1 / (scene radius) units, clamped to the config's range."""
        sc = self.config.sharpness
        return self.log_s.exp().clamp(sc.min, sc.max)

    def _table(self) -> Table | None:
        if self.scene.table is None:
            return None
        return Table(self.table_normal, self.table_offset, self.table_albedo.exp())

    # ---- rays and samples ----------------------------------------------------------------------------------------
    def make_batch(self, views: torch.Tensor, *, train: bool) -> RayBatch:
        """Rays and samples for views (nv,): one ray in every cell of every zone (jittered when training), then
        (training) importance rays and, always, importance samples. No gradient."""
        rc, g = self.config.rays, self.grid
        s_up = max(float(self.sharpness.detach()), self.config.sharpness.upsample) / self.radius
        cells = g.all_cells()[None].expand(len(views), -1, -1)  # (nv, Z, C)
        batch = self._coarse(views, cells, train)
        weight = g.cell_weight[None].expand(cells.shape)
        if train and self.n_imp_rays > 0:
            # The importance probabilities must not depend on the rays they weight: taken from this step's own rays,
            # a cell whose ray happened to hit the object gets a high pi and so a small weight, and the estimate is
            # biased low at every silhouette (-8 % on a small ball). Take them from the cells' returns the last time
            # these views were rendered for training (uniform for a view not seen yet): independent of this step's
            # jitter, so the balance heuristic stays unbiased, and free.
            prob = self.view_prob[views]
            contrib = batch.coarse_contribution(s_up)
            self.view_prob[views] = contrib + 0.1 * contrib.mean(-1, keepdim=True) + 1e-30
            extra_cells = g.draw_cells(prob, self.n_imp_rays, self.gen)  # (nv, Z, n_imp)
            w_all = mixture_weights(g.cell_weight[None], prob, self.n_imp_rays)  # (nv, Z, C)
            weight = torch.cat([w_all, torch.gather(w_all, 2, extra_cells)], dim=2)
            batch = batch.concat(self._coarse(views, extra_cells, True))
        batch.weight = weight * batch.returns
        if rc.importance_samples > 0:
            shape = batch.t.shape
            more = importance(batch.t.reshape(-1, shape[-1]), batch.coarse_sdf.reshape(-1, shape[-1]), s_up,
                              rc.importance_samples, jitter=train, generator=self.gen)
            batch.t = merge(batch.t.reshape(-1, shape[-1]), more).reshape(shape[:-1] + (-1,))
        return batch

    def _coarse(self, views: torch.Tensor, cells: torch.Tensor, jitter: bool) -> RayBatch:
        """Rays through cells (nv, Z, M) of each view, their stratified samples and the field there (no gradient)."""
        nv, z, m = cells.shape
        dirs = self.grid.directions(cells.permute(1, 0, 2).reshape(z, nv * m), jitter=jitter, generator=self.gen)
        dirs = dirs.reshape(z, nv, m, 3).permute(1, 0, 2, 3)  # (nv, Z, M, 3) in the sensor frame
        poses = self.scene.poses.to(self.device, self.dtype)[views]
        world = torch.einsum("vij,vzmj->vzmi", poses[:, :3, :3], dirs)
        origins = poses[:, None, None, :3, 3].expand_as(world).contiguous()
        o, d = origins.reshape(-1, 3), world.reshape(-1, 3)
        far_max = None
        if self.scene.table is not None:
            with torch.no_grad():
                far_max = table_hit(o, d, self._table())
        near, far, hit = sphere_interval(o, d, self.center, self.radius, self.config.rays.near_m, far_max)
        # A ray that meets the table but not the scene sphere (low views: the table reaches far past the sphere)
        # still returns the table's light, through empty space, as the measured histogram holds it.
        returns = hit if far_max is None else hit | torch.isfinite(far_max)
        t = stratified(near, far, self.config.rays.samples_per_ray, jitter=jitter, generator=self.gen)
        with torch.no_grad():
            x = (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)
            f = torch.cat([self.field.sdf(c) for c in x.split(1 << 16)]).reshape(t.shape)
        shape = (nv, z, m)
        return RayBatch(views=views, origins=origins, dirs=world, t=t.reshape(shape + (-1,)),
                        coarse_sdf=f.reshape(shape + (-1,)), hit=hit.reshape(shape).to(self.dtype),
                        returns=returns.reshape(shape).to(self.dtype))

    # ---- one step ------------------------------------------------------------------------------------------------
    def step(self) -> dict:
        with flush_denormals(self.device):
            return self._step()

    def _step(self) -> dict:
        t0 = time.perf_counter()
        rc, lc = self.config.rays, self.config.loss
        nv = min(rc.views_per_batch, self.scene.n_views)
        views = torch.randperm(self.scene.n_views, generator=self.gen)[:nv].to(self.device)
        batch = self.make_batch(views, train=True)
        self.optim.zero_grad(set_to_none=True)
        s_m = self.sharpness / self.radius
        albedo = self.log_albedo.exp()
        bg, counts, cycles, valid = self.background[views], self.counts[views], self.cycles[views], self.valid[views]

        def data_loss(transient):
            lam = self.forward.rates(transient.reshape(nv, self.scene.sensor.n_zones, -1), bg)
            if lc.kind == "l2":
                return hist_l2(self.forward, lam, counts, cycles, valid, self.scale)
            return hist_nll(self.forward, lam, counts, cycles, valid)

        data, eik = backprop_batch(self.field, self.forward, batch, s_m, albedo, self._table(), data_loss,
                                   lc.eikonal_weight, self.chunk_points)
        extra = tv = torch.zeros((), device=self.device, dtype=self.dtype)
        if lc.eikonal_points > 0:  # 0: the Eikonal term on the ray samples alone (no TV then: __init__)
            # Random points in the scene sphere keep the field an SDF away from the rays too.
            x = self._random_points(lc.eikonal_points)
            _, g = self.field.sdf_and_grad(x, create_graph=True)
            extra = lc.eikonal_weight * eikonal(g) * (lc.eikonal_points / (lc.eikonal_points + batch.n_samples))
            if self.terms.tv and lc.tv_weight > 0:
                tv = normal_tv(self.field, x, 0.01 * self.radius, self.gen)
                extra = extra + lc.tv_weight * tv
            extra.backward()
        self._set_lr()
        self.optim.step()
        self.steps_done += 1
        self.train_s += time.perf_counter() - t0
        loss = float(data) + lc.eikonal_weight * float(eik) + float(extra.detach())
        if not math.isfinite(loss):
            raise ReconstructionError(f"the loss became {loss} at step {self.steps_done} (diverged)")
        return {"loss": loss, "data": float(data), "eikonal": float(eik), "tv": float(tv.detach()),
                "sharpness": float(self.sharpness.detach()), "albedo": float(albedo.detach())}

    def _random_points(self, n: int) -> torch.Tensor:
        u = torch.randn(n, 3, generator=self.gen, dtype=torch.float64)
        r = torch.rand(n, 1, generator=self.gen, dtype=torch.float64) ** (1 / 3)
        x = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-12) * r * self.radius
        return x.to(self.device, self.dtype) + self.center

    def _set_lr(self) -> None:
        oc = self.config.optim
        progress = self.plan.progress(self.steps_done, self.train_s)
        if not (self.plan.steps or self.plan.budget_s):
            progress = self.steps_done / oc.nominal_steps
        horizon = self.plan.steps or oc.nominal_steps
        warmup = min(oc.warmup_steps / horizon, 0.02) if horizon < 50 * oc.warmup_steps else oc.warmup_steps / horizon
        factor = cosine_lr(progress, warmup, oc.lr_floor)
        for group in self.optim.param_groups:
            group["lr"] = oc.lr * factor

    # ---- outputs -------------------------------------------------------------------------------------------------
    def object_sdf(self, x: torch.Tensor) -> torch.Tensor:
        """The object's SDF cut to the scene sphere and to the free side of the table (metres), (N, 3) -> (N,)."""
        f = torch.maximum(self.field.sdf(x), (x - self.center).norm(dim=-1) - self.radius)
        if self.scene.table is not None:
            f = torch.maximum(f, self.table_offset.detach() - x @ self.table_normal)
        return f

    def extract_mesh(self, resolution: int):
        box = self.scene.box.to(self.device, self.dtype)
        grad = lambda x: self.field.sdf_and_grad(x, create_graph=False)[1]  # noqa: E731
        return marching_cubes_mesh(self.object_sdf, grad, box, resolution)

    def render_histograms(self, view_ids) -> np.ndarray:
        views = torch.as_tensor(list(view_ids), dtype=torch.long, device=self.device)
        z, out = self.scene.sensor.n_zones, []
        for v in views.split(1):
            batch = self.make_batch(v, train=False)
            with torch.no_grad(), flush_denormals(self.device):
                table = self._table()
                table = None if table is None else Table(table.normal, table.offset.detach(), table.albedo.detach())
                tr = batch_transient(self.field, self.forward, batch, (self.sharpness / self.radius).detach(),
                                     self.log_albedo.exp().detach(), table, self.chunk_points)
                lam = self.forward.rates(tr.reshape(1, z, -1), self.background[v])
                out.append(self.forward.expected_counts(lam, self.cycles[v]).double().cpu().numpy())
        return np.concatenate(out)

    def summary(self) -> dict:
        out = {"sharpness": float(self.sharpness.detach()), "albedo": float(self.log_albedo.detach().exp()),
               "hist_scale": self.scale, "steps": self.steps_done, "train_seconds": self.train_s,
               "rays_per_zone": self.grid.n_cells, "importance_rays_per_zone": self.n_imp_rays,
               "chunk_points": self.chunk_points}
        if self.scene.table is not None:
            out["table_offset_m"] = float(self.table_offset.detach())
            out["table_albedo"] = float(self.table_albedo.detach().exp())
        return out
