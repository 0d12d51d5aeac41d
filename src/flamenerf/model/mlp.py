"""A plain ReLU MLP with NeRF-style skip connections (the input is re-concatenated).

Conditioning that is the same for every sample of a ray (a frame code, an expression, a
view direction) can be passed as `cond` with a broadcastable shape, e.g. (R, 1, C) next to
samples (R, S, D). The network is the same as one fed the concatenation [x, cond] (the
weights are one Linear over both), but the conditioning's share of the first layer is
computed once per ray instead of once per sample, and no (R·S, C) copy is ever made.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flamenerf import runtime

_fusing = threading.local()


@contextlib.contextmanager
def fused_cpu_inference(bf16: bool = False) -> Iterator[None]:
    """Within this block (in this thread), MLPs on float32 CPU tensors without autograd run
    each layer as one oneDNN matmul with its bias and ReLU fused in: 2x faster than
    matmul, bias add and ReLU as separate passes (a `fast` density head, 65k samples, one
    thread: 5.5 ms vs 11.1 ms). Rounding differs from the plain path in the last bits, so
    the training forward (and eval's PSNR figures, rendered with it) never uses it.

    `bf16`: on a CPU with native bfloat16 arithmetic (AVX-512 BF16 or AMX) where it is
    measured to pay (`bf16_pays`), the layers run in bfloat16 between a float32 input and a
    float32 output; elsewhere it is ignored."""
    old = getattr(_fusing, "on", False), getattr(_fusing, "bf16", False)
    _fusing.on = _oneDNN_linear() is not None
    _fusing.bf16 = _fusing.on and bf16 and bf16_pays()
    try:
        yield
    finally:
        _fusing.on, _fusing.bf16 = old


@contextlib.contextmanager
def bf16_training(on: bool = True) -> Iterator[None]:
    """Within this block (in this thread), MLPs on float32 CPU tensors *with* autograd run
    their layers in bfloat16 (float32 weights cast per call, so the optimiser keeps float32
    masters; each MLP's output is float32 again). Not measured here: a run decides once,
    when it starts, whether it trains so (`train.bf16`, settled by `bf16_pays`), so that
    its numbers do not change with the machine's load from one step or resume to the next."""
    old = getattr(_fusing, "train_bf16", False)
    _fusing.train_bf16 = on
    try:
        yield
    finally:
        _fusing.train_bf16 = old


def native_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 natively (else oneDNN emulates it, slowly)."""
    cpu = getattr(torch, "cpu", None)
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(cpu, c, lambda: False)()) for c in checks)


_bf16_lock = threading.Lock()
_bf16_verdict: bool | None = None
BF16_MIN_GAIN = 1.3
"""bfloat16 layers are used only where they are at least this much faster than float32:
a decision near the line would flip between processes with the machine's load."""


def bf16_pays() -> bool:
    """Whether bfloat16 layers beat float32 ones here: native support, then a one-off
    measurement per process (30-40 ms) of a `fast` head layer both ways. The flags alone do
    not tell: on a Zen 4 CPU bfloat16 was 2.3x faster per 64-wide layer, on an Intel Xeon
    with the same AVX-512 BF16 flag 2x slower (a 256 px `fast` frame 1.19 s in bfloat16,
    1.04 s in float32, medians of 5 alternating frames: README, "Rendering speed")."""
    global _bf16_verdict
    with _bf16_lock:
        if _bf16_verdict is None:
            _bf16_verdict = native_bf16() and _oneDNN_linear() is not None and \
                _measured_gain() >= BF16_MIN_GAIN
        return _bf16_verdict


def _measured_gain() -> float:
    """float32 time / bfloat16 time of one fused 48 -> 64 ReLU layer on 32768 rows, each
    as `_fused_linear` runs it (bfloat16: the input converted first), best of 5."""
    import time

    op = torch.ops.mkldnn._linear_pointwise
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(32768, 48, generator=gen)
    w, b = torch.randn(64, 48, generator=gen), torch.randn(64, generator=gen)
    wb, bb = w.bfloat16(), b.bfloat16()

    def best(f) -> float:
        f()
        times = []
        for _ in range(5):
            t = time.perf_counter()
            f()
            times.append(time.perf_counter() - t)
        return min(times)

    with torch.no_grad():
        t32 = best(lambda: op(x, w, b, "relu", [], ""))
        t16 = best(lambda: op(x.to(torch.bfloat16), wb, bb, "relu", [], ""))
    return t32 / max(t16, 1e-9)


def _oneDNN_linear():
    """torch's oneDNN linear with fused post-ops (what inductor emits), when this build has
    it; it is a private op, so anything unexpected falls back to the plain path."""
    op = getattr(torch.ops.mkldnn, "_linear_pointwise", None) if torch.backends.mkldnn.is_available() else None
    return op


def _linear_of_parts(layer: nn.Linear, parts: list[Tensor], relu: bool, dtype: torch.dtype,
                     dense) -> Tensor:
    """relu?(layer(cat(parts, -1))) without autograd, as `linear_of_concat` broadcasts the
    parts, in as few passes over the activations as the kernel `dense` allows. Parts with
    one row per sample (parts[0]'s leading shape) go through dense(x (n, k), w (out, k),
    bias or None, relu) -> (n, out) in `dtype` (the weights cast once and kept:
    `params_in`); a layer over those alone gets its bias and ReLU inside that kernel.
    Later parts with fewer rows (per ray, broadcastable) are multiplied in the layer's own
    precision and summed with the bias into one small term, added in place; then ReLU in
    place. Without it each of those terms, the bias and the ReLU would be a pass of its own
    over every sample's activation."""
    weight, bias = params_in(layer, dtype)
    lead = parts[0].shape[:-1]
    rows = parts[0].numel() // parts[0].shape[-1]
    if len(parts) == 1:
        k = parts[0].shape[-1]
        return dense(parts[0].to(dtype).reshape(rows, k), weight, bias, relu).view(*lead, -1)
    out, small, start = None, None, 0
    for p in parts:
        k = p.shape[-1]
        cols = slice(start, start + k)
        start += k
        if p.shape[:-1] == lead:
            y = dense(p.to(dtype).reshape(rows, k), weight[:, cols], None, False).view(*lead, -1)
            out = y if out is None else out.add_(y)
        else:  # shapes may broadcast either way: summed out of place
            y = F.linear(p.to(layer.weight.dtype), layer.weight[:, cols])
            small = y if small is None else small + y
    assert start == layer.in_features, (start, layer.in_features)
    if layer.bias is not None:
        small = layer.bias if small is None else small + layer.bias
    if small is not None:
        small = small.to(out.dtype)
        if relu and out.device.type == "cpu" and out.dtype == torch.float32:
            return torch.ops.aten._add_relu_(out, small)  # one pass; float32 CPUs only
        out.add_(small)
    return out.relu_() if relu else out


def _dense_onednn(x: Tensor, w: Tensor, b: Tensor | None, relu: bool) -> Tensor:
    """x @ w.T (+ b, ReLU) as one oneDNN matmul with its post-ops (CPUs)."""
    return torch.ops.mkldnn._linear_pointwise(x, w.contiguous(), b, "relu" if relu else "none",
                                              [], "")


def _dense_blas(x: Tensor, w: Tensor, b: Tensor | None, relu: bool) -> Tensor:
    """x @ w.T (+ b, ReLU) as one BLAS call; bias and ReLU in cuBLASLt's epilogue on a GPU
    (`_addmm_activation`)."""
    if b is None:
        y = x @ w.t()
        return y.relu_() if relu else y
    return (torch._addmm_activation if relu else torch.addmm)(b, x, w.t())


def params_in(layer: nn.Linear, dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
    """The layer's weight and bias in `dtype`, cached until the parameters change (an
    optimiser step bumps their version) or move."""
    if layer.weight.dtype == dtype:
        return layer.weight, layer.bias
    key = (dtype, layer.weight._version, layer.weight.data_ptr(),
           None if layer.bias is None else layer.bias._version)
    cached = getattr(layer, "_flamenerf_cast", None)
    if cached is None or cached[0] != key:
        cached = (key, layer.weight.detach().to(dtype),
                  None if layer.bias is None else layer.bias.detach().to(dtype))
        layer._flamenerf_cast = cached
    return cached[1], cached[2]


def linear_of_concat(layer: nn.Linear, parts: list[Tensor],
                     dtype: torch.dtype | None = None) -> Tensor:
    """layer(cat(parts, -1)) for parts whose leading dims broadcast against each other.
    `dtype`: the float32 weights cast to it on each call, autograd through the cast (the
    bfloat16 training layers); the bias then rides in parts[0]'s product (one row per
    sample), which saves a pass over the output."""
    weight, bias = layer.weight, layer.bias
    if dtype is not None:
        weight, bias = weight.to(dtype), bias.to(dtype)
    out, start = None, 0
    for p in parts:
        w = weight[:, start:start + p.shape[-1]]
        start += p.shape[-1]
        y = F.linear(p, w, bias if dtype is not None and out is None else None)
        out = y if out is None else out + y
    assert start == layer.in_features, (start, layer.in_features)
    return out if dtype is not None else out + bias


class MLP(nn.Module):
    def __init__(self, in_dim: int, width: int, depth: int, skips: tuple[int, ...] = (),
                 out_dim: int | None = None):
        super().__init__()
        self.skips = set(skips)
        layers, d = [], in_dim
        for i in range(depth):
            if i in self.skips:
                d += in_dim
            layers.append(nn.Linear(d, width))
            d = width
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(d, out_dim) if out_dim is not None else None
        self.out_dim = out_dim if out_dim is not None else width

    def forward(self, x: Tensor, cond: Tensor | None = None) -> Tensor:
        """x (*bs, in_dim - C), cond (*bs', C) broadcastable to x's leading dims, or None
        (then x holds the whole input) -> (*bs, out_dim)."""
        inputs = [x] if cond is None else [x, cond]
        if getattr(_fusing, "on", False) and x.device.type == "cpu" and x.dtype == torch.float32 \
                and not torch.is_grad_enabled():
            return self._forward_fused(inputs)
        if getattr(_fusing, "train_bf16", False) and x.device.type == "cpu" \
                and x.dtype == torch.float32:
            return self._forward_bf16(inputs)
        # inference mode: the inference path's (model/inference.py); the reference renderer
        # (no_grad) stays the training forward exactly
        if runtime.gpu_inference(x.device) and torch.is_inference_mode_enabled():
            return self.forward_lean(inputs)
        h = None
        for i, layer in enumerate(self.layers):
            if h is None:
                h = linear_of_concat(layer, inputs)
            elif i in self.skips:
                h = linear_of_concat(layer, [h, *inputs])
            else:
                h = layer(h)
            h = torch.relu(h)
        if self.out is None:
            return h
        if h is None:  # depth 0: a single linear map of the input
            return linear_of_concat(self.out, inputs)
        return self.out(h)

    def forward_lean(self, inputs: list[Tensor]) -> Tensor:
        """The forward pass without autograd in as few passes over the activations as
        PyTorch ops allow (`_linear_of_parts` with one BLAS call a layer): the GPU's
        inference path (any device runs it; the tests compare it with the plain path on a
        CPU). The plain path makes a new activation for the bias, one for each
        conditioning term and one for the ReLU: at a 512 px frame's ~8 M samples a 64-wide
        half-precision activation is 1 GB, and those passes were most of an H100's `add`
        and `clamp_min` time (docs/bench/gpu_h100_20261126_prof512.txt: 7.3 and 3.8 of
        50 ms). Runs in the autocast dtype where autocast is on."""
        dev = inputs[0].device.type
        dtype = (torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev)
                 else inputs[0].dtype)
        with torch.autocast(dev, enabled=False):
            return self._layers(inputs, lambda layer, parts, relu: _linear_of_parts(
                layer, parts, relu, dtype, _dense_blas))

    def _forward_bf16(self, inputs: list[Tensor]) -> Tensor:
        def linear(layer, parts, relu):
            h = linear_of_concat(layer, parts, torch.bfloat16)
            return torch.relu(h) if relu else h

        return self._layers([p.to(torch.bfloat16) for p in inputs], linear).float()

    def _forward_fused(self, inputs: list[Tensor]) -> Tensor:
        dtype = torch.bfloat16 if getattr(_fusing, "bf16", False) else torch.float32
        return self._layers(inputs, lambda layer, parts, relu: _linear_of_parts(
            layer, parts, relu, dtype, _dense_onednn)).float()

    def _layers(self, inputs: list[Tensor], linear) -> Tensor:
        """The layers in order through linear(layer, parts, relu): parts the inputs for the
        first layer and at a skip the last activation with the inputs again, else it
        alone; ReLU on every layer but the output."""
        h = None
        for i, layer in enumerate(self.layers):
            parts = inputs if h is None else [h, *inputs] if i in self.skips else [h]
            h = linear(layer, parts, True)
        if self.out is not None:
            h = linear(self.out, inputs if h is None else [h], False)
        return h
