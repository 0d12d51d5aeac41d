"""The GPU's inference path, wired end to end without a GPU: a CPU run sent down it
(`runtime.gpu_inference`) with the Triton kernels under Triton's interpreter, against the
CPU's own inference path. What differs between the two is only the layers' summation order.
The interpreter is chosen when Triton is imported, so the check runs in a fresh process."""

import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                                reason="Triton is not installed (the test extra installs it)")

TESTS = Path(__file__).resolve().parents[1]

CHECK = textwrap.dedent("""
    import dataclasses

    import torch
    from flamenerf import gpu_kernels, runtime
    from flamenerf.model import mlp
    from flamenerf.model.inference import FAST
    from test_inference import render, toy_model

    assert gpu_kernels.available(torch.device("cpu"))
    m = toy_model()
    m.cfg.sampler.refine_main = 16  # the second pass too
    # float32 throughout: this CPU's bfloat16 layers would differ by their rounding, and
    # autocast (the GPU's half precision) is CUDA's alone
    settings = dataclasses.replace(FAST, half=False)
    cpu = render(m, settings)

    calls = {"contract": 0, "lean": 0, "encode": 0, "heads": 0}
    def counted(name, fn):
        def wrapper(*a, **k):
            out = fn(*a, **k)
            calls[name] += out is not None  # the kernel ran (None: the caller's fallback)
            return out
        return wrapper
    gpu_kernels.hashgrid_contract = counted("contract", gpu_kernels.hashgrid_contract)
    gpu_kernels.hashgrid_forward = counted("encode", gpu_kernels.hashgrid_forward)
    gpu_kernels.field_heads = counted("heads", gpu_kernels.field_heads)
    mlp.MLP.forward_lean = counted("lean", mlp.MLP.forward_lean)
    runtime.gpu_inference = lambda device: True
    mlp._oneDNN_linear = lambda: None  # the CPU's fused layers off: the lean ones instead
    gpu = render(m, settings)
    assert all(v > 0 for v in calls.values()), calls
    assert 0.2 < float(cpu["acc"].mean()) < 0.999
    for k in ("rgb", "acc", "depth"):
        err = (gpu[k] - cpu[k]).abs().max()
        assert err < 2e-4, (k, float(err))
    print("gpu path agrees", calls)
""")


def test_gpu_inference_path_matches_the_cpu_one_under_the_interpreter():
    env = {**os.environ, "TRITON_INTERPRET": "1", "FLAMENERF_GPU_KERNELS": "1",
           "FLAMENERF_CPU_KERNELS": "0",  # the hash grid's encoding from the Triton kernel
           "PYTHONPATH": os.pathsep.join([str(TESTS / "model"), str(TESTS),
                                          os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", CHECK], env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "gpu path agrees" in out.stdout
