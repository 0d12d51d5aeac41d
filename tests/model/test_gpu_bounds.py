"""The Triton kernels stay inside their tensors on a whole frame: an untrained `fast` model
(workflows/untrained.py's, which bench_render.py times: a toy face mesh, detail levels and
expression fields) rendered
down the GPU's inference path under Triton's interpreter, every load and store checked
(tests/triton_bounds.py). The kernels' own tests check their values; this checks what a
GPU would fault on, with the shapes a frame gives them."""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                                reason="Triton is not installed (the test extra installs it)")

ROOT = Path(__file__).resolve().parents[2]

CHECK = textwrap.dedent("""
    import json

    import numpy as np
    import torch
    import triton_bounds
    from flamenerf import gpu_kernels
    from flamenerf.model.gpu_emulation import gpu_path_on_cpu
    from flamenerf.model.inference import FAST
    from flamenerf.model.render_image import render_image
    from flamenerf.workflows.untrained import camera, untrained

    triton_bounds.install()
    m = untrained("fast", torch.device("cpu"))
    w, a = m.codes(torch.tensor([0]))
    intr, c2w = camera(16)
    mask = np.zeros((16, 16), bool)
    mask[4:12, 5:11] = True
    with gpu_path_on_cpu(half=True):
        render_image(m, intr, c2w, w[0].detach(), a[0].detach(), torch.full((m.expr_dim,), 0.3),
                     mask, settings=FAST)
    frame = json.loads(json.dumps(triton_bounds.stats))
    # the check can fail: a mesh index past the one mesh reads another's vertices
    triton_bounds.stats["out_of_bounds"].clear()
    gpu_kernels.knn(torch.rand(10, 3), torch.rand(1, 50, 3), torch.full((10,), 1), 1)
    print(json.dumps({"frame": frame, "planted": triton_bounds.stats["out_of_bounds"]}))
""")


@pytest.mark.slow
def test_the_kernels_stay_inside_their_tensors_on_a_frame():
    env = {**os.environ, "TRITON_INTERPRET": "1", "FLAMENERF_GPU_KERNELS": "1",
           "FLAMENERF_CPU_KERNELS": "0",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", CHECK], env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    frame = got["frame"]
    assert set(frame["launches"]) == {"hashgrid", "knn", "field_heads"}, frame
    assert frame["checked"] > 10**4, frame
    assert frame["out_of_bounds"] == {}, frame
    assert got["planted"].get("knn load", 0) > 0, got
