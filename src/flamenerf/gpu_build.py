"""The GPU kernels built for an NVIDIA GPU on a machine without one, and what each needs.

Triton's interpreter, which runs the kernels in the tests, is not its compiler: a kernel
can pass every interpreter test and still fail to build for a GPU, or build and spill
registers to slow local memory. Triton ships its compiler and NVIDIA's `ptxas` and
`cuobjdump`, none of which needs a GPU: a launch recorded anywhere
(`gpu_kernels.recording()`, e.g. a CPU render down the GPU's path under the interpreter:
model/gpu_emulation.py) is compiled here for a compute capability, and the cubin's
registers a thread, spilled bytes and shared memory are read. Used by
tests/model/test_gpu_path.py and benchmarks/gpu_kernels_build.py.
"""

from __future__ import annotations

import inspect
import re
import subprocess
import tempfile
import time
from pathlib import Path

from flamenerf import gpu_kernels

def build(launch: dict, arch: int) -> dict:
    """Compile a recorded launch (`gpu_kernels.launch_signature`) for an NVIDIA GPU of
    compute capability `arch` (80: A100, 90: H100/H200) without a GPU: Triton's compiler and
    the ptxas it ships. -> {"arch", "seconds", "registers", "spill_bytes" (stack and local
    memory a thread uses: registers that did not fit), "shared_bytes"}. Raises what
    Triton raises where the kernel does not compile. The process must not run Triton's
    interpreter (`TRITON_INTERPRET`), whose kernels are not compiled."""
    import triton
    from triton.backends.compiler import GPUTarget

    kernel = gpu_kernels._define()[launch["kernel"]]
    names = list(inspect.signature(kernel.fn).parameters)
    signature = {n: launch["signature"].get(n, "constexpr") for n in names}
    src = triton.compiler.ASTSource(
        fn=kernel, signature=signature,
        constexprs={(names.index(k),): v for k, v in launch["constexprs"].items()},
        attrs={(names.index(k),): [["tt.divisibility", 16]] for k in launch["divisible"]})
    target = GPUTarget("cuda", arch, 32)
    options = triton.compiler.make_backend(target).parse_options(
        {"num_warps": launch.get("num_warps", 4), "enable_fp_fusion": gpu_kernels.FP_FUSION})
    t = time.perf_counter()
    compiled = triton.compile(src, target=target, options=options.__dict__)
    seconds = time.perf_counter() - t
    usage = _resource_usage(compiled.asm["cubin"])
    return {"arch": arch, "seconds": round(seconds, 2), "registers": usage["REG"],
            "spill_bytes": usage["STACK"] + usage["LOCAL"], "shared_bytes": usage["SHARED"]}


def _resource_usage(cubin: bytes) -> dict:
    """cuobjdump's resource usage of a one-kernel cubin: {"REG": ..., "STACK": ...}."""
    import triton

    tool = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    with tempfile.NamedTemporaryFile(suffix=".cubin") as f:
        f.write(cubin)
        f.flush()
        text = subprocess.run([str(tool), "-res-usage", f.name], capture_output=True,
                              text=True, check=True).stdout
    return {k: int(v) for k, v in re.findall(r"([A-Z]+):(\d+)", text)}
