"""Triton kernels for GPUs: the hash grid's encoding without autograd (every level in one
kernel; for the expression feature fields contracted with each point's projected β in the
same kernel), a hash field's density and colour heads in one kernel (`field_heads`), and
the k nearest mesh vertices of many points.

On a GPU, `HashGrid.forward_grouped` builds each corner's index and weight as separate
PyTorch tensors (G, N) and gathers them with `index_select`: an H100 spent most of a
256 px frame in those gathers and the elementwise index arithmetic around them
(docs/bench/gpu_profile.json). Here each program takes a block of points at one level and
keeps indices and weights in registers, so the only memory traffic is the points, the
table rows read and the features written. Forward only, without autograd: training keeps
`forward_grouped`, whose gradients PyTorch derives.

The k nearest vertices: `meshes.nearest_vertices_brute` computes every point's distance to
every vertex and selects with `topk`; on an H200 that selection was 37 % of a mesh-guided
256 px frame's GPU time. Here each point keeps its k best in registers while it walks its
mesh's vertices (V ~ 500-800, k <= 8), in tiles of vertices that a block of points skips
where none of them is nearer than a point's k-th best so far.

Triton comes with PyTorch's CUDA builds; without it (or with `FLAMENERF_GPU_KERNELS=0`)
the callers fall back to PyTorch ops (`FLAMENERF_GPU_KERNELS=knn,hashgrid` keeps only the
kernels named, `=1` turns on every one, UNPROVEN too; benchmarks/gpu_kernel_check.py finds
a kernel that fails on a GPU that way), and so do a kernel's callers where that kernel
fails to build (it alone goes off). `TRITON_INTERPRET=1` runs the kernels on a CPU
(how the tests check them against the references).
"""

from __future__ import annotations

import contextlib
import inspect
import os
import warnings

import torch
from torch import Tensor

from flamenerf.errors import UserError

_kernels: dict | None = None
_tried = False
_recorded: list | None = None  # `recording()`'s launches


NAMES = ("hashgrid", "knn", "field_heads")
"""The kernels, by name (what FLAMENERF_GPU_KERNELS lists)."""

UNPROVEN: frozenset[str] = frozenset()
"""Kernels left off unless asked for (`FLAMENERF_GPU_KERNELS=1` or by name) until they have
rendered right on a GPU (benchmarks/gpu_kernel_check.py). None now: `field_heads` with
widths of 16 ended an H200's frame with an illegal memory access; padded to DOT_MIN it
rendered right there (2026-11-28, Triton 3.6: within 1.3e-4 of the kernels-off frame,
512 px at 33.2 fps against 30.1 without it; docs/bench/gpu_h200_20261128b.json)."""


def chosen() -> frozenset[str]:
    """The kernels FLAMENERF_GPU_KERNELS asks for: unset or empty, all but UNPROVEN; `0`,
    none; `1`, all; else the names listed (comma-separated). A name that is no kernel is a
    UserError (the CLI checks it before any work)."""
    value = os.environ.get("FLAMENERF_GPU_KERNELS", "").strip()
    if value in ("", "0", "1"):
        return {"": frozenset(NAMES) - UNPROVEN, "0": frozenset(),
                "1": frozenset(NAMES)}[value]
    names = {n.strip() for n in value.split(",") if n.strip()}
    if names - set(NAMES):
        raise UserError(f"FLAMENERF_GPU_KERNELS={value}: no kernel "
                        f"{', '.join(sorted(names - set(NAMES)))} (there are "
                        f"{', '.join(NAMES)}; or 0 for none, 1 for all)")
    return frozenset(names)


def available(device: torch.device) -> bool:
    """Whether the kernels can run on tensors of `device`."""
    if not chosen():
        return False
    interpret = os.environ.get("TRITON_INTERPRET") == "1"
    if device.type != "cuda" and not (interpret and device.type == "cpu"):
        return False
    return _load() is not None


def working() -> list[str]:
    """The kernels chosen and built or not yet tried, by name (one that failed is off:
    `_launch`)."""
    kernels = _load() if chosen() else None
    return sorted(kernels) if kernels is not None else []


def _load() -> dict | None:
    global _kernels, _tried
    if not _tried:
        keep = chosen()  # a wrong name raises before anything is kept
        _tried = True
        try:
            kernels = _define()
        except ImportError:
            kernels = None
        _kernels = None if kernels is None else {n: k for n, k in kernels.items() if n in keep}
    return _kernels


def first_line(e: BaseException) -> str:
    """An error's first line (its type where it says nothing): for one-line messages."""
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def fault_advice(again: str = "run again") -> str:
    """What to do after a GPU fault, for a one-line message: `again` ('run again', 'restart
    the viewer') without the Triton kernels, unless they were off already."""
    if not chosen():
        return ("the Triton kernels were off, so PyTorch or the driver faulted "
                "(FLAMENERF_DEBUG=1 shows the traceback)")
    return (f"{again} with FLAMENERF_GPU_KERNELS=0 (PyTorch's ops only) and please report "
            "it (FLAMENERF_DEBUG=1 shows the traceback)")


FP_FUSION = True
"""Multiplies and adds fused (FMA), as the kernels were tested: named at each launch, as
Triton 3.9 warns where it is left to its default, which 3.10 turns off."""


def _launch(name: str, grid: tuple, *args, **meta) -> bool:
    """Run kernel `name`; False (with one warning, and that kernel off from then on) where
    Triton cannot build it for this GPU or driver: its callers then take PyTorch ops, and
    the other kernels go on."""
    kernels = _load()
    if kernels is None or name not in kernels:
        return False
    if _recorded is not None:
        _recorded.append(launch_signature(name, kernels[name], args, meta))
    try:
        kernels[name][grid](*args, enable_fp_fusion=FP_FUSION, **meta)
        return True
    except Exception as e:  # noqa: BLE001 - any build or launch failure means: do without
        if gpu_faulted(e):  # the CUDA context is gone: PyTorch's ops would fail too
            raise GPUFault(f"a GPU fault was reported at the launch of the Triton kernel "
                           f"{name} ({first_line(e)}; CUDA reports faults late: "
                           "CUDA_LAUNCH_BLOCKING=1 names the kernel that made it)") from e
        del kernels[name]
        warnings.warn(f"flamenerf: the Triton kernel {name} failed ({type(e).__name__}: "
                      f"{str(e)[:200]}); using PyTorch ops instead", stacklevel=3)
        return False


class GPUFault(RuntimeError):
    """A kernel ended its CUDA context (an access out of bounds, say): nothing on that GPU
    runs in this process after it."""


def gpu_faulted(e: BaseException) -> bool:
    """Whether `e` says the CUDA context is lost (errors CUDA reports once and then for
    every call: an illegal address or instruction, a failed assertion, a misaligned
    access), rather than a kernel that could not be built or launched."""
    text = str(e).lower()
    return any(k in text for k in ("illegal memory access", "illegal address",
                                   "illegal instruction", "misaligned address",
                                   "device-side assert", "unspecified launch failure"))


@contextlib.contextmanager
def recording():
    """Yields a list that collects each kernel launch's signature while the block runs
    (`launch_signature`): what `gpu_build.build` compiles for a GPU, offline."""
    global _recorded
    kept, _recorded = _recorded, []
    try:
        yield _recorded
    finally:
        _recorded = kept


_DTYPES = {torch.float32: "fp32", torch.float16: "fp16", torch.bfloat16: "bf16",
           torch.int64: "i64", torch.int32: "i32", torch.int16: "i16", torch.int8: "i8",
           torch.uint8: "u8", torch.bool: "i1"}


def launch_signature(name: str, kernel, args: tuple, meta: dict) -> dict:
    """A launch as Triton's compiler takes it: {"kernel", "signature" (argument -> type,
    "*fp16" for a pointer), "constexprs", "divisible" (arguments Triton's launcher would
    specialise as multiples of 16: aligned pointers, integers), "num_warps"}. An integer
    argument equal to 1 is a constant, as Triton's launcher specialises it."""
    params = inspect.signature(kernel.fn).parameters  # the same under the interpreter
    names = list(params)
    sig, const, div = {}, {k: v for k, v in meta.items() if k in names}, []
    for arg, a in zip(names, args):
        if "constexpr" in str(params[arg].annotation):  # a constant passed by position
            const[arg] = a
        elif isinstance(a, Tensor):
            if a.dtype not in _DTYPES:
                raise TypeError(f"{name}: argument {arg} of dtype {a.dtype}")
            sig[arg] = "*" + _DTYPES[a.dtype]
            if a.data_ptr() % 16 == 0:
                div.append(arg)
        elif isinstance(a, bool):
            sig[arg] = "i1"
        elif isinstance(a, int):
            if a == 1:
                const[arg] = 1
                continue
            sig[arg] = ("i32" if -2**31 <= a < 2**31 else "i64" if -2**63 <= a < 2**63
                        else "u64")
            if a % 16 == 0:
                div.append(arg)
        elif isinstance(a, float):
            sig[arg] = "fp32"
        else:
            raise TypeError(f"{name}: argument {arg} of type {type(a).__name__}")
    return {"kernel": name, "signature": sig, "constexprs": const, "divisible": div,
            "num_warps": meta.get("num_warps", 4)}


def _define() -> dict:
    import triton
    import triton.language as tl

    @triton.jit
    def hashgrid_fwd(x_ptr, table_ptr, res_ptr, dense_ptr, offset_ptr, out_ptr, n,
                     out_stride, hash_mask, col0, z_ptr,
                     F: tl.constexpr, FP: tl.constexpr, BLOCK: tl.constexpr,
                     RANK: tl.constexpr, FE: tl.constexpr):
        lv = tl.program_id(1)
        # int64 rows: a 512 px frame's second pass can hold up to 262144 x 128 points,
        # whose offsets into a features buffer of 48 columns reach 1.6e9 (2^31 at 64)
        rows = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        ok = rows < n
        r = tl.load(res_ptr + lv)  # int64
        dense = tl.load(dense_ptr + lv) != 0
        offset = tl.load(offset_ptr + lv)  # int64: first row of this level's table
        rf = r.to(tl.float32)
        feats = tl.arange(0, FP)
        fok = feats < F
        acc = tl.zeros((BLOCK, FP), dtype=tl.float32)
        # per axis: the cell's lower corner (as forward_grouped: x·r in float32, its floor
        # kept inside the grid so that x = 1 lies on the top face) and the fraction
        px = tl.minimum(tl.maximum(tl.load(x_ptr + rows * 3, mask=ok, other=0.0), 0.0), 1.0) * rf
        py = tl.minimum(tl.maximum(tl.load(x_ptr + rows * 3 + 1, mask=ok, other=0.0), 0.0),
                        1.0) * rf
        pz = tl.minimum(tl.maximum(tl.load(x_ptr + rows * 3 + 2, mask=ok, other=0.0), 0.0),
                        1.0) * rf
        bx = tl.minimum(tl.floor(px), rf - 1.0)
        by = tl.minimum(tl.floor(py), rf - 1.0)
        bz = tl.minimum(tl.floor(pz), rf - 1.0)
        fx, fy, fz = px - bx, py - by, pz - bz
        ix, iy, iz = bx.to(tl.int64), by.to(tl.int64), bz.to(tl.int64)
        stride = r + 1
        for c in tl.static_range(8):
            dx, dy, dz = (c >> 2) & 1, (c >> 1) & 1, c & 1
            cx, cy, cz = ix + dx, iy + dy, iz + dz
            # hashed: the low bits of the products, which int64 holds exactly
            hashed = (cx ^ (cy * 2654435761) ^ (cz * 805459861)) & hash_mask
            flat = cx + cy * stride + cz * stride * stride
            idx = tl.where(dense, flat, hashed) + offset
            w = ((fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy)
                 * (fz if dz else 1.0 - fz))
            f = tl.load(table_ptr + idx[:, None] * F + feats[None, :],
                        mask=ok[:, None] & fok[None, :], other=0.0)
            acc += f.to(tl.float32) * w[:, None]
        if RANK == 0:
            dst = out_ptr + rows[:, None] * out_stride + col0 + lv * F + feats[None, :]
            tl.store(dst, acc.to(out_ptr.dtype.element_ty), mask=ok[:, None] & fok[None, :])
        else:
            # a level's F = RANK·FE features as (RANK, FE), contracted with the point's
            # z (RANK,): out[lv·FE + e] = Σ_r z_r acc[r·FE + e]
            z = tl.load(z_ptr + rows[:, None] * RANK + feats[None, :] // FE,
                        mask=ok[:, None] & fok[None, :], other=0.0).to(tl.float32)
            acc = acc * z
            for e in tl.static_range(FE):
                col = tl.sum(tl.where((feats % FE == e)[None, :], acc, 0.0), 1)
                tl.store(out_ptr + rows * out_stride + col0 + lv * FE + e,
                         col.to(out_ptr.dtype.element_ty), mask=ok)

    @triton.jit
    def knn(p_ptr, v_ptr, which_ptr, d_ptr, i_ptr, n, V: tl.constexpr,
            K: tl.constexpr, KP: tl.constexpr, BLOCK: tl.constexpr, TILE: tl.constexpr,
            CHECK: tl.constexpr):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = rows < n
        px = tl.load(p_ptr + rows * 3, mask=ok, other=0.0)
        py = tl.load(p_ptr + rows * 3 + 1, mask=ok, other=0.0)
        pz = tl.load(p_ptr + rows * 3 + 2, mask=ok, other=0.0)
        # 32-bit vertex offsets (the caller checks that they fit): 64-bit ones cost a
        # third more registers
        base = tl.load(which_ptr + rows, mask=ok, other=0).to(tl.int32) * V
        cols = tl.arange(0, KP)
        # the k best so far, unsorted; padding columns at -inf are never the worst
        best = tl.where(cols[None, :] < K, float("inf"), float("-inf")) + tl.zeros(
            (BLOCK, KP), dtype=tl.float32)
        besti = tl.zeros((BLOCK, KP), dtype=tl.int32)
        # the vertices in tiles of TILE; with CHECK a tile's distances in one vectorised
        # step, and its vertices inserted in turn only where some point of the block has
        # one of them nearer than its k-th best so far (a tile skipped would have inserted
        # nothing: the same answer). Each thread holds its rows' TILE distances: 16 took
        # ~160 registers a thread on sm_90 (255 and spills with the insertions unrolled
        # from them), 8 with 8 warps ~60 (gpu_build.py)
        for j0 in range(0, V, TILE):
            if CHECK:
                jj = j0 + tl.arange(0, TILE)
                live = ok[:, None] & (jj < V)[None, :]
                v = (base[:, None] + jj[None, :]) * 3
                dx = px[:, None] - tl.load(v_ptr + v, mask=live, other=0.0)
                dy = py[:, None] - tl.load(v_ptr + v + 1, mask=live, other=0.0)
                dz = pz[:, None] - tl.load(v_ptr + v + 2, mask=live, other=0.0)
                d = tl.where(live, dx * dx + dy * dy + dz * dz, float("inf"))
                need = tl.sum((tl.min(d, 1) < tl.max(best, 1)).to(tl.int32), 0)
            else:
                need = 1
            if need > 0:
                for j in range(j0, tl.minimum(j0 + TILE, V)):
                    w = (base + j) * 3
                    ex = px - tl.load(v_ptr + w, mask=ok, other=0.0)
                    ey = py - tl.load(v_ptr + w + 1, mask=ok, other=0.0)
                    ez = pz - tl.load(v_ptr + w + 2, mask=ok, other=0.0)
                    dj = ex * ex + ey * ey + ez * ez
                    worst = tl.max(best, 1)
                    # the first column holding the worst: replaced where this vertex is
                    # nearer
                    at = tl.min(tl.where(best == worst[:, None], cols[None, :], KP), 1)
                    put = (cols[None, :] == at[:, None]) & (dj < worst)[:, None]
                    best = tl.where(put, dj[:, None], best)
                    besti = tl.where(put, base[:, None] + j, besti)
        keep = ok[:, None] & (cols[None, :] < K)
        tl.store(d_ptr + rows[:, None] * K + cols[None, :], best, mask=keep)
        tl.store(i_ptr + rows[:, None] * K + cols[None, :], besti.to(tl.int64), mask=keep)

    @triton.jit
    def field_heads(f_ptr, f_stride, term_ptr, per, n,
                    w1_ptr, b1_ptr, w2_ptr, b2_ptr, wc1_ptr, wc2_ptr, bc2_ptr, wc3_ptr,
                    bc3_ptr, sigma_ptr, rgb_ptr,
                    CIN: tl.constexpr, CP: tl.constexpr, H: tl.constexpr, TH: tl.constexpr,
                    G: tl.constexpr, OUT: tl.constexpr, BLOCK: tl.constexpr,
                    PREC: tl.constexpr):
        # int64 offsets: a refinement pass can hold tens of millions of samples
        rows = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        ok = rows < n
        kin, hc, gc, oc = tl.arange(0, CP), tl.arange(0, H), tl.arange(0, G), tl.arange(0, OUT)
        dt = w1_ptr.dtype.element_ty
        f = tl.load(f_ptr + rows[:, None] * f_stride + kin[None, :],
                    mask=ok[:, None] & (kin < CIN)[None, :], other=0.0).to(dt)
        # the density head: features -> H (ReLU) -> G = σ's logit and the geometry features
        w1 = tl.load(w1_ptr + kin[:, None] * H + hc[None, :])
        h = tl.dot(f, w1, input_precision=PREC) + tl.load(b1_ptr + hc)[None, :]
        h = tl.maximum(h, 0.0).to(dt)
        w2 = tl.load(w2_ptr + hc[:, None] * G + gc[None, :])
        g = tl.dot(h, w2, input_precision=PREC) + tl.load(b2_ptr + gc)[None, :]
        logit = tl.sum(tl.where((gc == 0)[None, :], g, 0.0), 1)
        tl.store(sigma_ptr + rows, tl.exp(tl.minimum(logit, 15.0)), mask=ok)  # trunc_exp
        # the colour head: geometry features (wc1's row 0, σ's, is zero) plus the ray's
        # conditioning term -> H -> H -> RGB
        wc1 = tl.load(wc1_ptr + gc[:, None] * H + hc[None, :])
        # the hidden width H padded from TH: the padding's units stay 0 (zero weights)
        term = tl.load(term_ptr + (rows // per)[:, None] * TH + hc[None, :],
                       mask=ok[:, None] & (hc < TH)[None, :], other=0.0).to(tl.float32)
        c = tl.maximum(tl.dot(g.to(dt), wc1, input_precision=PREC) + term, 0.0).to(dt)
        wc2 = tl.load(wc2_ptr + hc[:, None] * H + hc[None, :])
        c = tl.dot(c, wc2, input_precision=PREC) + tl.load(bc2_ptr + hc)[None, :]
        c = tl.maximum(c, 0.0).to(dt)
        wc3 = tl.load(wc3_ptr + hc[:, None] * OUT + oc[None, :])
        o = tl.dot(c, wc3, input_precision=PREC) + tl.load(bc3_ptr + oc)[None, :]
        rgb = 1.0 / (1.0 + tl.exp(-o))
        tl.store(rgb_ptr + rows[:, None] * 3 + oc[None, :], rgb,
                 mask=ok[:, None] & (oc < 3)[None, :])

    return {"hashgrid": hashgrid_fwd, "knn": knn, "field_heads": field_heads}


KNN_TILE, KNN_WARPS = 8, 4
"""The nearest-vertex kernel's tile of vertices (0: none, every vertex inserted in turn)
and warps a block: timed on an H200 on a 512 px frame's calls (benchmarks/gpu_choices.py,
2026-11-28): on its 1.03M points tile 8 with 4 warps 2.69 ms, 8 warps 3.09, no tile 4.6-4.8,
tile 16 3.1-3.5; on the second pass's 20k points every choice 0.23-0.37 ms."""

HEADS_BLOCK, HEADS_WARPS = 64, 4
"""The field heads' points a block and warps a block: timed on an H200 on a 512 px frame's
calls (benchmarks/gpu_choices.py, 2026-11-28): on its 8.4M points 2.10 ms, against 2.34 ms
for 128 points a block and 3.2-4.4 ms with 8 warps; on 67k points all within 0.09-0.10 ms."""


def knn(pts: Tensor, meshes: Tensor, which: Tensor, k: int, tile: int | None = None,
        warps: int | None = None) -> tuple[Tensor, Tensor] | None:
    """The k nearest vertices of each point's own mesh, nearest first: pts (P, 3), meshes
    (M, V, 3), which (P,) long -> squared distances (P, k) float32 and indices (P, k) long
    into the M·V stacked vertices (k <= V); None where the kernel failed (`_launch`) or
    its 32-bit vertex offsets would not hold M·V·3. Distances are summed as (x - v)² per
    axis, not through `cdist`'s |x|² + |v|² - 2x·v. `tile` (0 or a power of two),
    `warps`: KNN_TILE and KNN_WARPS unless given."""
    P, (M, V) = len(pts), meshes.shape[:2]
    tile = KNN_TILE if tile is None else tile
    warps = KNN_WARPS if warps is None else warps
    if tile & (tile - 1):
        raise ValueError(f"knn: tile {tile} is not 0 or a power of two")
    if M * V * 3 >= 2**31:  # the kernel's vertex offsets are 32-bit
        return None
    d2 = torch.empty(P, k, dtype=torch.float32, device=pts.device)
    idx = torch.empty(P, k, dtype=torch.long, device=pts.device)
    if P and not _launch("knn", (triton_cdiv(P, 128),), pts.detach().float().contiguous(),
                         meshes.detach().float().contiguous(), which.contiguous(), d2, idx,
                         P, V, K=k, KP=max(2, 1 << (k - 1).bit_length()), BLOCK=128,
                         TILE=max(tile, 1), CHECK=tile > 0, num_warps=warps):
        return None
    d2, order = torch.sort(d2, -1)
    return d2, idx.gather(-1, order)


def hashgrid_forward(grid, x: Tensor, out: Tensor | None = None, col0: int = 0
                     ) -> Tensor | None:
    """HashGrid `grid`'s encoding of x (N, 3) in [0, 1]^3 without autograd -> (N, L·F)
    float32; or written into columns col0.. of `out` (N, C) (unit column stride); None
    where the kernel failed (`_launch`)."""
    n, L, F = x.shape[0], grid.levels, grid.features
    if out is None:
        out = torch.empty(n, L * F, dtype=torch.float32, device=x.device)
        col0 = 0
    if n == 0:
        return out
    if not _hashgrid(grid, x, out, col0, None, 0):
        return None
    return out


def hashgrid_contract(grid, x: Tensor, z: Tensor, features: int) -> Tensor | None:
    """Σ_r z_r G_r(x) at each level of `grid`, whose F = rank·features features per level
    are read as (rank, features) (the expression feature fields, model/field.py):
    x (N, 3) in [0, 1]^3, z (N, rank) -> (N, L·features) float32; None where the kernel
    failed. The grid's (N, L·F) features are never written: for the expression fields that
    is 8x the contracted output, and the small batched product over them was ~5 % of an
    H100's 512 px frame (aten::bmm in docs/bench/gpu_h100_20261126_prof512.txt)."""
    n, L = x.shape[0], grid.levels
    rank = grid.features // features
    assert rank * features == grid.features and z.shape == (n, rank), (z.shape, grid.features)
    out = torch.empty(n, L * features, dtype=torch.float32, device=x.device)
    if n and not _hashgrid(grid, x, out, 0, z.contiguous(), features):
        return None
    return out


def _hashgrid(grid, x: Tensor, out: Tensor, col0: int, z: Tensor | None, fe: int) -> bool:
    table, res, dense, offsets = _flat_layout(grid)
    F = grid.features
    block = 128 if F <= 4 else 32
    fp = 1 << (F - 1).bit_length()
    rank = F // fe if z is not None else 0
    return _launch("hashgrid", (triton_cdiv(x.shape[0], block), grid.levels),
                   x.detach().float().contiguous(), table, res, dense, offsets, out,
                   x.shape[0], out.stride(0), grid.size - 1, col0,
                   out if z is None else z,  # z_ptr: unused without a contraction
                   F=F, FP=fp, BLOCK=block, RANK=rank, FE=max(fe, 1))


def field_heads(feats: Tensor, term: Tensor, per: int, density_head, rgb_head,
                block: int | None = None, warps: int | None = None
                ) -> tuple[Tensor, Tensor] | None:
    """A hash field's density and colour heads (model/field.HashField, one hidden layer
    and two) in one kernel: each block of points goes from its features to σ and RGB in
    registers, so that none of the heads' activations (64 numbers a point, written and
    read again between the layers and their bias, ReLU and casts) touch the GPU's memory;
    those passes and the small matmuls were most of an H100's 512 px frame
    (docs/bench/gpu_h100_20261126_prof512.txt).

    feats (N, C) the density head's input (unit column stride; half precision on the
    GPU's inference path, float32 elsewhere: the layers run in its dtype, float32 exactly);
    term (M, H) the colour head's first layer applied to the per-ray conditioning (γ(d),
    φ), bias included, point i taking row i // per -> σ (N,) (trunc_exp of the logit) and
    RGB (N, 3), float32; None where the heads are not of that shape or the kernel failed.
    `block` (a power of two, at least DOT_MIN), `warps`: HEADS_BLOCK and
    HEADS_WARPS unless given.
    """
    block = HEADS_BLOCK if block is None else block
    warps = HEADS_WARPS if warps is None else warps
    if block & (block - 1) or block < DOT_MIN:
        raise ValueError(f"field_heads: block {block} is not a power of two >= {DOT_MIN}")
    if len(density_head.layers) != 1 or len(rgb_head.layers) != 2 or density_head.skips \
            or rgb_head.skips or density_head.out is None or rgb_head.out is None:
        return None
    N, C = feats.shape
    H = density_head.layers[0].out_features
    geo = density_head.out.out_features - 1
    if (not 0 < H <= 128 or C > 128 or not 0 < geo < 64
            or C != density_head.layers[0].in_features or rgb_head.out.out_features != 3
            or rgb_head.layers[0].out_features != H or rgb_head.layers[1].out_features != H
            or feats.stride(-1) != 1 or term.shape[-1] != H):
        return None
    w = _head_weights(density_head, rgb_head, geo, feats.dtype)
    sigma = torch.empty(N, dtype=torch.float32, device=feats.device)
    rgb = torch.empty(N, 3, dtype=torch.float32, device=feats.device)
    if N == 0:
        return sigma, rgb
    cp, hp, g = w[0].shape[0], w[0].shape[1], w[2].shape[1]
    if not _launch("field_heads", (triton_cdiv(N, block),), feats, feats.stride(0),
                   term.contiguous(), per, N, *w, sigma, rgb, CIN=C, CP=cp, H=hp, TH=H, G=g,
                   OUT=DOT_MIN, BLOCK=block, num_warps=warps,
                   # float32 exactly (tf32 is ignored for half-precision operands)
                   PREC="ieee" if feats.dtype == torch.float32 else "tf32"):
        return None
    return sigma, rgb


def _head_weights(density_head, rgb_head, geo: int, dtype: torch.dtype) -> tuple:
    """`field_heads`' weights: transposed, zero-padded to powers of two (at least DOT_MIN),
    in `dtype` (biases float32); cached on the density head until a
    parameter changes (an optimiser step bumps its version) or moves."""
    params = [*density_head.parameters(), *rgb_head.parameters()]
    key = (dtype, DOT_MIN, tuple((p._version, p.data_ptr()) for p in params))
    kept = getattr(density_head, "_flamenerf_field_heads", None)
    if kept is not None and kept[0] == key:
        return kept[1]
    l1, l2 = density_head.layers[0], density_head.out
    c1, c2, c3 = rgb_head.layers[0], rgb_head.layers[1], rgb_head.out
    H, C = l1.out_features, l1.in_features
    cp, hp, g = _pow2(C), _pow2(H), _pow2(geo + 1)

    def padded(m: Tensor, rows: int, cols: int, at: int = 0) -> Tensor:
        out = m.new_zeros(rows, cols)
        out[at:at + m.shape[0], :m.shape[1]] = m
        return out.to(dtype).contiguous()

    def vec(b: Tensor, size: int) -> Tensor:
        out = b.new_zeros(size)
        out[:len(b)] = b
        return out.float().contiguous()

    with torch.no_grad():
        w = (padded(l1.weight.t(), cp, hp), vec(l1.bias, hp),
             padded(l2.weight.t(), hp, g), vec(l2.bias, g),
             # the geometry features are columns 1.. of the density head's output
             padded(c1.weight[:, :geo].t(), g, hp, at=1),
             padded(c2.weight.t(), hp, hp), vec(c2.bias, hp),
             padded(c3.weight.t(), hp, DOT_MIN), vec(c3.bias, DOT_MIN))
    density_head._flamenerf_field_heads = (key, w)
    return w


DOT_MIN = 64
"""The least size of any dimension of `field_heads`' matrix products (its block of points,
the padded features, hidden, geometry and output widths). `tl.dot` takes 16, but a kernel
of several dots with dimensions of 16 or 32 reads shared memory out of bounds on sm_90
(triton-lang/triton#10486 and #11366; pytorch/helion#1905 found 8 and 64 and up safe on an
H100): this kernel, with geometry and output widths of 16, ended an H200's first frame
with an illegal memory access (2026-11-28, Triton 3.6). Not yet run on a GPU padded so."""


def _pow2(n: int) -> int:
    return max(DOT_MIN, 1 << (n - 1).bit_length())


def triton_cdiv(a: int, b: int) -> int:
    return (a + b - 1) // b


def _flat_layout(grid):
    """The grid's tables as one (ΣT_l, F) tensor and its per-level resolution, dense flag
    and first row. The tables are joined at every call: a cache keyed on their versions
    would miss writes through `.data`, and the copy costs ~30 µs of a GPU's time. The
    first rows depend on the tables' sizes alone and are kept (copying them to the device
    made every call wait for it), with the levels' resolutions and dense flags, fixed when
    the grid is made."""
    tables = [t.detach() for t in grid.tables]
    dev = tables[0].device
    key = (dev, tuple(len(t) for t in tables))
    kept = getattr(grid, "_flat_layout_rows", None)
    if kept is None or kept[0] != key:
        offsets = torch.tensor([0, *key[1][:-1]], dtype=torch.int64).cumsum(0).to(dev)
        kept = (key, grid.res.to(dev, torch.int64).contiguous(),
                grid.dense.to(dev, torch.int8).contiguous(), offsets)
        grid._flat_layout_rows = kept
    return (torch.cat(tables).contiguous(), *kept[1:])
