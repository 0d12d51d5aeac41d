"""Bake benchmark: how closely and how fast a trained run's bake draws it.

For each run given (trained already, e.g. `flamenerf train ... --preset fast`): bakes it
(`flamenerf bake`, timed), then draws the frames of its dataset's `reanimate` split (the
built-in scene: novel expressions from novel cameras, with ground truth) and of its `val`
split (each frame's camera and expression, frame 0's codes: eval's driven held-out) with
the bake and with the run's NeRF (the reference renderer, what eval measures): PSNR of the
whole image and of the face mask, bake against NeRF and, with ground truth, each against
it. Then speed: the reference rasteriser (this process, CPU) and the exported page in
headless Chromium (software WebGL: `--bench` frames drawn one after another, each
finished), at 128 and 256 px, and the export's size. Prints a table and writes JSON.

    python benchmarks/bench_bake.py RUN [RUN ...] --json docs/bench/bake_128.json
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TARGETS = """targets (fast, 128 and 256 px): bake against the run's own renders, same cameras
and expressions: face >= 32 dB, whole image >= 30 dB; against ground truth the re-animation
face within 1 dB of the NeRF's; bake <= 10 min at 128 px; the page >= 44 frames/s at 128 px
(10x the viewer's 4.4 updates/s on this CPU); export <= 50 MB at 256 px."""


def browser_fps(page: Path, w: int, frames: int) -> float | None:
    """Frames per second of the exported page in headless Chromium at w px, or None
    without Chromium."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as prof:
        out = subprocess.run(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
             "--use-angle=swiftshader", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run",
             f"--user-data-dir={prof}", f"--window-size={w + 40},{w + 40}", "--dump-dom",
             f"{page.absolute().as_uri()}?bare=1&w={w}&bench={frames}"],
            capture_output=True, text=True, timeout=600)
    m = re.search(r'"fps":([0-9.eE+-]+)', out.stdout)
    return float(m.group(1)) if m else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--frames", type=int, default=12, help="frames per split compared")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from flamenerf.data.dataset import Intrinsics
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.baked import bake_fidelity
    from flamenerf.splats.avatar import load_avatar
    from flamenerf.splats.rasterise import render_avatar
    from flamenerf.training.run import load_run
    from flamenerf.viewer.web_export import export_web
    from flamenerf.workflows.bake import BakeOptions, bake
    from flamenerf.workflows.bench import git_commit, machine_description

    print(TARGETS)
    report = {"machine": machine_description(), "commit": git_commit(), "runs": {}}
    for run_dir in args.runs:
        summary = bake(BakeOptions(run_dir, views=args.views))
        print(summary.describe())
        avatar = load_avatar(summary.path)
        run = load_run(run_dir)
        ds = run.dataset()
        intr = run.train_intrinsics(ds)
        row = {"bake_seconds": summary.seconds, "splats": summary.splats,
               "face_splats": summary.face_splats, "views": summary.views, "splits": {}}
        for split in ("reanimate", "val"):
            if not ds.splits.get(split):
                continue
            frames = ds.split(split)
            pick = np.linspace(0, len(frames) - 1, min(args.frames, len(frames))).round()
            fs = FrameSet(ds, [frames[int(i)] for i in pick], intr)
            res = bake_fidelity(run, avatar, fs, truth=True)
            row["splits"][split] = res
            line = (f"  {split:<9} bake vs NeRF: whole {res['baked_vs_nerf']['psnr']:.2f} dB, "
                    f"face {res['baked_vs_nerf']['psnr_face']:.2f} dB")
            if "baked_vs_truth" in res:
                line += (f"; face vs truth: bake {res['baked_vs_truth']['psnr_face']:.2f}, "
                         f"NeRF {res['nerf_vs_truth']['psnr_face']:.2f} dB")
            print(line)
        speed = {}
        with tempfile.TemporaryDirectory() as tmp:
            site = export_web(avatar, Path(tmp) / "site")
            row["export_mb"] = site.bytes / 1e6
            for w in (128, 256):
                m = avatar.meta["intrinsics"]
                base = Intrinsics(m["w"], m["h"], m["fx"], m["fy"], m["cx"], m["cy"])
                it = base.scaled(w / base.w)
                cam = np.asarray(avatar.meta["camera"])
                render_avatar(avatar, avatar.high, cam, it)
                t0 = time.perf_counter()
                for i in range(10):
                    render_avatar(avatar, avatar.low + (avatar.high - avatar.low) * (i % 2), cam,
                                  it)
                py = 10 / (time.perf_counter() - t0)
                page = browser_fps(site.folder / "index.html", w, 60)
                speed[w] = {"reference_rasteriser_fps": py, "page_fps": page}
                print(f"  {w} px: reference rasteriser {py:.1f} frames/s, page in headless "
                      f"Chromium {'-' if page is None else f'{page:.1f}'} frames/s")
        row["speed"] = speed
        print(f"  export {row['export_mb']:.1f} MB")
        report["runs"][str(run_dir)] = row
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
