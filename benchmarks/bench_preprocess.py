#!/usr/bin/env python
"""Benchmark `flamenerf preprocess` on real clips: frames tracked, reprojection error,
frames per second (with the machine's load average, since CPU time is shared), and the
pictures for docs/preprocessing.md.

    python benchmarks/bench_preprocess.py \\
        --video orbit=clips/orbit_still_head.mp4 \\
        --video expressions=clips/expressions_static_camera.mp4 \\
        --out-dir /tmp/bench_preprocess --json benchmarks/results/preprocess.json \\
        --docs docs --trace expressions

For each NAME=VIDEO it writes the dataset to OUT_DIR/NAME, a contact sheet of overlay
frames to DOCS/preprocess_NAME.png, and for the --trace clip the jawOpen / smile / blink
trace to DOCS/expressions_trace.png. Extra flags after `--` go to the preprocessing
options (e.g. `-- size=128 fps=15`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def contact_sheet_from_dataset(ds_dir: Path, out_png: Path, n: int = 8, cols: int = 4):
    import imageio.v3 as iio

    from flamenerf.data.dataset import load_dataset
    from flamenerf.geometry import project_points
    from flamenerf.tracking import qa

    ds = load_dataset(ds_dir)
    pick = np.unique(np.round(np.linspace(0, len(ds.frames) - 1, n)).astype(int))
    tiles = []
    for k in pick:
        f = ds.frames[k]
        img = (ds.load_image(f) * 255 + 0.5).astype(np.uint8)
        uv, _ = project_points(ds.face_vertices[k].astype(np.float64), ds.intrinsics, f.c2w)
        label = f"t={f.extra.get('time', 0):.1f}s {f.extra.get('reprojection_error_px', 0):.2f}px"
        # head axes: the camera seen from the head
        cam = f.c2w if f.head_pose is None else np.linalg.inv(f.head_pose) @ f.c2w
        tiles.append(qa.overlay_frame(img, ds.load_mask(f), uv, ds.intrinsics, cam, label,
                                      upscale=1))
    out_png.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out_png, qa.contact_sheet(tiles, cols=cols))


def trace_from_dataset(ds_dir: Path, out_png: Path, title: str):
    from flamenerf.data.dataset import load_dataset
    from flamenerf.tracking import qa
    from flamenerf.tracking.report import GROUPS_ARKIT

    ds = load_dataset(ds_dir)
    t = np.array([f.extra["time"] for f in ds.frames])
    qa.plot_expression_traces(out_png, t, ds.expression_matrix(ds.frames),
                              ds.expression_names, GROUPS_ARKIT, title=title)


def _scene_row(sc: dict) -> dict:
    bg = sc["background"] or {}
    r = (lambda v, d=3: None if v is None else round(v, d))  # noqa: E731
    return {
        "case": sc["case"], "warnings": sc["warnings"],
        "background_status": bg.get("status"), "background_reason": bg.get("reason"),
        "frames": bg.get("frames"), "registered": bg.get("registered"),
        "background_reprojection_px": r(bg.get("reprojection_error_px_source")),
        "background_points": bg.get("points"),
        "background_focal_px": r(bg.get("focal_px_source"), 1),
        "background_s": r(bg.get("seconds"), 1),
        "camera_motion": {k: (r(v) if not isinstance(v, list) else [r(x) for x in v])
                          for k, v in sc["camera_motion"].items()},
        "head_motion": {k: r(v) for k, v in sc["head_motion"].items()},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--video", action="append", required=True, metavar="NAME=VIDEO")
    ap.add_argument("--out-dir", type=Path, default=Path("/tmp/bench_preprocess"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--docs", type=Path, default=None, help="write the docs pictures here")
    ap.add_argument("--trace", default=None, help="NAME of the clip whose trace to plot")
    ap.add_argument("opts", nargs="*", help="PreprocessOptions overrides, key=value")
    args = ap.parse_args()

    from flamenerf.tracking.pipeline import PreprocessOptions, preprocess_video

    overrides = {}
    for kv in args.opts:
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v) if v[:1].isdigit() or v in ("true", "false") else v
    results = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                           "python": sys.version.split()[0]}, "clips": {}}
    for spec in args.video:
        name, path = spec.split("=", 1)
        out = args.out_dir / name
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        rep = preprocess_video(path, out, PreprocessOptions(overwrite=True, progress=False,
                                                            **overrides))
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()
        err = rep["reprojection_error_px"]
        row = {
            "video": path, "selected_frames": rep["selected_frames"],
            "tracked_frames": rep["tracked_frames"], "kept_frames": rep["kept_frames"],
            "tracked_percent": round(rep["tracked_percent"], 2),
            "dropped": len(rep["dropped"]),
            "median_reprojection_error_px_source": round(err["rigid_median_source"], 3),
            "median_reprojection_error_px_out": round(err["rigid_median_out"], 3),
            "out_size": rep["crop"]["out_size"],
            "fov_x_deg": round(rep["camera"]["fov_x_deg"], 2),
            "azimuth_range_deg": [round(a, 1) for a in rep["camera"]["azimuth_range_deg"]],
            "wall_s": round(wall, 2),
            "frames_per_second": round(rep["selected_frames"] / wall, 2),
            "timings_s": {k: round(v, 2) for k, v in rep["timings_s"].items()},
            "scene": _scene_row(rep["scene"]),
            "loadavg_1min_before_after": [round(load0[0], 2), round(load1[0], 2)],
        }
        results["clips"][name] = row
        sc = row["scene"]
        print(f"{name}: {sc['case']}; background {sc['background_status']} "
              f"({sc['registered']} of {sc['frames']} frames registered, "
              f"{sc['background_reprojection_px']} px, {sc['background_s']} s)", flush=True)
        print(f"{name}: tracked {row['tracked_frames']}/{row['selected_frames']} "
              f"({row['tracked_percent']:.1f}%), median reprojection error "
              f"{row['median_reprojection_error_px_source']:.2f} px source / "
              f"{row['median_reprojection_error_px_out']:.2f} px at {row['out_size']}, "
              f"{row['frames_per_second']:.1f} frames/s (load {load0[0]:.2f} -> "
              f"{load1[0]:.2f})", flush=True)
        if args.docs is not None:
            contact_sheet_from_dataset(out, args.docs / f"preprocess_{name}.png")
            if name == args.trace:
                trace_from_dataset(out, args.docs / "expressions_trace.png",
                                   f"{Path(path).name}: MediaPipe blendshape scores (β)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
