"""Input encodings: NeRF positional encoding with the Nerfies coarse-to-fine window, and a
pure-PyTorch multiresolution hash grid.

PE convention (pinned by tests): γ(x) = (x, sin(2^0 πx), cos(2^0 πx), ..., sin(2^{m-1} πx),
cos(2^{m-1} πx)), blocks ordered by frequency, sin before cos, input first; x is in the
normalised scene box [-1, 1]^3.
"""

from __future__ import annotations

import ctypes
import math

import torch
from torch import Tensor, nn

from flamenerf import cpu_kernels, gpu_kernels, runtime


def cosine_easing_window(num_freqs: int, alpha: float | Tensor) -> Tensor:
    """Coarse-to-fine weights w_l(α) = (1 − cos(π·clamp(α − l, 0, 1))) / 2, l = 0..m−1.

    -> (num_freqs,). α = m·t/N grows with the step t; all bands are on once α ≥ m.
    """
    bands = torch.arange(num_freqs, dtype=torch.float32)
    x = torch.clamp(torch.as_tensor(alpha, dtype=torch.float32) - bands, 0.0, 1.0)
    return 0.5 * (1.0 - torch.cos(math.pi * x))


def positional_encoding(x: Tensor, num_freqs: int, window: Tensor | None = None) -> Tensor:
    """(*bs, d) -> (*bs, d + 2·d·num_freqs). `window` (num_freqs,) weights each band."""
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xb = x[..., None, :] * freqs[:, None]  # (*bs, m, d)
    enc = torch.stack([torch.sin(xb), torch.cos(xb)], dim=-2)  # (*bs, m, 2, d)
    if window is not None:
        enc = enc * window.to(x)[:, None, None]
    return torch.cat([x, enc.flatten(-3)], dim=-1)


def pe_dim(d: int, num_freqs: int) -> int:
    return d + 2 * d * num_freqs


_PRIMES = (1, 2654435761, 805459861)
_PRIMES32 = tuple(p - (1 << 32) if p >= 1 << 31 else p for p in _PRIMES)


class HashGrid(nn.Module):
    """Multiresolution hash encoding (Müller et al. 2022).

    Tables are (T_l, F), one per level. On a CPU a compiled kernel encodes (cache misses
    on the tables bound the cost there, and an entry's features side by side halve them);
    on a GPU `forward_grouped` (every level of a kind in one set of PyTorch ops: kernel
    launches bound the cost there); `forward_torch`, level by level, is the reference.
    """

    def __init__(self, levels: int = 16, features: int = 2, log2_size: int = 17,
                 base_res: int = 16, max_res: int = 1024):
        super().__init__()
        self.levels, self.features, self.size = levels, features, 2**log2_size
        growth = math.exp((math.log(max_res) - math.log(base_res)) / max(levels - 1, 1))
        res = [int(math.floor(base_res * growth**lv)) for lv in range(levels)]
        self.register_buffer("res", torch.tensor(res, dtype=torch.int64), persistent=False)
        dense = [(r + 1) ** 3 <= self.size for r in res]
        self.register_buffer("dense", torch.tensor(dense), persistent=False)
        # One table per level, sized to what the level can address: the gradient of an
        # index_select is a zero-filled tensor of the table's size, so per-level tables
        # keep that fill small (one shared table spent 25% of a CPU step in fill_).
        self.tables = nn.ParameterList([
            nn.Parameter(torch.empty((r + 1) ** 3 if d else self.size, features)
                         .uniform_(-1e-4, 1e-4))
            for r, d in zip(res, dense)])

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def forward(self, x: Tensor) -> Tensor:
        """x (N, 3) in [0, 1]^3 -> (N, L·F). On a CPU, the compiled kernel when it builds
        (cpu_kernels.py), else `forward_torch`; on a GPU without autograd the Triton
        kernel (gpu_kernels.py) where Triton is installed; else `forward_grouped`."""
        if (x.device.type == "cpu" and x.dtype == torch.float32
                and self.tables[0].dtype == torch.float32):  # the kernel is float32 only

            lib = cpu_kernels.kernel_library()
            if lib is not None:
                return _HashGridCPU.apply(x.contiguous(), self, lib, *self.tables)
            return self.forward_torch(x)
        if not torch.is_grad_enabled():

            if gpu_kernels.available(x.device):  # inference on a GPU: one fused kernel
                out = gpu_kernels.hashgrid_forward(self, x)
                if out is not None:
                    return out
        return self.forward_grouped(x)

    @torch.no_grad()
    def encode_into(self, x: Tensor, out: Tensor) -> None:
        """out[:] = self(x) without autograd: x (N, 3) in [0, 1]^3, out (N, L·F) a view
        whose rows may lie in a wider buffer (unit column stride). The CPU's kernel and the
        GPU's Triton kernel write there directly, so that the features of several grids end
        up side by side without a `cat` (at inference on a CPU, that copy was ~5 % of a
        256 px frame; on a GPU the kernel also stores half precision, without a cast)."""
        if (x.device.type == "cpu" and x.dtype == torch.float32 and out.dtype == torch.float32
                and self.tables[0].dtype == torch.float32 and out.stride(-1) == 1
                and out.shape == (x.shape[0], self.out_dim)):

            lib = cpu_kernels.kernel_library()
            if lib is not None:
                _kernel_forward(lib, self, x.contiguous(),
                                [t.detach().contiguous() for t in self.tables], out)
                return
        if out.stride(-1) == 1 and out.shape == (x.shape[0], self.out_dim):

            # the Triton kernel stores in out's dtype (half on the GPU's inference path)
            if (gpu_kernels.available(x.device)
                    and gpu_kernels.hashgrid_forward(self, x, out=out) is not None):
                return
        out.copy_(self(x))

    @torch.no_grad()
    def contract(self, x: Tensor, z: Tensor, features: int) -> Tensor | None:
        """Σ_r z_r G_r(x) at each level, the level's F features read as (rank, features)
        (the expression feature fields, model/field.py), without writing the (N, L·F)
        features: x (N, 3) in [0, 1]^3, z (N, rank) -> (N, L·features) float32. By the
        CPU's compiled kernel or the GPU's Triton kernel; None where neither runs (the
        caller then multiplies the features itself)."""
        rank = self.features // features
        if rank * features != self.features or z.shape != (x.shape[0], rank):
            return None
        if runtime.gpu_inference(x.device):

            return (gpu_kernels.hashgrid_contract(self, x, z, features)
                    if gpu_kernels.available(x.device) else None)
        if x.device.type != "cpu":
            return None

        lib = cpu_kernels.kernel_library()
        if lib is None or self.features > 64 or self.tables[0].dtype != torch.float32:
            return None
        x, z = x.float().contiguous(), z.float().contiguous()
        out = torch.empty(x.shape[0], self.levels * features)
        res, dense = self.kernel_layout()
        tables = [t.detach().contiguous() for t in self.tables]
        lib.hashgrid_contract(x.data_ptr(), x.shape[0], self.levels, self.features,
                              _pointers(tables), res, dense, self.size - 1, z.data_ptr(),
                              rank, out.data_ptr(), out.stride(0), torch.get_num_threads())
        return out

    def kernel_layout(self) -> tuple:
        """ctypes arrays of the per-level resolutions and dense flags."""
        if getattr(self, "_layout", None) is None:
            L = self.levels
            self._layout = ((ctypes.c_int64 * L)(*self.res.tolist()),
                            (ctypes.c_uint8 * L)(*[int(d) for d in self.dense.tolist()]))
        return self._layout

    def level_groups(self) -> list[tuple[int, int, bool]]:
        """Runs of consecutive levels of one kind: (first, end, dense)."""
        dense = self.dense.tolist()
        groups, lo = [], 0
        for lv in range(1, self.levels + 1):
            if lv == self.levels or dense[lv] != dense[lo]:
                groups.append((lo, lv, bool(dense[lo])))
                lo = lv
        return groups

    def forward_grouped(self, x: Tensor) -> Tensor:
        """The same encoding with every level of a kind (dense, hashed) in one set of ops:
        the GPU path. Level by level, a training step of `fast` launched ~3,700 kernels
        and left an H100 idle ~90 % of the step (docs/bench/gpu_profile.json); here
        the launches do not grow with the levels (1,500 per step). x (N, 3) -> (N, L·F)."""
        n, dev = x.shape[0], x.device
        xs = x.clamp(0, 1)
        outs = []
        for lo, hi, dense in self.level_groups():
            r = self.res[lo:hi].to(dev)  # (G,)
            rf = r.to(xs.dtype)[:, None, None]
            pos = xs[None] * rf  # (G, N, 3): the same float32 products as level by level
            base = torch.minimum(torch.floor(pos.detach()), rf - 1)
            frac = pos - base
            # int32 indices: half the index arithmetic's memory traffic. A hashed index keeps
            # the low log2_size bits of its products, which wrap-around int32 arithmetic
            # gives exactly (the primes as their int32 bit patterns); dense indices and the
            # tables' offsets stay below 2^31
            b = base.to(torch.int32)
            if dense:
                r32 = r.to(torch.int32)
                stride = torch.stack([torch.ones_like(r32), r32 + 1, (r32 + 1) ** 2], -1)
                combine = torch.add
            else:
                stride = torch.tensor(_PRIMES32, dtype=torch.int32, device=dev).expand(hi - lo, 3)
                combine = torch.bitwise_xor
            t0 = b * stride[:, None]  # (G, N, 3)
            t1 = t0 + stride[:, None]
            terms = [(t0[..., i], t1[..., i]) for i in range(3)]
            xy = [combine(tx, ty) for tx in terms[0] for ty in terms[1]]
            idx = torch.stack([combine(v, tz) for v in xy for tz in terms[2]])  # (8, G, N)
            if not dense:
                idx = idx & (self.size - 1)
            sizes = [len(t) for t in self.tables[lo:hi]]
            offsets = torch.tensor([0, *sizes[:-1]], dtype=torch.int32, device=dev).cumsum(
                0, dtype=torch.int32)
            idx = idx + offsets[None, :, None]
            fx, fy, fz = frac.unbind(-1)
            wxy = [wx * wy for wx in (1 - fx, fx) for wy in (1 - fy, fy)]
            w = torch.stack([v * wz for v in wxy for wz in (1 - fz, fz)])  # (8, G, N)
            table = torch.cat(list(self.tables[lo:hi])) if hi - lo > 1 else self.tables[lo]
            f = table.index_select(0, idx.reshape(-1)).view(8, hi - lo, n, self.features)
            outs.append((f * w[..., None]).sum(0).permute(1, 0, 2).reshape(n, -1))
        return torch.cat(outs, -1)

    def forward_torch(self, x: Tensor) -> Tensor:
        """The same encoding as PyTorch ops, level by level (the CPU's fallback and the
        kernel's reference)."""
        n = x.shape[0]
        xs = x.clamp(0, 1)
        mask = self.size - 1  # the table size is a power of two: `& mask` is `% size`
        outs = []
        # One level at a time, corners built from per-axis terms: every intermediate is
        # (N,) or (8, N), which keeps memory traffic (the CPU's bottleneck) low.
        for lv, (r, dense) in enumerate(zip(self.res.tolist(), self.dense.tolist())):
            pos = xs * r
            # x = 1 lies on the top face: keep its cell inside the grid (frac becomes 1)
            base = torch.floor(pos.detach()).clamp(max=r - 1)
            frac = pos - base  # (N, 3)
            b = base.to(torch.int64)
            if dense:
                terms = [(b[:, 0], b[:, 0] + 1),
                         (b[:, 1] * (r + 1), (b[:, 1] + 1) * (r + 1)),
                         (b[:, 2] * (r + 1) ** 2, (b[:, 2] + 1) * (r + 1) ** 2)]
                combine = torch.add
            else:
                terms = [(b[:, i] * p, (b[:, i] + 1) * p) for i, p in enumerate(_PRIMES)]
                combine = torch.bitwise_xor
            xy = [combine(tx, ty) for tx in terms[0] for ty in terms[1]]  # 4 x (N,)
            idx = torch.stack([combine(v, tz) for v in xy for tz in terms[2]])  # (8, N)
            if not dense:
                idx = idx & mask
            fx, fy, fz = frac.unbind(-1)
            wxy = [wx * wy for wx in (1 - fx, fx) for wy in (1 - fy, fy)]
            w = torch.stack([v * wz for v in wxy for wz in (1 - fz, fz)])  # (8, N)
            table = self.tables[lv]
            if table.device.type == "cpu":
                # gathering from a feature-major copy is faster on a CPU (fallback `fast`
                # step 1.44 s -> 1.29 s; PERF_NOTES: index_select on (F, T) is the best layout)
                f = table.t().contiguous().index_select(1, idx.reshape(-1)).view(-1, 8, n)
                outs.append((f * w).sum(1).t())  # (N, F)
            else:
                f = table.index_select(0, idx.reshape(-1)).view(8, n, self.features)
                outs.append((f * w[..., None]).sum(0))  # (N, F)
        return torch.cat(outs, -1)


def _pointers(tensors) -> ctypes.Array:
    return (ctypes.c_void_p * len(tensors))(*[0 if t is None else t.data_ptr() for t in tensors])


def _kernel_forward(lib, grid: HashGrid, x: Tensor, tables, out: Tensor) -> None:
    """The compiled forward pass: x (N, 3) contiguous float32, tables the grid's (contiguous),
    out (N, L·F) float32 with unit column stride, its rows out.stride(0) floats apart."""
    res, dense = grid.kernel_layout()
    lib.hashgrid_forward(x.data_ptr(), x.shape[0], grid.levels, grid.features,
                         _pointers(tables), res, dense, grid.size - 1, out.data_ptr(),
                         out.stride(0), torch.get_num_threads())


class _HashGridCPU(torch.autograd.Function):
    """HashGrid.forward through the compiled kernel; gradients for x and every table."""

    @staticmethod
    def forward(ctx, x: Tensor, grid: HashGrid, lib, *tables: Tensor) -> Tensor:
        tables = tuple(t.detach().contiguous() for t in tables)
        out = torch.empty(x.shape[0], grid.out_dim, dtype=x.dtype)
        _kernel_forward(lib, grid, x, tables, out)
        ctx.grid, ctx.lib = grid, lib
        ctx.save_for_backward(x, *tables)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gout: Tensor):
        x, *tables = ctx.saved_tensors
        grid, lib = ctx.grid, ctx.lib
        gout = gout.contiguous()
        gx = torch.empty_like(x) if ctx.needs_input_grad[0] else None
        scratch = torch.empty(grid.levels, *x.shape) if gx is not None else None
        gts = [torch.zeros_like(t) if ctx.needs_input_grad[3 + i] else None
               for i, t in enumerate(tables)]
        res, dense = grid.kernel_layout()
        any_table = any(g is not None for g in gts)
        lib.hashgrid_backward(x.data_ptr(), x.shape[0], grid.levels, grid.features,
                              _pointers(tables), res, dense, grid.size - 1,
                              gout.data_ptr(), _pointers(gts) if any_table else None,
                              None if gx is None else gx.data_ptr(),
                              None if gx is None else scratch.data_ptr(), torch.get_num_threads())
        return (gx, None, None, *gts)
