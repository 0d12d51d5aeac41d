"""Canonical radiance fields F(γ(x'), γ(d), φ, 𝕀β) -> (σ, c): the paper's NeRF MLP and a
hash-grid field with the same inputs and outputs."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flamenerf import gpu_kernels, runtime
from flamenerf.config import FieldConfig
from flamenerf.geometry import ellipsoid_weight
from flamenerf.model.encodings import HashGrid, pe_dim, positional_encoding
from flamenerf.model.mlp import MLP


def trunc_exp(x: Tensor) -> Tensor:
    # exp with a clamped argument: instant-ngp's density activation without overflow
    return torch.exp(x.clamp(max=15.0))


class NeRFField(nn.Module):
    """The paper's canonical NeRF: 8x256 trunk with a skip at layer 4 over (γ(x'), 𝕀β);
    σ from the trunk; colour from (trunk feature, γ(d), φ) through one 128-wide layer."""

    def __init__(self, cfg: FieldConfig, expr_dim: int):
        super().__init__()
        self.cfg, self.expr_dim = cfg, expr_dim
        in_dim = pe_dim(3, cfg.pos_freqs) + expr_dim
        self.trunk = MLP(in_dim, cfg.width, cfg.depth, cfg.skips)
        self.sigma = nn.Linear(cfg.width, 1)
        self.feature = nn.Linear(cfg.width, cfg.width)
        self.rgb = MLP(cfg.width + view_dim(cfg) + cfg.appearance_dim,
                       cfg.width // 2, 1, (), out_dim=3)

    def _trunk(self, x: Tensor, expr: Tensor | None) -> Tensor:
        return self.trunk(positional_encoding(x, self.cfg.pos_freqs),
                          expr if self.expr_dim else None)

    def density(self, x: Tensor, expr: Tensor | None) -> Tensor:
        return torch.relu(self.sigma(self._trunk(x, expr)))[..., 0]

    def forward(self, x: Tensor, d: Tensor, app: Tensor, expr: Tensor | None):
        """x (*bs, 3) canonical in [-1,1]^3; d (*, 3) unit, app (*, A), expr (*, E) either
        per point or per ray (broadcastable to *bs, e.g. (R, 1, ·) for x (R, S, 3)) ->
        σ (*bs), rgb (*bs, 3)."""
        h = self._trunk(x, expr)
        sigma = torch.relu(self.sigma(h))[..., 0]
        c = self.rgb(self.feature(h), _view_conditioning(d, app, self.cfg))
        return sigma, torch.sigmoid(c)


def view_dim(cfg: FieldConfig) -> int:
    """Width of γ(d) in the colour head's input: 0 for a field without view dependence."""
    return pe_dim(3, cfg.dir_freqs) if cfg.view_dependent else 0


def _view_conditioning(d: Tensor, app: Tensor, cfg: FieldConfig) -> Tensor:
    """[γ(d), φ] (or φ alone without view dependence): (*, 3), (*, A) ->
    (*, view_dim(cfg) + A)."""
    app = app.expand(*d.shape[:-1], -1)
    if not cfg.view_dependent:
        return app
    return torch.cat([positional_encoding(d, cfg.dir_freqs), app], -1)


class HashField(nn.Module):
    """Hash-grid features of x', then a one-hidden-layer density head over (features, 𝕀β)
    and a two-layer colour head over (geometry features, γ(d), φ)."""

    def __init__(self, cfg: FieldConfig, expr_dim: int,
                 detail_region: tuple[Tensor, Tensor, Tensor] | None = None):
        """detail_region: where `cfg.detail_levels` act, an ellipsoid in the field's own
        coordinates (the normalised canonical box): centre (3,), its axes as the columns of
        (3, 3), semi-axes (3,). Without one (a model built without a dataset) the field has
        no detail levels."""
        super().__init__()
        self.cfg, self.expr_dim = cfg, expr_dim
        if cfg.hash_max_res <= 0:
            raise ValueError("field.hash_max_res 0 (one cell per pixel at the face) is settled "
                             "for a dataset when a run is built (training.trainer."
                             "settle_dataset_defaults); set it to build a model without one")
        self.grid = HashGrid(cfg.hash_levels, cfg.hash_features, cfg.hash_log2_size,
                             cfg.hash_base_res, cfg.hash_max_res)
        self.expr_grid = None
        extra = 0
        if expr_dim and cfg.expr_rank > 0:
            self.expr_grid = HashGrid(cfg.expr_levels, cfg.expr_rank * cfg.expr_features,
                                      cfg.expr_log2_size, cfg.expr_base_res, cfg.expr_max_res)
            self.expr_proj = nn.Linear(expr_dim, cfg.expr_rank, bias=False)
            extra = cfg.expr_levels * cfg.expr_features
        self.detail = None
        if cfg.detail_levels > 0 and detail_region is not None:
            if cfg.detail_max_res <= cfg.hash_max_res:
                raise ValueError(f"field.detail_max_res ({cfg.detail_max_res}) must exceed "
                                 f"field.hash_max_res ({cfg.hash_max_res}); 0 is settled "
                                 "for a dataset when a run is built")
            # the levels go on where the main grid's stop, at its geometric growth's pace
            g = (cfg.detail_max_res / cfg.hash_max_res) ** (1 / cfg.detail_levels)
            # drawn aside from the global stream, so that the other parameters start as
            # without the detail levels (but the density head's wider first layer)
            with torch.random.fork_rng(devices=[]):
                self.detail = HashGrid(cfg.detail_levels, cfg.hash_features,
                                       cfg.detail_log2_size,
                                       max(int(cfg.hash_max_res * g), cfg.hash_max_res + 1),
                                       cfg.detail_max_res)
            extra += self.detail.out_dim
            for k, v in zip(("centre", "axes", "radii"), detail_region):
                self.register_buffer(f"detail_{k}", v.float().clone(), persistent=False)
        self.direct = bool(expr_dim) and (cfg.expr_direct or self.expr_grid is None)
        self.density_head = MLP(self.grid.out_dim + extra + (expr_dim if self.direct else 0),
                                cfg.head_width, 1, (),
                                out_dim=1 + cfg.geo_features)
        self.rgb = MLP(cfg.geo_features + view_dim(cfg) + cfg.appearance_dim,
                       cfg.head_width, 2, (), out_dim=3)

    def _geo(self, x: Tensor, expr: Tensor | None) -> Tensor:
        if (x.device.type == "cpu" and x.dtype == torch.float32 and not torch.is_grad_enabled()
                or runtime.gpu_inference(x.device) and torch.is_inference_mode_enabled()):
            h = self._features_in_place(x, expr)
        else:
            h = self.grid((x.reshape(-1, 3) + 1) * 0.5).view(*x.shape[:-1], -1)
            if self.detail is not None:
                h = torch.cat([h, self._detail_features(x)], -1)
            if self.expr_grid is not None:
                h = torch.cat([h, self._expression_features(x, expr)], -1)
        return self.density_head(h, expr if self.direct else None)

    @torch.no_grad()
    def _features_in_place(self, x: Tensor, expr: Tensor | None) -> Tensor:
        """`_geo`'s concatenated features without the `cat`: every part written into its
        columns of one buffer (the inference path). x (*bs, 3) -> (*bs, width), in the
        autocast dtype where autocast is on (the GPU's half precision: the density head
        reads it without a cast), else x's."""
        flat = x.reshape(-1, 3)
        dev = x.device.type
        dtype = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else x.dtype
        a = self.grid.out_dim
        width = (a + (self.detail.out_dim if self.detail is not None else 0)
                 + (self.expr_grid_width if self.expr_grid is not None else 0))
        # zeros: the detail and expression columns are written only where they are not 0
        # (one contiguous fill costs less than filling those columns of every row)
        buf = (flat.new_zeros(len(flat), width, dtype=dtype) if width > a
               else flat.new_empty(len(flat), a, dtype=dtype))
        self.grid.encode_into((flat + 1) * 0.5, buf[:, :a])
        if self.detail is not None:
            self._detail_features(x, out=buf[:, a:a + self.detail.out_dim])
            a += self.detail.out_dim
        if self.expr_grid is not None:
            self._expression_features(x, expr, out=buf[:, a:])
        return buf.view(*x.shape[:-1], width)

    @property
    def expr_grid_width(self) -> int:
        return self.cfg.expr_levels * self.cfg.expr_features

    def _detail_features(self, x: Tensor, out: Tensor | None = None) -> Tensor:
        """The detail levels times the head region's weight, evaluated only where it is
        non-zero (the tables then hold the head alone, so its cells collide only with each
        other). x (*bs, 3) -> (*bs, detail levels·features); or written into `out` (N, ·),
        a view holding zeros, without autograd."""
        flat = x.reshape(-1, 3)
        w = ellipsoid_weight(flat, self.detail_centre, self.detail_axes, self.detail_radii,
                             self.cfg.detail_band)
        idx = (w > 0).nonzero()[:, 0]
        f = (self.detail((flat[idx] + 1) * 0.5) * w[idx, None] if len(idx)
             else flat.new_zeros(0, self.detail.out_dim))
        return _scatter_rows(f, idx, len(flat), x.shape[:-1], out)

    def _expression_features(self, x: Tensor, expr: Tensor, out: Tensor | None = None
                             ) -> Tensor:
        """Σ_r (Aβ)_r G_r(x), evaluated only where β ≠ 0 (elsewhere it is exactly 0).
        x (*bs, 3), expr per point or broadcastable -> (*bs, levels·features); or written
        into `out` (N, ·), a view holding zeros, without autograd."""
        cfg = self.cfg
        L, R, Fe = cfg.expr_levels, cfg.expr_rank, cfg.expr_features
        bs, E = x.shape[:-1], expr.shape[-1]
        if torch.is_grad_enabled():  # A's gradient needs G wherever β ≠ 0
            z = self.expr_proj(expr).expand(*bs, R).reshape(-1, R)
            active = (expr.abs().amax(-1, keepdim=True) > 0).expand(*bs, 1).reshape(-1)
            idx = active.nonzero()[:, 0]
            z = z[idx]
        else:
            # the sum is 0 where β = 0 (A has no bias): project only the other points, found
            # by one matrix-vector product. Most points of an image lie outside the face's
            # silhouette; projecting all of them and testing Aβ was ~8 % of a 128 px viewer
            # update on the 2-core CPU
            live = (expr.abs() @ expr.new_ones(E)) > 0  # expr's leading shape
            idx = live.expand(bs).reshape(-1).nonzero()[:, 0]
            z = self.expr_proj(expr.expand(*bs, E).reshape(-1, E)[idx]) if len(idx) else None
        if len(idx):
            xs = (x.reshape(-1, 3)[idx] + 1) * 0.5
            f = None
            # at inference, the contraction inside the grid's kernel (`contract` picks the
            # CPU's or the GPU's); the training forward and the reference renderer keep the
            # product below
            if torch.is_inference_mode_enabled():
                f = self.expr_grid.contract(xs, z, Fe)
            if f is None:
                g = self.expr_grid(xs).view(-1, L, R, Fe)
                # (n, 1, 1, R) @ (n, L, R, F): a batched product, ~1.6x faster than the
                # equivalent einsum on a CPU
                f = torch.matmul(z[:, None, None, :], g).reshape(-1, L * Fe)
        else:
            f = x.new_zeros(0, L * Fe)
        return _scatter_rows(f, idx, x.numel() // 3, bs, out)

    def density(self, x: Tensor, expr: Tensor | None) -> Tensor:
        return trunc_exp(self._geo(x, expr)[..., 0])

    def forward(self, x: Tensor, d: Tensor, app: Tensor, expr: Tensor | None):
        """As NeRFField.forward."""
        if runtime.gpu_inference(x.device) and torch.is_inference_mode_enabled():
            fused = self._forward_fused(x, d, app, expr)
            if fused is not None:
                return fused
        g = self._geo(x, expr)
        sigma = trunc_exp(g[..., 0])
        c = self.rgb(g[..., 1:], _view_conditioning(d, app, self.cfg))
        return sigma, torch.sigmoid(c)

    def _forward_fused(self, x: Tensor, d: Tensor, app: Tensor, expr: Tensor | None
                       ) -> tuple[Tensor, Tensor] | None:
        """`forward` on the GPU's inference path: the features in one buffer, then both
        heads in one Triton kernel (gpu_kernels.field_heads), the colour head's per-ray
        conditioning applied once per ray. None where the kernel does not apply (β fed to
        the density head directly, per-sample conditioning of another shape, no Triton, the
        kernel turned off: FLAMENERF_GPU_KERNELS), before any work (the caller then computes the
        features itself)."""

        if (self.direct or not gpu_kernels.available(x.device)
                or "field_heads" not in gpu_kernels.working()):
            return None
        bs, geo = x.shape[:-1], self.cfg.geo_features
        cond = _view_conditioning(d, app, self.cfg)
        if cond.shape[:-1] == bs:
            per = 1
        elif len(bs) == 2 and cond.shape[:-1] == (bs[0], 1):
            per = bs[1]  # one row per ray, its samples share it
        else:
            return None
        first = self.rgb.layers[0]
        term = F.linear(cond.reshape(-1, cond.shape[-1]), first.weight[:, geo:], first.bias)
        feats = self._features_in_place(x, expr)
        out = gpu_kernels.field_heads(feats.reshape(-1, feats.shape[-1]), term.float(), per,
                                      self.density_head, self.rgb)
        if out is None:
            return None
        return out[0].view(bs), out[1].view(*bs, 3)


class ProposalField(nn.Module):
    """Density only, from a small hash grid of observation-space x and 𝕀β: cheap enough to
    evaluate densely along every ray, so that the main field is evaluated where it matters."""

    def __init__(self, levels: int, log2_size: int, max_res: int, width: int, expr_dim: int):
        super().__init__()
        self.expr_dim = expr_dim
        self.grid = HashGrid(levels, 2, log2_size, 16, max_res)
        self.head = MLP(self.grid.out_dim + expr_dim, width, 1, (), out_dim=1)

    def density(self, x: Tensor, expr: Tensor | None) -> Tensor:
        """x (*bs, 3) in [-1, 1]^3, expr per point or per ray (broadcastable) -> σ (*bs)."""
        return trunc_exp(self.raw_density(x, expr))

    def raw_density(self, x: Tensor, expr: Tensor | None) -> Tensor:
        """The density before its activation; expr None means 𝕀β = 0. -> (*bs)."""
        h = self.grid((x.reshape(-1, 3) + 1) * 0.5).view(*x.shape[:-1], -1)
        if self.expr_dim and expr is None:
            expr = h.new_zeros(self.expr_dim)
        return self.head(h, expr if self.expr_dim else None)[..., 0]


def _scatter_rows(f: Tensor, idx: Tensor, n: int, bs: tuple, out: Tensor | None) -> Tensor:
    """Rows f (M, C) at idx (M,) of an (n, C) zero tensor -> viewed as (*bs, C); or written
    into `out` (n, C), a view into a wider buffer that holds zeros, and returned as it."""
    if out is not None:
        if len(idx):
            out.index_copy_(0, idx, f.to(out.dtype))
        return out
    # zeros in f's dtype: under CUDA's autocast f may be half, and index_copy does not
    # promote there (CPU autocast does, so only a GPU run showed it)
    z = f.new_zeros(n, f.shape[-1])
    return (z.index_copy(0, idx, f) if len(idx) else z).view(*bs, f.shape[-1])


def make_field(cfg: FieldConfig, expr_dim: int,
               detail_region: tuple[Tensor, Tensor, Tensor] | None = None) -> nn.Module:
    """The canonical field of `cfg.kind`; detail_region: HashField's (the MLP has none)."""
    if cfg.kind == "hash":
        return HashField(cfg, expr_dim, detail_region)
    return NeRFField(cfg, expr_dim)
