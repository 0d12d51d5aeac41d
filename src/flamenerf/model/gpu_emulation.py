"""A CPU render sent down the GPU's inference path, for checks without a GPU: the GPU's
layers and kernels (`runtime.gpu_inference`), its nearest vertices (distance blocks and
the Triton kernel, not the CPU's k-d tree or compiled kernel) and, with `half`, CPU
autocast in float16 standing in for CUDA's. The Triton kernels then need Triton's
interpreter (`TRITON_INTERPRET=1` before Triton is imported, with
`FLAMENERF_GPU_KERNELS=1`). Its passes are the GPU's too: rays in the GPU's chunks, one
thread, the proposal's termination checked once per ray (`RenderSettings`'s choices as for
CUDA). Used by tests/model/test_gpu_path.py, benchmarks/gpu_kernels_build.py (which records
the launches to compile them for GPUs) and benchmarks/gpu_path_ops.py."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from flamenerf import meshes, runtime
from flamenerf.model import expression, inference, mlp


@contextlib.contextmanager
def gpu_path_on_cpu(half: bool = True) -> Iterator[None]:
    """Within the block, CPU renders take the GPU's inference path (module functions
    replaced, restored after). `half`: the fields in float16 where the render's settings
    ask for half precision, as on CUDA (else float32 throughout)."""

    def autocast(device, settings):
        return (torch.autocast("cpu", dtype=torch.float16) if half and settings.half
                else contextlib.nullcontext())

    cuda = torch.device("cuda")
    Settings = inference.RenderSettings

    def as_on_cuda(name):  # a RenderSettings choice made as for a CUDA device
        fn = getattr(Settings, name)
        return lambda self, device, *a: fn(self, cuda, *a)

    swaps = [(runtime, "gpu_inference", lambda device: True),
             (mlp, "_oneDNN_linear", lambda: None),  # the lean layers, not oneDNN's fused
             (expression, "nearest_vertices", meshes.nearest_vertices_off_cpu),
             (inference, "_autocast", autocast),
             # the GPU's passes: one chunk of a frame's rays, the proposal's termination
             # checked once per ray, and one render thread (which the interpreter needs too:
             # it patches triton.language while a kernel runs, so two kernels interpreted at
             # once fail, and go off, `_launch`)
             *[(Settings, name, as_on_cuda(name)) for name in
               ("rays_per_chunk", "render_threads", "proposal_samples_per_check")]]
    kept = [(mod, name, getattr(mod, name)) for mod, name, _ in swaps]
    try:
        for mod, name, fn in swaps:
            setattr(mod, name, fn)
        yield
    finally:
        for mod, name, fn in kept:
            setattr(mod, name, fn)
