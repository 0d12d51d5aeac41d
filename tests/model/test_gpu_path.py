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
    from flamenerf import gpu_kernels
    from flamenerf.model import mlp
    from flamenerf.model.gpu_emulation import gpu_path_on_cpu
    from flamenerf.model.inference import FAST
    from test_inference import render, toy_model

    assert gpu_kernels.available(torch.device("cpu"))
    m = toy_model()
    m.cfg.sampler.refine_main = 16  # the second pass too
    # float32 throughout: this CPU's bfloat16 layers would differ by their rounding
    settings = dataclasses.replace(FAST, half=False)
    cpu = render(m, settings)

    calls = {"contract": 0, "lean": 0, "encode": 0, "heads": 0, "knn": 0}
    def counted(name, fn):
        def wrapper(*a, **k):
            out = fn(*a, **k)
            calls[name] += out is not None  # the kernel ran (None: the caller's fallback)
            return out
        return wrapper
    gpu_kernels.hashgrid_contract = counted("contract", gpu_kernels.hashgrid_contract)
    gpu_kernels.hashgrid_forward = counted("encode", gpu_kernels.hashgrid_forward)
    gpu_kernels.field_heads = counted("heads", gpu_kernels.field_heads)
    gpu_kernels.knn = counted("knn", gpu_kernels.knn)
    mlp.MLP.forward_lean = counted("lean", mlp.MLP.forward_lean)
    with gpu_path_on_cpu():
        gpu = render(m, settings)
    heads_on = "field_heads" in gpu_kernels.working()
    assert all(v > 0 for k, v in calls.items() if k != "heads"), calls
    assert (calls["heads"] > 0) == heads_on, calls
    assert 0.2 < float(cpu["acc"].mean()) < 0.999
    for k in ("rgb", "acc", "depth"):
        err = (gpu[k] - cpu[k]).abs().max()
        assert err < 2e-4, (k, float(err))
    import json
    print("gpu path agrees", json.dumps(calls))
""")

RECORD = textwrap.dedent("""
    import dataclasses
    import json
    import sys

    from flamenerf import gpu_kernels
    from flamenerf.model.gpu_emulation import gpu_path_on_cpu
    from flamenerf.model.inference import FAST
    from test_inference import render, toy_model

    m = toy_model()
    ref = render(m, dataclasses.replace(FAST, half=False))
    with gpu_path_on_cpu(half=True), gpu_kernels.recording() as launches:
        half = render(m, FAST)  # the fields in float16, as CUDA's autocast runs them
    for k in ("rgb", "acc", "depth"):
        err = float((half[k] - ref[k]).abs().max())
        assert 0 < err < 1e-2, (k, err)  # float16's rounding (3.6e-3 seen), and no more
    json.dump(launches, open(sys.argv[1], "w"))
""")

BUILD = textwrap.dedent("""
    import json
    import sys

    from flamenerf import gpu_build, gpu_kernels

    launches = json.load(open(sys.argv[1]))
    assert {x["kernel"] for x in launches} == {"hashgrid", "knn", "field_heads"}, launches
    assert {x["signature"]["f_ptr"] for x in launches if x["kernel"] == "field_heads"} \\
        == {"*fp16"}
    for x in {json.dumps(x, sort_keys=True): x for x in launches}.values():
        got = gpu_build.build(x, 90)
        # no spill, and room for several blocks an SM (the tiled knn took 255 registers)
        assert got["spill_bytes"] == 0 and got["registers"] <= 128, (x["kernel"], got)
    print("built for sm_90")
""")


@pytest.mark.slow
def test_gpu_inference_path_matches_the_cpu_one_under_the_interpreter():
    """With every kernel on (the default), and with the field heads' kernel off: the same
    image as the CPU's path, and the features computed once either way (the heads'
    fallback once computed them a second time)."""
    import json

    calls = {}
    for chosen in (None, "hashgrid,knn"):
        env = {**os.environ, "TRITON_INTERPRET": "1",
               "FLAMENERF_CPU_KERNELS": "0",  # the hash grid's encoding from the Triton kernel
               "PYTHONPATH": os.pathsep.join([str(TESTS / "model"), str(TESTS),
                                              os.environ.get("PYTHONPATH", "")])}
        env.pop("FLAMENERF_GPU_KERNELS", None)
        if chosen is not None:
            env["FLAMENERF_GPU_KERNELS"] = chosen
        out = subprocess.run([sys.executable, "-W", "ignore", "-c", CHECK], env=env,
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        assert "gpu path agrees" in out.stdout
        calls[chosen] = json.loads(out.stdout.split("gpu path agrees", 1)[1])
    assert calls[None]["heads"] > 0 and calls["hashgrid,knn"]["heads"] == 0, calls
    assert calls[None]["encode"] == calls["hashgrid,knn"]["encode"], calls


def _nvidia_tools() -> bool:
    """Triton's compiler with the NVIDIA backend and the tools it ships (ptxas, cuobjdump),
    and the ASTSource of Triton >= 3.3 (`constexprs`), which gpu_build calls."""
    import inspect

    import triton
    import triton.compiler

    tools = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    return ((tools / "ptxas").exists() and (tools / "cuobjdump").exists()
            and "constexprs" in inspect.signature(triton.compiler.ASTSource).parameters)


@pytest.mark.skipif(importlib.util.find_spec("triton") is None or not _nvidia_tools(),
                    reason="Triton without its NVIDIA backend's tools, or older than 3.3")
@pytest.mark.slow
def test_the_gpu_paths_kernels_build_for_an_h100_without_one(tmp_path):
    """The launches of a half-precision frame down the GPU's path (recorded under the
    interpreter) compile for sm_90 with Triton's compiler and ptxas, which ship with Triton:
    a kernel that only the interpreter takes, or one that spills registers, is found here
    rather than in scarce time on a GPU."""
    env = {**os.environ, "TRITON_INTERPRET": "1", "FLAMENERF_GPU_KERNELS": "1",
           "FLAMENERF_CPU_KERNELS": "0",
           "PYTHONPATH": os.pathsep.join([str(TESTS / "model"), str(TESTS),
                                          os.environ.get("PYTHONPATH", "")])}
    rec = tmp_path / "launches.json"
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", RECORD, str(rec)], env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    env.pop("TRITON_INTERPRET")
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", BUILD, str(rec)], env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "built for sm_90" in out.stdout
