"""FLAME-in-NeRF: a deformable NeRF conditioned on masked expression parameters.

One class for every preset, composed of the paper's parts, each in a module of its own:
the per-frame codes ω_i, φ_i (embeddings here), the SE(3) warp with its coarse-to-fine
window (model/warp.py, model/se3.py), the canonical field (model/field.py: the paper's
MLP or a hash grid), the expression pathway with the spatial prior
(model/expression.py), the samplers and compositing (model/render.py), and the losses
(model/losses.py, composed by `get_loss_dict`). The config picks the field (`mlp`/`hash`),
the sampler (`hierarchical`/`proposal`) and the expression mode (`masked`/`none`/
`everywhere`). `forward` is the training renderer; model/inference.py renders the same
model faster outside training.

A model built with a `head_region` (datasets with head poses, `model.head.follow`) takes
points into the head's canonical frame before anything else sees them (`head_points`);
without one, or for rays without a head transform, points are exactly as before.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flamenerf.config import ModelConfig
from flamenerf.data.captured_views import MAX_ANGLE_DEG
from flamenerf.data.rays import RayBatch  # noqa: F401 - the model's input, re-exported
from flamenerf.model.expression import ExpressionConditioner
from flamenerf.model.field import ProposalField, make_field
from flamenerf.model.head_rig import HeadRig
from flamenerf.model.losses import (LossBatch, LossTerms, LossWeights, face_depth_loss,
                                    face_region_loss, photometric_loss, ray_weights,
                                    still_depth)
from flamenerf.model.render import (composite, interlevel_loss, render_weights, sample_pdf,
                                    stratified_samples)
from flamenerf.model.view_directions import captured_direction
from flamenerf.model.warp import SE3Field


def _plain_region(region: dict) -> dict:
    """An ellipsoid (data/head_pose.HeadRegion.to_dict) as plain floats and lists, for a
    run's saved init arguments."""
    return {k: [list(map(float, r)) if isinstance(r, list) else float(r) for r in v]
            for k, v in region.items()}


class FlameNeRF(nn.Module):
    def __init__(self, cfg: ModelConfig, num_codes: int, expr_dim: int, near: float,
                 far: float, box_min: list[float], box_max: list[float],
                 mesh_vertices: int = 0, mesh_faces: int = 0, head_region: dict | None = None,
                 detail_region: dict | None = None, warp_region: dict | None = None,
                 expression_mean: list[float] | None = None,
                 guide_skip: list[int] | None = None, background: float = 0.0,
                 generic_controls: list[int] | None = None):
        super().__init__()
        self.cfg = cfg
        # what a ray left unfinished is rendered over outside training (TrainConfig's
        # `render_background`); training composites over black and the trainer adds its own
        self.background = float(background)
        self.captured: tuple[Tensor, Tensor | None, Tensor] | None = None
        self.captured_max_angle = 0.0
        self.near, self.far = float(near), float(far)
        self.expr_dim = expr_dim
        # controls whose mesh shape is generic (`set_expression_model`), for the ranges that
        # what users ask for is clamped to
        self.generic_controls: list[int] = list(generic_controls or [])
        self.init_args = dict(num_codes=num_codes, expr_dim=expr_dim, near=near, far=far,
                              box_min=list(map(float, box_min)),
                              box_max=list(map(float, box_max)))
        # the head's ellipsoid (data/head_pose.HeadRegion.to_dict, world units), kept in
        # init_args so that a loaded run rebuilds it; buffers for the device only. The model
        # follows the head in it (`head_region`), or a still head's deformation stays in it
        # (`warp_region`: `warp.still_head_only` where no head is followed)
        self.follows_head = head_region is not None and cfg.head.follow
        still_head = warp_region is not None and not self.follows_head and cfg.warp.enabled
        name = "head_region" if self.follows_head else "warp_region" if still_head else None
        if name is not None:
            region = head_region if self.follows_head else warp_region
            self.init_args[name] = _plain_region(region)
        # model/head_rig.py: how points follow the head (or a still head's warp stays in it)
        self.head_rig = HeadRig(region, cfg.head.band) if name is not None else None
        bmin, bmax = torch.tensor(box_min), torch.tensor(box_max)
        self.register_buffer("center", (bmin + bmax) / 2)
        # isotropic scale, so that rigid warps in normalised space are rigid in the world
        self.register_buffer("half_extent", ((bmax - bmin) / 2).max())
        field_expr = 0 if cfg.expression_mode == "none" else expr_dim
        # how β reaches the field (model/expression.py): the spatial prior and its
        # refinements, with the per-subject face-mesh model they use
        self.expression = ExpressionConditioner(cfg, expr_dim, self.center, self.half_extent,
                                                mesh_vertices, mesh_faces)
        if self.expression.uses_mesh_model:
            self.init_args.update(mesh_vertices=int(mesh_vertices), mesh_faces=int(mesh_faces))
            if guide_skip:
                self.set_guide_skip(torch.tensor(guide_skip, dtype=torch.long))
        if expression_mean is not None:
            self.set_expression_mean(torch.tensor(expression_mean))
        self.deform_codes = nn.Embedding(num_codes, cfg.warp.code_dim)
        self.appearance_codes = nn.Embedding(num_codes, cfg.field.appearance_dim)
        nn.init.normal_(self.deform_codes.weight, std=1e-2)
        nn.init.normal_(self.appearance_codes.weight, std=1e-2)
        self.warp_expression = cfg.warp.enabled and cfg.warp.expression_input and field_expr > 0
        self.warp = (SE3Field(cfg.warp, field_expr if self.warp_expression else 0)
                     if cfg.warp.enabled else None)
        self.warp_in_head = (self.follows_head and bool(cfg.warp.head_only)) or still_head
        # the hash field's detail levels act in the head's region (data/head_pose.head_region,
        # world units; kept in init_args for a loaded run), normalised for the field
        region = None
        if detail_region is not None and cfg.field.kind == "hash" and cfg.field.detail_levels:
            self.init_args["detail_region"] = _plain_region(detail_region)
            c, a, r = (torch.tensor(detail_region[k]).float()
                       for k in ("centre", "axes", "radii"))
            region = (self.normalize(c), a, r / self.half_extent)
        self.field = make_field(cfg.field, field_expr, region)
        s = cfg.sampler
        if s.kind == "hierarchical":
            self.field_coarse = make_field(cfg.field, field_expr, region)
        elif s.kind == "proposal":
            self.proposal = ProposalField(s.proposal_levels, s.proposal_log2_size,
                                          s.proposal_max_res, s.proposal_width, field_expr)
        else:
            raise ValueError(f"unknown sampler {s.kind!r}")

    # ---------------------------------------------------------------- expression
    def set_expression_model(self, neutral: Tensor, basis: Tensor, faces: Tensor,
                             mesh_only: list[int] | tuple[int, ...] = ()) -> None:
        """The per-subject β -> mesh model (`ExpressionConditioner.set_mesh_model`);
        `mesh_only`, generic shapes' controls, kept in init_args as `generic_controls`."""
        self.expression.set_mesh_model(neutral, basis, faces, mesh_only)
        self.generic_controls = [int(k) for k in mesh_only]
        if self.generic_controls:
            self.init_args["generic_controls"] = list(self.generic_controls)
        else:
            self.init_args.pop("generic_controls", None)

    def set_guide_skip(self, vertices: Tensor) -> None:
        """Vertex indices (K,) that the mesh guide ignores (`mesh_guide.max_residual`); kept
        in init_args so that a loaded run rebuilds them."""
        self.expression.set_guide_skip(vertices)
        self.init_args["guide_skip"] = [int(v) for v in vertices]

    def set_expression_mean(self, mean: Tensor) -> None:
        """β̄ (E,) (`ExpressionConditioner.set_mean`); kept in init_args so that a loaded
        run rebuilds it."""
        self.expression.set_mean(mean)
        self.init_args["expression_mean"] = [float(v) for v in mean]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # runs saved before the expression pathway was a part of its own stored the face
        # mesh model's buffers at the top: the same tensors under their new names
        for name in ("mesh_neutral", "mesh_basis", "mesh_faces", "mesh_regions"):
            if prefix + name in state_dict:
                state_dict[f"{prefix}expression.{name}"] = state_dict.pop(prefix + name)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ---------------------------------------------------------------- conditioning
    def update_to_step(self, step: int, total_steps: int) -> None:
        """Set step-dependent state: the c2f window α(t) = m·t/N with N the run's
        `anneal_fraction` of `total_steps`."""
        if self.warp is not None:
            w = self.cfg.warp
            n = max(w.anneal_fraction * total_steps, 1.0)
            self.warp.set_alpha(min(w.num_freqs * step / n, w.num_freqs))

    @contextlib.contextmanager
    def outside_training(self) -> Iterator[FlameNeRF]:
        """The model as a render outside training sees it (eval mode: the second pass over
        unfinished rays, the trained background's mean, the captured view directions; a
        training model has none of them), its mode restored after."""
        was_training = self.training
        self.eval()
        try:
            yield self
        finally:
            self.train(was_training)

    def codes(self, frame_index: Tensor) -> tuple[Tensor, Tensor]:
        """frame_index (R,) long -> ω (R, code_dim), φ (R, appearance_dim)."""
        return self.deform_codes(frame_index), self.appearance_codes(frame_index)

    def head_weight(self, x: Tensor, band: float | None = None) -> Tensor:
        """`HeadRig.weight`: how much of the head's motion world points x (*bs, 3) take."""
        return self.head_rig.weight(x, band)

    def head_points(self, x: Tensor, dirs: Tensor, head: Tensor | None
                    ) -> tuple[Tensor, Tensor]:
        """World samples x (R, S, 3) and directions (R, 3) in the head's canonical frame for
        rays with head twists (R, 6) (`HeadRig.points`); unchanged without a followed head
        or twists."""
        xc, dc, _ = self._head_points(x, dirs, head)
        return xc, dc

    def _head_points(self, x: Tensor, dirs: Tensor, head: Tensor | None
                     ) -> tuple[Tensor, Tensor, Tensor | None]:
        """head_points, and the share of the head's motion each ray's direction took (R,)
        (None where nothing moves)."""
        if not self.follows_head or head is None:
            return x, dirs, None
        return self.head_rig.points(x, dirs, head)

    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.center) / self.half_extent

    def warp_points(self, xn: Tensor, code: Tensor, expr: Tensor | None = None) -> Tensor:
        """Normalised observation points (*bs, 3), codes (*, D) and masked expressions
        (*, E) broadcastable -> canonical (*bs, 3). A warp that takes β gets β = 0 when
        `expr` is None: the face-region regulariser holds the face still under ω alone."""
        if self.warp is None:
            return xn
        if self.warp_expression:
            e = code.new_zeros(*code.shape[:-1], self.expr_dim) if expr is None else expr
            code = torch.cat([code, e.expand(*code.shape[:-1], -1)], -1)
        if not self.warp_in_head:
            return self.warp(xn, code)
        # x + g(x) (warp(x) - x), g = the head's weight (over the warp's own band): 1 in the
        # head's region, 0 in the still world, whose points skip the warp
        g = self.head_weight(xn * self.half_extent + self.center, self.cfg.warp.band)
        live = g > 0
        if bool(live.all()):
            return xn + g[..., None] * (self.warp(xn, code) - xn)
        out = xn.clone()
        if bool(live.any()):
            xl, gl = xn[live], g[live][:, None]
            cl = code.expand(*xn.shape[:-1], code.shape[-1])[live]
            out[live] = xl + gl * (self.warp(xl, cl) - xl)
        return out

    # ---------------------------------------------------------------- querying
    def _query(self, field: nn.Module, xn: Tensor, dirs: Tensor, code: Tensor, app: Tensor,
               expr: Tensor | None) -> tuple[Tensor, Tensor]:
        """Points (*bs, 3) with per-point or broadcastable conditioning -> σ (*bs),
        rgb (*bs, 3)."""
        xc = self.warp_points(xn, code, expr)
        return field(xc, dirs, app, expr)

    def sample_points(self, origins: Tensor, dirs: Tensor, t: Tensor, expr: Tensor | None,
                      head: Tensor | None, inside: Tensor | None = None
                      ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Samples at depths t (R, S) along rays (R, 3), (R, 3) with masked expressions
        (R, E) and head twists (R, 6) (either None) -> normalised points ready for the warp
        (R, S, 3) (in the head's frame, carried to the neutral mesh when mesh-guided), unit
        view directions (R, 3), and the expression each point gets (R, S, E), or (R, 1, E)
        per ray without the per-control prior. The one place both renderers (training and
        model/inference.py) prepare samples. `inside` (R,) bool: the rays whose β passes the
        prior (`expression.inside`; None: those whose `expr` is not 0). Outside training, with captured views set,
        the directions are kept near the capture (`captured_direction`)."""
        x, d, share = self._head_points(origins[:, None] + t[..., None] * dirs[:, None], dirs,
                                        head)
        xn, expr_pts = self.expression.point_inputs(self.normalize(x), expr, inside)
        d = F.normalize(d, dim=-1)
        if self.captured is not None and not self.training:
            d = self.captured_direction(origins, d, head, share)
        return xn, d, expr_pts

    def proposal_points(self, origins: Tensor, dirs: Tensor, t: Tensor,
                        head: Tensor | None) -> Tensor:
        """The proposal's samples (R, S, 3), normalised, in the head's frame (no warp)."""
        x, _ = self.head_points(origins[:, None] + t[..., None] * dirs[:, None], dirs, head)
        return self.normalize(x)

    def _query_rays(self, field, rays: RayBatch, t: Tensor, expr: Tensor | None):
        """Samples at depths t (R, S) along each ray -> σ (R, S), rgb (R, S, 3). The ray's
        codes go in once per ray, shaped (R, 1, ·), and broadcast over samples."""
        xn, dn, expr_pts = self.sample_points(rays.origins, rays.dirs, t, expr, rays.head,
                                              self.expression.inside(rays.face_ray))
        return self._query(field, xn, dn[:, None], rays.deform_code[:, None],
                           rays.appearance_code[:, None], expr_pts)

    def _deltas(self, t: Tensor, dirs: Tensor, last: float) -> Tensor:
        """Distances between samples in normalised units. t (R, S) -> (R, S)."""
        dt = torch.cat([t[:, 1:] - t[:, :-1], torch.full_like(t[:, :1], last)], -1)
        return dt * (dirs.norm(dim=-1, keepdim=True) / self.half_extent)

    # ---------------------------------------------------------------- captured views
    def set_captured_views(self, views, max_angle: float | None = None) -> None:
        """Render colour as the capture saw it (data/captured_views.py; None: as asked),
        within `max_angle` radians of a captured view (default: captured_views.MAX_ANGLE_DEG).
        Not part of the checkpoint: a run's loader sets it from its dataset
        (training/run.Run.attach); training never uses it."""
        self.captured_max_angle = (math.radians(MAX_ANGLE_DEG) if max_angle is None
                                   else float(max_angle))
        if views is None:
            self.captured = None
            return
        dev = self.center.device

        def t(a):
            return None if a is None else torch.as_tensor(a, dtype=torch.float32, device=dev)

        self.captured = (t(views.world), t(views.twists), t(views.focus))

    def captured_direction(self, origins: Tensor, dirs: Tensor, head: Tensor | None,
                           share: Tensor | None) -> Tensor:
        """`view_directions.captured_direction` with this model's captured views."""
        return captured_direction(self.captured, self.captured_max_angle, origins, dirs,
                                  head, share)

    def _background(self) -> float:
        return 0.0 if self.training else self.background

    # ---------------------------------------------------------------- loss
    def face_reg_points(self, n: int, generator: torch.Generator | None,
                        tracked: Callable[[], Tensor]) -> Tensor:
        """The n points (normalised, (n, 3)) the face-region regulariser holds still: on
        the neutral mesh where mesh-guided (the guide carries the face there before the
        warp), else on the frames' tracked face meshes (`tracked()`: world points)."""
        if self.expression.mesh_guided:
            return self.expression.neutral_points(n, generator)
        return self.normalize(tracked())

    def get_loss_dict(self, out: dict[str, Tensor], batch: LossBatch,
                      weights: LossWeights | None = None) -> LossTerms:
        """The whole loss of a forward pass `out` against `batch` (model/losses.py): the
        photometric terms (`photo`, and `photo_coarse` / `interlevel` where the sampler
        produces them), the face-depth prior where `batch` has mesh depths, the face-region
        regulariser ‖D(x_mesh; ω) − x_mesh‖ where it has points (and the model a warp)."""
        weights = weights or LossWeights()  # the photometric terms alone
        terms = LossTerms()
        raw, target = terms.raw, batch.rgb
        # background that moves by itself counts less: a static scene cannot explain it,
        # and fitting it anyway spends the warp and the per-frame codes on it
        ray_w = ray_weights(batch.moving, weights.moving)
        raw["photo"] = photometric_loss(out["rgb"], target, ray_w)
        photometric = raw["photo"]
        if "rgb_coarse" in out:
            raw["photo_coarse"] = photometric_loss(out["rgb_coarse"], target, ray_w)
            photometric = photometric + raw["photo_coarse"]
        if "interlevel" in out:
            raw["interlevel"] = out["interlevel"]
            photometric = photometric + weights.interlevel * out["interlevel"]
        terms.weighted["photometric"] = photometric
        if batch.mesh_depth is not None and weights.face_depth > 0:
            raw["face_depth"] = face_depth_loss(out["weights"], out["t"],
                                                still_depth(batch.mesh_depth, batch.moving),
                                                weights.face_depth_margin)
            terms.weighted["face_depth"] = weights.face_depth * raw["face_depth"]
        if batch.reg_points is not None and weights.face_reg > 0 and self.warp is not None:
            pts = batch.reg_points
            raw["face_reg"] = face_region_loss(self.warp_points(pts, batch.reg_codes), pts)
            terms.weighted["face_reg"] = weights.face_reg * raw["face_reg"]
        return terms

    # ---------------------------------------------------------------- rendering
    def forward(self, rays: RayBatch, jitter: bool = False,
                generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """-> rgb (R, 3), depth (R,), acc (R,), plus `rgb_coarse` for the hierarchical
        sampler and `num_samples` (network evaluations, for throughput figures)."""
        expr = self.expression.masked(rays.expression, rays.face_ray)
        kind = self.cfg.sampler.kind
        if kind == "hierarchical":
            return self._forward_hierarchical(rays, expr, jitter, generator)
        return self._forward_proposal(rays, expr, jitter, generator)

    def _forward_hierarchical(self, rays, expr, jitter, generator):
        s = self.cfg.sampler
        R = len(rays)
        t_c = stratified_samples(self.near, self.far, R, s.num_coarse, jitter,
                                 rays.origins.device, generator)
        sig_c, rgb_c = self._query_rays(self.field_coarse, rays, t_c, expr)
        w_c = render_weights(sig_c, self._deltas(t_c, rays.dirs, 1e10))
        out_c = composite(w_c, rgb_c, t_c)
        mids = 0.5 * (t_c[:, 1:] + t_c[:, :-1])
        t_f = sample_pdf(mids, w_c[:, 1:-1], s.num_fine, jitter, generator)
        if s.fine_reuses_coarse:
            t_f, _ = torch.sort(torch.cat([t_c, t_f], -1), -1)
        else:
            t_f, _ = torch.sort(t_f, -1)
        sig_f, rgb_f = self._query_rays(self.field, rays, t_f, expr)
        w_f = render_weights(sig_f, self._deltas(t_f, rays.dirs, 1e10))
        out = composite(w_f, rgb_f, t_f, self._background())
        out["rgb_coarse"], out["acc_coarse"] = out_c["rgb"], out_c["acc"]
        if self.training:
            out["weights"], out["t"] = w_f, t_f  # for the face-depth prior
        out["num_samples"] = torch.tensor(t_c.numel() + t_f.numel())
        return out

    def _forward_proposal(self, rays, expr, jitter, generator, num_main: int | None = None):
        s = self.cfg.sampler
        M = s.num_main if num_main is None else num_main
        R, P, dev = len(rays), s.num_proposal, rays.origins.device
        edges_p = torch.linspace(self.near, self.far, P + 1, device=dev).expand(R, P + 1)
        t_p = stratified_samples(self.near, self.far, R, P, jitter, dev, generator)
        xn = self.proposal_points(rays.origins, rays.dirs, t_p, rays.head)
        sig_p = self.proposal.density(xn, None if expr is None else expr[:, None])  # (R, P)
        scale = rays.dirs.norm(dim=-1, keepdim=True) / self.half_extent
        w_p = render_weights(sig_p, (edges_p[:, 1:] - edges_p[:, :-1]) * scale)
        edges_m, _ = torch.sort(sample_pdf(edges_p, w_p, M + 1, jitter, generator,
                                          stratified=True), -1)
        t_m = 0.5 * (edges_m[:, 1:] + edges_m[:, :-1])
        sig_m, rgb_m = self._query_rays(self.field, rays, t_m, expr)
        w_m = render_weights(sig_m, (edges_m[:, 1:] - edges_m[:, :-1]) * scale)
        out = composite(w_m, rgb_m, t_m, self._background())
        if self.training:
            out["interlevel"] = interlevel_loss(edges_m, w_m, edges_p, w_p)
            out["weights"], out["t"] = w_m, t_m  # for the face-depth prior
        out["num_samples"] = torch.tensor(R * M)
        if num_main is None and not self.training:
            out = self._refine_unfinished(out, w_p.sum(-1), rays, expr, jitter, generator)
        return out

    def _refine_unfinished(self, out, proposal_acc, rays, expr, jitter, generator):
        """The rays `SamplerConfig.unfinished` picks (by `out["acc"]` and the proposal's
        opacity (R,)) rendered again with `sampler.refine_main` samples."""
        s = self.cfg.sampler
        if s.refine_main <= 0:
            return out
        redo = s.unfinished(out["acc"], proposal_acc)
        if len(redo) == 0:
            return out
        again = self._forward_proposal(rays[redo], None if expr is None else expr[redo],
                                       jitter, generator, num_main=s.refine_main)
        for k in ("rgb", "depth", "acc"):
            out[k] = out[k].index_put((redo,), again[k])
        out["num_samples"] = out["num_samples"] + again["num_samples"]
        return out
