"""How the frame's expression β reaches the canonical field: FLAME-in-NeRF's conditioning,
top to bottom, in one place.

1. `masked`: the spatial prior. A ray's β reaches the networks only where its pixel lies
   inside the face model's silhouette (the paper's 𝕀(x)·β; `expression_mode`: `masked`,
   `none` for the Nerfies variant, `everywhere` for the no-prior ablation), centred on the
   training frames' mean β̄ and scaled: 𝕀·(β − β̄)·s. `inside` says which rays it lets in,
   and `confined` whether β can change only rays through the silhouette, which is what
   the renderers' caches ask before they keep the other pixels.
2. Per point (`point_inputs`), this project's refinements of the same prior, never wider:
   - per-control regions: control k reaches a point only near the face-mesh vertices k
     moves in the per-subject β -> mesh model (`region_expression`);
   - the mesh guide: points near the face are carried from the mesh of the ray's β to the
     neutral mesh before the warp (`guide_points`), so that the warp and the field see the
     face at rest and β is left the residual.
   Both look up the nearest vertices of each point on the mesh of its ray's own β, once
   (`shared_neighbours`).
3. The fields then take the per-point expression (model/field.py: the hash field's
   expression feature fields, the MLPs' inputs).

`raw` undoes step 1 for the mesh model, which works with β itself.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from flamenerf.config import ModelConfig
from flamenerf.meshes import (GUIDE_CUTOFF, displacement_of_neighbours, expression_mesh,
                              nearest_vertices, surface_points)

GATE_CUTOFF = 3.0
"""Per-control prior: gates are exp(-(d/r)²), cut to 0 beyond d = 3r (exp(-9) ≈ 1e-4)."""


def distinct_rows(x: Tensor) -> tuple[Tensor, Tensor]:
    """torch.unique(x, dim=0, return_inverse=True) for x (N, E), with the common case (an
    image or a viewer update: every row the same) answered without unique's row-by-row
    comparisons (~4 % of a 128 px viewer update's CPU time under torch's profiler).
    -> (U, E), (N,) long."""
    if len(x) and bool((x == x[:1]).all()):
        return x[:1], torch.zeros(len(x), dtype=torch.long, device=x.device)
    return torch.unique(x, dim=0, return_inverse=True)


class ExpressionConditioner(nn.Module):
    """The expression pathway (module docstring). `center` (3,) and `half_extent` () are
    the scene box's normalisation, which the model's points are in."""

    def __init__(self, cfg: ModelConfig, expr_dim: int, center: Tensor, half_extent: Tensor,
                 mesh_vertices: int = 0, mesh_faces: int = 0):
        super().__init__()
        self.cfg = cfg
        self.expr_dim = expr_dim
        self.mesh_guided = bool(cfg.mesh_guide.enabled) and self.mode != "none"
        self.regions = cfg.expression_regions.enabled and self.mode != "none"
        self.uses_mesh_model = self.mesh_guided or self.regions
        # the box, constant after construction (the model's own buffers are the saved ones)
        self.register_buffer("center", center.clone(), persistent=False)
        self.register_buffer("half_extent", half_extent.clone(), persistent=False)
        # β̄ of `cfg.expression_centre` (set_mean; zeros: β enters as it is)
        self.register_buffer("mean", torch.zeros(expr_dim), persistent=False)
        if self.uses_mesh_model:
            if mesh_vertices <= 0 or mesh_faces <= 0:
                raise ValueError("the per-subject face-mesh model needs the mesh's vertex and "
                                 "face counts")
            # the per-subject expression model (world units), filled by set_mesh_model
            self.register_buffer("mesh_neutral", torch.zeros(mesh_vertices, 3))
            self.register_buffer("mesh_basis", torch.zeros(expr_dim, mesh_vertices, 3))
            self.register_buffer("mesh_faces", torch.zeros(mesh_faces, 3, dtype=torch.long))
            # (V, E): how much of control k's β each vertex's neighbourhood receives
            self.register_buffer("mesh_regions", torch.zeros(mesh_vertices, expr_dim))
            # (V,): vertices that do not guide (`set_guide_skip`)
            self.register_buffer("guide_skip", torch.zeros(mesh_vertices, dtype=torch.bool),
                                 persistent=False)
            self._any_guide_skip = False  # on the host: no device sync per guided batch

    # ---------------------------------------------------------------- the spatial prior
    @property
    def mode(self) -> str:
        """`masked` (the spatial prior), `none` (no β: Nerfies), `everywhere` (no prior)."""
        return self.cfg.expression_mode

    def masked(self, expression: Tensor, face_ray: Tensor) -> Tensor | None:
        """𝕀(x)·β, what the networks see: the spatial prior. (R, E), (R,) -> (R, E), or
        None for `nerfies`; 𝕀·(β − β̄) with `expression_centre`."""
        if self.mode == "none":
            return None
        e = (expression - self.mean) * self.cfg.expression_scale
        if self.mode == "masked":
            e = e * face_ray[:, None].to(e)
        return e

    def inside(self, face_ray: Tensor) -> Tensor | None:
        """Which rays' β passes the prior: (R,) bool -> (R,) bool (every ray for the
        no-prior ablation), None for `nerfies`."""
        if self.mode == "none":
            return None
        return (face_ray.bool() if self.mode == "masked"
                else torch.ones_like(face_ray, dtype=torch.bool))

    @property
    def confined(self) -> bool:
        """Whether β changes only rays through the prior's silhouette (the spatial prior,
        or no β at all): where only β changes, a renderer may keep every other pixel
        (the viewer's slider, a re-animation from a still camera). Not so for the no-prior
        ablation, whose β reaches every ray."""
        return self.mode in ("masked", "none")

    @property
    def reaches_nothing(self) -> bool:
        """Whether β reaches no ray at all (the Nerfies variant): a new β changes nothing."""
        return self.mode == "none"

    def raw(self, expr: Tensor, inside: Tensor | None) -> tuple[Tensor, Tensor]:
        """The β behind network inputs `expr` (R, E) (`masked`'s output) of rays whose prior
        lets β in (`inside` (R,) bool; None: the rays whose input is not 0, right when β is
        not centred) -> β (R, E), inside (R,). The meshes, the per-control prior and the
        mesh guide work with β itself."""
        if inside is None:
            inside = expr.abs().amax(-1) > 0
        beta = expr / self.cfg.expression_scale + inside[:, None].to(expr) * self.mean
        return beta, inside

    def set_mean(self, mean: Tensor) -> None:
        """β̄ (E,): the networks see 𝕀·(β − β̄) (`masked`)."""
        self.mean.copy_(mean.to(self.mean))

    # ---------------------------------------------------------------- the face-mesh model
    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.center) / self.half_extent

    def set_mesh_model(self, neutral: Tensor, basis: Tensor, faces: Tensor,
                       mesh_only: list[int] | tuple[int, ...] = ()) -> None:
        """neutral (V, 3), basis (E, V, 3) world units (`meshes.fit_expression_model`),
        faces (F, 3). `mesh_only`: controls that act through the mesh alone (generic shapes
        of controls the training frames never moved, data/generic_shapes.py): no region, so
        the fields never see them, as in training, and the mesh guide moves the face."""
        self.mesh_neutral.copy_(neutral)
        self.mesh_basis.copy_(basis)
        self.mesh_faces.copy_(faces)
        motion = basis.norm(dim=-1)  # (E, V)
        top = motion.amax(-1, keepdim=True)
        thr = self.cfg.expression_regions.threshold
        # soft membership: 1 where the control moves a vertex by thr of its largest motion
        # or more, fading to 0 with the motion, so that gates vary smoothly across the face
        soft = (motion / (thr * top).clamp_min(1e-12)).clamp(max=1.0) * (top > 0)
        soft[list(mesh_only)] = 0.0
        self.mesh_regions.copy_(soft.T)

    def set_guide_skip(self, vertices: Tensor) -> None:
        """Vertex indices (K,) that the mesh guide ignores (`mesh_guide.max_residual`)."""
        self.guide_skip.zero_()
        self.guide_skip[vertices.to(self.guide_skip.device)] = True
        self._any_guide_skip = len(vertices) > 0

    def face_mesh(self, expression: Tensor) -> Tensor:
        """The face mesh of β in world units: (..., E) -> (..., V, 3)."""
        return expression_mesh(self.mesh_neutral, self.mesh_basis, expression)

    def neutral_points(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """n uniformly random points on the neutral mesh, normalised. -> (n, 3)."""
        dev = self.mesh_neutral.device
        tri = torch.randint(len(self.mesh_faces), (n,), generator=generator).to(dev)
        uv = torch.rand(n, 2, generator=generator).to(dev)
        return self.normalize(surface_points(self.mesh_neutral, self.mesh_faces, tri, uv))

    def _neutral_diagonal(self) -> float:
        # kept while the mesh and the box are the same tensors, unchanged in place (writes
        # through `.data` excepted, as for the bakes): reading it from a GPU waits for the
        # device, three times per guided batch
        ts = [t for t in (self.mesh_neutral, self.center, self.half_extent)
              if isinstance(t, Tensor)]
        kept = getattr(self, "_neutral_diagonal_kept", None)
        if kept is None or len(kept[0]) != len(ts) or not all(
                a is t and v == t._version for (a, v), t in zip(kept[0], ts)):
            neutral = self.normalize(self.mesh_neutral)
            kept = (tuple((t, t._version) for t in ts),
                    float((neutral.amax(0) - neutral.amin(0)).norm()))
            self._neutral_diagonal_kept = kept
        return kept[1]

    def _guide_falloff(self) -> float:
        return self.cfg.mesh_guide.falloff * self._neutral_diagonal()

    def _gate_radius(self) -> float:
        # settled per dataset when a run is built (trainer.settle_dataset_defaults); a model
        # made without a dataset (tests, untrained benchmarks) has no face parts
        return self.cfg.expression_regions.resolved_radius(False) * self._neutral_diagonal()

    # ---------------------------------------------------------------- per point
    def point_inputs(self, xn: Tensor, expr: Tensor | None, inside: Tensor | None
                     ) -> tuple[Tensor, Tensor | None]:
        """Normalised samples xn (R, S, 3) of rays with masked expressions `expr` (R, E)
        (`masked`; `inside`: `inside`'s rays, None as in `raw`) -> the points the warp
        takes (carried to the neutral mesh where mesh-guided) and each point's expression
        (R, S, E) under the per-control prior, or (R, 1, E) per ray without it (None for
        `nerfies`)."""
        shared = self.shared_neighbours(xn, expr, inside)
        expr_pts = self.region_expression(xn, expr, inside, shared)
        return self.guide_points(xn, expr, inside, shared), expr_pts

    def _ray_neighbours(self, xn: Tensor, beta: Tensor, rows: Tensor, k: int, bound: float
                        ) -> dict:
        """The k nearest vertices (within `bound`) of the points xn[rows] (n, S, 3) on the
        mesh of their ray's own β (R, E), one mesh per distinct β (a training batch has
        ~100, an image one) -> {"rows", "beta" (n, E), "meshes" (U, V, 3), "d2k" (n·S, k),
        "idx" (n·S, k) into the U·V stacked vertices}."""
        uniq, inv = distinct_rows(beta[rows])
        meshes = self.normalize(self.face_mesh(uniq))  # (U, V, 3)
        d2k, idx = nearest_vertices(xn[rows], meshes, min(k, meshes.shape[1]), bound, inv)
        return {"rows": rows, "beta": beta[rows], "meshes": meshes, "d2k": d2k, "idx": idx}

    @torch.no_grad()
    def shared_neighbours(self, xn: Tensor, expr: Tensor | None,
                          inside: Tensor | None = None) -> dict | None:
        """With both the per-control prior and the mesh guide: `_ray_neighbours` of the rays
        `inside`, one query that serves both (`_region_gates` takes the nearest, the guide
        all k; two queries were a sixth of a guided 256 px frame on a CPU). None where not
        both."""
        if expr is None or not (self.mesh_guided and self.regions):
            return None
        beta, inside = self.raw(expr.detach(), inside)
        rows = inside.nonzero()[:, 0]
        if len(rows) == 0:
            return None
        bound = max(GUIDE_CUTOFF * self._guide_falloff(), GATE_CUTOFF * self._gate_radius())
        return self._ray_neighbours(xn, beta, rows, self.cfg.mesh_guide.neighbours, bound)

    @torch.no_grad()
    def guide_points(self, xn: Tensor, expr: Tensor | None, inside: Tensor | None = None,
                     shared: dict | None = None) -> Tensor:
        """Carry normalised points (R, S, 3) of rays with masked expressions (R, E)
        (`masked`; `inside` as in `raw`) from their expression's mesh to the neutral mesh.
        Rays outside the silhouette under the prior, and rays with β = 0, get mesh(0) =
        neutral, i.e. stay put. `shared`: `shared_neighbours`."""
        if not self.mesh_guided or expr is None:
            return xn
        falloff, S = self._guide_falloff(), xn.shape[1]
        if shared is None:
            beta, inside = self.raw(expr, inside)
            rows = (inside & (beta.abs().amax(-1) > 0)).nonzero()[:, 0]
            if len(rows) == 0:
                return xn
            nb = self._ray_neighbours(xn, beta, rows, self.cfg.mesh_guide.neighbours,
                                      GUIDE_CUTOFF * falloff)
            d2k, idx = nb["d2k"], nb["idx"]
        else:  # the rays with β = 0 among the shared ones stay put
            nb = shared
            moving = nb["beta"].abs().amax(-1) > 0
            if not bool(moving.any()):
                return xn
            rows, k = nb["rows"][moving], nb["d2k"].shape[-1]
            d2k = nb["d2k"].view(-1, S, k)[moving].reshape(-1, k)
            idx = nb["idx"].view(-1, S, k)[moving].reshape(-1, k)
        if self._any_guide_skip:  # those vertices neither move points nor fade them
            d2k = d2k.masked_fill(self.guide_skip[idx % self.guide_skip.shape[0]], float("inf"))
            d2k, order = d2k.sort(1)
            idx = idx.gather(1, order)
        move = displacement_of_neighbours(d2k, idx, nb["meshes"],
                                          self.normalize(self.mesh_neutral), falloff)
        out = xn.clone()
        out[rows] = xn[rows] + move.view(len(rows), S, 3)
        return out

    def region_expression(self, xn: Tensor, expr: Tensor | None,
                          inside: Tensor | None = None, shared: dict | None = None
                          ) -> Tensor | None:
        """Per-point masked expressions under the per-control prior: input k fades with
        the distance from the vertices (of the ray's own expression mesh) that control k
        moves. xn (R, S, 3) normalised, expr (R, E) (`masked`; `inside` as in `raw`;
        `shared`: `shared_neighbours`) -> (R, S, E); per-ray `expr` as (R, 1, E) when the
        prior is off."""
        if expr is None:
            return None
        if not self.regions:
            return expr[:, None]
        beta, inside = self.raw(expr.detach(), inside)
        return self._region_gates(xn, beta, inside, shared=shared) * expr[:, None]

    @torch.no_grad()
    def _region_gates(self, xn: Tensor, beta: Tensor, inside: Tensor | None = None,
                      shared: dict | None = None) -> Tensor:
        """(R, S, 3), β (R, E), inside (R,) bool -> (R, S, E) in [0, 1]: each point's share
        of each control, the membership of its nearest vertex (on the mesh of the ray's
        own β) in the control's region times exp(-d²/r²) of the distance d to that vertex,
        cut to 0 beyond d = GATE_CUTOFF·r (where it is below 1e-4: the expression fields
        then skip the point). Rays not `inside` (None: rays with β = 0) get 0."""
        out = xn.new_zeros(*xn.shape[:2], beta.shape[-1])
        if inside is None:
            inside = beta.abs().amax(-1) > 0
        rows = inside.nonzero()[:, 0]
        if len(rows) == 0:
            return out
        r = self._gate_radius()
        S, cut = xn.shape[1], GATE_CUTOFF * r
        if shared is None:
            shared = self._ray_neighbours(xn, beta, rows, 1, cut)
        # the nearest vertex (of the guide's k, when shared)
        d = shared["d2k"][:, 0].sqrt()
        d = d.masked_fill(d > cut, float("inf"))
        nn_ = shared["idx"][:, 0] % self.mesh_regions.shape[0]
        out[shared["rows"]] = (self.mesh_regions[nn_] * torch.exp(-(d / r).square())[:, None]
                               ).view(len(shared["rows"]), S, -1)
        return out
