"""What benchmarks/gpu_kernel_check.py renders and how it picks the set of Triton kernels
to keep: the configurations it tries (FIRST, then on a failure BISECT) and the largest set
that rendered right at every size (best_set), as FLAMENERF_GPU_KERNELS takes it."""

from __future__ import annotations

from flamenerf.gpu_kernels import NAMES, UNPROVEN

DEFAULT = ",".join(k for k in NAMES if k not in UNPROVEN)
RIGHT = 0.05
"""The largest colour difference from the kernels-off frame that counts as rendering right
(half precision and the layers' summation order differ by ~1e-3)."""

FIRST = [("off", "0", ""), ("all", "1", ""),
         ("default", "", ""),  # FLAMENERF_GPU_KERNELS unset: what a user gets
         ("field_heads widths of 16", "field_heads", "64,4,16")]
"""(label, FLAMENERF_GPU_KERNELS ('' unset), field_heads' BLOCK,WARPS,DOT_MIN or '')"""
BISECT = [c for c in [(f"{k} alone", k, "") for k in NAMES]
          + [(f"all but {k}", ",".join(x for x in NAMES if x != k), "") for k in NAMES]
          if ("" if c[1] == DEFAULT else c[1], c[2]) not in {(f[1], f[2]) for f in FIRST}]
"""Each kernel alone and all but each, less what FIRST rendered already."""


def kernel_set(env: str) -> str:
    """FLAMENERF_GPU_KERNELS's value as the list of names it turns on ('1': all, '0')."""
    return DEFAULT if env == "" else env


def best_set(rows: list[dict]) -> str:
    """The largest set of kernels (as FLAMENERF_GPU_KERNELS takes it) whose every render,
    at every size, was right: '1' for all of them, '0' for none."""
    ok: dict[str, bool] = {}
    for r in rows:
        if not r["heads"]:
            e = kernel_set(r["env"])
            ok[e] = ok.get(e, True) and r["right"]
    sets = sorted((e for e in ok if e != "0"),
                  key=lambda e: len(NAMES) + 1 if e == "1" else len(e.split(",")),
                  reverse=True)
    return next((e for e in sets if ok[e]), "0")
