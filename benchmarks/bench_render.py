"""Rendering speed and quality: the reference renderer (the training forward, what eval
uses) against the inference path (model/inference.py, what render and the viewer use).

- frames per second at each size for each preset (untrained models: the work per frame
  does not depend on training, except early termination, which only a trained scene
  shows); large frames are timed on a band of rows and scaled (`rows_timed` says so);
- with --run DIR (a trained run; its dataset is needed): the same for the trained model,
  the PSNR of both renderers against the ground-truth images of a few training frames
  (their own codes, the run's resolution) and of the inference path against the
  reference, and the viewer's latency while the camera is dragged (time per update
  through the viewer's own render function, at its coarse drag level and at full size).

Prints a table and writes JSON + Markdown (default docs/bench/render.{json,md}). Timings on
a shared machine move with its load: the load average is recorded next to them.

Usage: python benchmarks/bench_render.py [--run DIR] [--dataset DIR] [--device cuda]
        [--sizes 128 256 512] [--presets fast flame-in-nerf nerfies no-prior] [--repeats 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from flamenerf.data.dataset import Intrinsics
from flamenerf.model.inference import FAST, REFERENCE, VIEWER
from flamenerf.model.render_image import render_image
from flamenerf.workflows.untrained import camera, untrained

PATHS = {"reference": REFERENCE, "inference": FAST, "viewer": VIEWER}


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def frame_seconds(model, intr: Intrinsics, c2w, omega, phi, expr, mask, settings,
                  repeats: int, max_rays: int) -> tuple[float, float, int]:
    """Best-of-`repeats` seconds for one whole frame (after one warm-up that also makes the
    bakes), timed on the first rows that hold at most max_rays rays. -> (wall s, this
    process's CPU s, rows timed). With one thread the CPU time is what the frame costs a
    core of its own, however busy the machine is."""
    rows = max(1, min(intr.h, max_rays // intr.w))
    band = Intrinsics(intr.w, rows, intr.fx, intr.fy, intr.cx, intr.cy)
    dev = next(model.parameters()).device
    render_image(model, band, c2w, omega, phi, expr, mask[:rows], settings=settings)
    best, cpu = math.inf, math.inf
    for _ in range(repeats):
        _sync(dev)
        t, c = time.perf_counter(), time.process_time()
        render_image(model, band, c2w, omega, phi, expr, mask[:rows], settings=settings)
        _sync(dev)
        best = min(best, time.perf_counter() - t)
        cpu = min(cpu, time.process_time() - c)
    return best * intr.h / rows, cpu * intr.h / rows, rows


def speed_rows(label, model, cams, omega, phi, expr, masks, sizes, repeats, max_rays):
    rows = []
    for size in sizes:
        intr, c2w = cams(size)
        row = {"model": label, "size": size}
        for path, settings in PATHS.items():
            s, cpu, timed = frame_seconds(model, intr, c2w, omega, phi, expr,
                                          masks(intr, c2w), settings, repeats, max_rays)
            row[f"{path}_s"] = round(s, 4)
            row[f"{path}_cpu_s"] = round(cpu, 4)
            row[f"{path}_fps"] = round(1 / s, 3)
            row[f"{path}_rows_timed"] = timed
        row["speedup"] = round(row["reference_s"] / row["inference_s"], 2)
        print(f"{label:>22s} {size:4d}px  reference {row['reference_s']:8.3f} s "
              f"(CPU {row['reference_cpu_s']:.3f})  inference {row['inference_s']:7.3f} s "
              f"(CPU {row['inference_cpu_s']:.3f}, {row['inference_fps']:6.2f} fps)  "
              f"x{row['speedup']:.1f}  load {os.getloadavg()[0]:.1f}", flush=True)
        rows.append(row)
    return rows


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(float(np.mean((a - b) ** 2)), 1e-12)))


def quality(run, ds, frames: int) -> dict:
    from flamenerf.data.prior import prior_mask
    from flamenerf.images import resize_image

    split = ds.split("train")
    pick = split[:: max(1, len(split) // frames)][:frames]
    intr = run.train_intrinsics(ds)
    rows = []
    for fr in pick:
        mask = prior_mask(ds, ds.face_vertices[fr.position], fr.c2w, intr)
        omega, phi = run.frame_codes(fr.frame_index)
        # at the training resolution, as the trainer sees it (data/scene.py)
        gt = resize_image(ds.load_image(fr), intr.w, intr.h)[..., :3]
        e = torch.as_tensor(fr.expression)
        out = {k: render_image(run.model, intr, fr.c2w, omega, phi, e, mask, settings=s)
               ["rgb"].numpy() for k, s in PATHS.items()}
        rows.append({"position": fr.position, "reference_psnr": psnr(out["reference"], gt),
                     "inference_psnr": psnr(out["inference"], gt),
                     "inference_vs_reference_psnr": psnr(out["inference"], out["reference"]),
                     "max_abs_diff": float(np.abs(out["inference"] - out["reference"]).max()),
                     "viewer_psnr": psnr(out["viewer"], gt)})
    mean = {k: round(float(np.mean([r[k] for r in rows])), 3) for k in rows[0] if k != "position"}
    mean["psnr_difference_db"] = round(mean["inference_psnr"] - mean["reference_psnr"], 3)
    mean["viewer_psnr_difference_db"] = round(mean["viewer_psnr"] - mean["reference_psnr"], 3)
    mean["frames"] = rows
    mean["resolution"] = [intr.w, intr.h]
    return mean


def viewer_latency(run, ds, height: int, steps: int) -> dict:
    """Time per update of RenderWorker._render while the camera orbits by 2° a step (every
    update a new camera and a new prior mask, as in a drag)."""
    from flamenerf.data.dataset import reference_position
    from flamenerf.viewer.mask import FaceMasker
    from flamenerf.viewer.renderer import RenderWorker

    pos = reference_position(ds)
    fr = ds.frames[pos]
    omega, phi = run.frame_codes(0)
    masker = FaceMasker(ds, pos, run.model)
    intr = ds.intrinsics
    fov = 2 * math.atan(intr.h / 2 / intr.fy)
    out = {"height": height}
    for path, settings in PATHS.items():
        w = RenderWorker(run.model, omega, phi, masker, fr.expression, lambda *a: None,
                         height=height, settings=settings)
        for level, h in enumerate(w.levels(height, True)):
            times = []
            for i in range(steps + 1):
                a = math.radians(2 * i)
                rot = np.array([[math.cos(a), 0, math.sin(a), 0], [0, 1, 0, 0],
                                [-math.sin(a), 0, math.cos(a), 0], [0, 0, 0, 1]])
                snap = dict(key=0, state=(i, 0), c2w=rot @ fr.c2w, fov_y=fov, aspect=1.0,
                            expression=fr.expression, mode="RGB", height=h, final=True,
                            depth_range=None, head=None, filmed=None)
                t = time.perf_counter()
                w._render(snap, level, cancellable=False)
                if i:  # the first one makes the bakes
                    times.append(time.perf_counter() - t)
            s = float(np.median(times))
            out[f"{path}_{h}px_s"] = round(s, 4)
            out[f"{path}_{h}px_updates_per_s"] = round(1 / s, 2)
            print(f"viewer {path:>9s} {h:4d}px: {1000 * s:7.1f} ms per update "
                  f"({1 / s:5.1f}/s)", flush=True)
    out.update(slider_latency(run, ds, masker, fr, fov, height, steps))
    out.update(filmed_latency(run, ds, masker, fr, fov, height, steps))
    return out


def filmed_latency(run, ds, masker, fr, fov: float, height: int, steps: int) -> dict:
    """Time per full-height update of the viewer's worker playing the capture as filmed
    from frame 0's camera: each update a new frame, so new codes, head pose and mesh, and
    the whole image again (rendering/filmed.py)."""
    from flamenerf.rendering.filmed import FilmedClip
    from flamenerf.viewer.renderer import RenderWorker

    cap = ds.capture()
    if not cap or run.codes_error(ds, cap) is not None:
        return {}
    clip = FilmedClip(run, ds, cap)
    w = RenderWorker(run.model, *run.frame_codes(0), masker, fr.expression, lambda *a: None,
                     height=height)
    top = len(w.levels(height, True)) - 1
    times = []
    for i in range(min(steps + 1, len(clip))):
        k = i * (len(clip) - 1) // max(steps, 1)
        f = clip.frame(k)
        snap = dict(key=0, state=(0, i), c2w=fr.c2w, fov_y=fov, aspect=1.0,
                    expression=f.expression, mode="RGB", height=height, final=True,
                    depth_range=None, head=f.head, filmed=f)
        t = time.perf_counter()
        w._render(snap, top, cancellable=False)
        if i:
            times.append(time.perf_counter() - t)
    s = float(np.median(times))
    print(f"viewer capture as filmed {height}px: {1000 * s:7.1f} ms per update "
          f"({1 / s:5.1f}/s)", flush=True)
    return {f"filmed_{height}px_s": round(s, 4), f"filmed_{height}px_updates_per_s": round(1 / s, 2)}


def slider_latency(run, ds, masker, fr, fov: float, height: int, steps: int) -> dict:
    """Time per full-height update of the viewer's worker while one slider moves and the
    camera stays (frame 0's): after one whole image, each update renders only the pixels
    inside the prior's silhouette before or after the change (viewer/renderer.py). The
    slider: the control whose range in the training frames is widest, swept across it."""
    from flamenerf.viewer.renderer import RenderWorker, View

    omega, phi = run.frame_codes(0)
    exprs = np.stack([f.expression for f in ds.frames]).astype(np.float32)
    k = int(np.argmax(exprs.max(0) - exprs.min(0)))
    lo, hi = float(exprs[:, k].min()), float(exprs[:, k].max())
    w = RenderWorker(run.model, omega, phi, masker, fr.expression, lambda *a: None,
                     height=height)
    top = len(w.levels(height, True)) - 1
    w.views[0] = View(fr.c2w.copy(), fov, 1.0)
    times, rays = [], []
    for i in range(steps + 2):
        e = np.asarray(fr.expression, np.float32).copy()
        if i:
            e[k] = lo + (hi - lo) * (i - 1) / max(steps, 1)
        snap = dict(key=0, state=(0, i), c2w=w.views[0].c2w, fov_y=fov, aspect=1.0,
                    expression=e, mode="RGB", height=height, final=True, depth_range=None,
                    head=None, filmed=None)
        t = time.perf_counter()
        frame = w._render(snap, top, cancellable=False)
        if i:  # the first one: the whole image
            times.append(time.perf_counter() - t)
            rays.append(frame.extras["rays"])
    s = float(np.median(times))
    name = run.expression_names[k] if k < len(run.expression_names) else str(k)
    print(f"viewer slider {name} {height}px: {1000 * s:7.1f} ms per update ({1 / s:5.1f}/s), "
          f"{int(np.median(rays))} of {height * height} rays", flush=True)
    return {f"slider_{height}px_s": round(s, 4),
            f"slider_{height}px_updates_per_s": round(1 / s, 2),
            f"slider_{height}px_rays": int(np.median(rays)), "slider_control": name}


def markdown(res: dict) -> str:
    lines = [f"# Rendering speed and quality ({res['device_name']})", "",
             f"`{res['command']}` — load average {res['loadavg_before'][0]:.1f} before, "
             f"{res['loadavg_after'][0]:.1f} after (a shared machine: other jobs slow it "
             "down). Reference: the training forward (eval); inference: "
             "model/inference.py (render, viewer).", "",
             "| model | size | reference s/frame (CPU s) | inference s/frame (CPU s) | "
             "inference fps | speed-up |", "|---|---|---|---|---|---|"]
    for r in res["speed"]:
        lines.append(f"| {r['model']} | {r['size']} | {r['reference_s']:.3f} "
                     f"({r['reference_cpu_s']:.3f}) | {r['inference_s']:.3f} "
                     f"({r['inference_cpu_s']:.3f}) | {r['inference_fps']:.2f} | "
                     f"{r['speedup']:.1f}x |")
    q = res.get("quality")
    if q:
        lines += ["", f"Quality on {len(q['frames'])} training frames of the run "
                  f"({q['resolution'][0]}x{q['resolution'][1]}, own codes): PSNR against the "
                  f"images {q['reference_psnr']:.3f} dB (reference) vs "
                  f"{q['inference_psnr']:.3f} dB (inference), difference "
                  f"{q['psnr_difference_db']:+.3f} dB; inference against reference "
                  f"{q['inference_vs_reference_psnr']:.1f} dB PSNR, max |diff| "
                  f"{q['max_abs_diff']:.3f}; the viewer's settings (fewer main samples) "
                  f"{q['viewer_psnr']:.3f} dB, {q['viewer_psnr_difference_db']:+.3f} dB."]
    v = res.get("viewer")
    if v:
        lines += ["", f"Viewer while dragging (height {v['height']}, per update through "
                  "RenderWorker._render, median):", ""]
        lines += [f"- {k.replace('_', ' ')}: {val}" for k, val in v.items() if k != "height"]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, default=None, help="a trained run (quality, viewer)")
    ap.add_argument("--dataset", type=Path, default=None, help="the run's dataset, if moved")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--presets", nargs="+",
                    default=["fast", "flame-in-nerf", "nerfies", "no-prior"])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--max-rays", type=int, default=0,
                    help="time at most this many rays per frame (0: 65536 for `fast` and "
                         "trained runs, 4096 for the paper's MLP presets on a CPU)")
    ap.add_argument("--frames", type=int, default=4, help="frames for the quality figure")
    ap.add_argument("--viewer-height", type=int, default=128)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--refine-main", type=int, default=-1,
                    help="the trained run's second-pass samples for rays its main samples "
                         "leave unfinished (model.sampler.refine_main; 0: no second pass; "
                         "-1: the run's own), to time a frame with and without it")
    ap.add_argument("--out", type=Path, default=Path("docs/bench/render"))
    args = ap.parse_args()
    from flamenerf.runtime import reexec_with_tuned_allocator

    reexec_with_tuned_allocator(sys.argv)  # PERF_NOTES: glibc's page faults, ~2x on CPU
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    load_before = os.getloadavg()
    res: dict = {"benchmark": "render", "command": "python benchmarks/bench_render.py "
                 + " ".join(sys.argv[1:]), "device": str(dev),
                 "device_name": (torch.cuda.get_device_name(dev) if dev.type == "cuda"
                                 else f"CPU, {torch.get_num_threads()} threads, "
                                      f"{os.cpu_count()} cores"),
                 "settings": {k: dataclasses.asdict(s) for k, s in PATHS.items()},
                 "speed": []}

    def cap(model) -> int:
        if args.max_rays:
            return args.max_rays
        if dev.type == "cpu":
            return 4096 if model.cfg.field.kind == "mlp" else 1 << 16
        # one pass of the renderer's own size: a smaller band, scaled, would pay the
        # per-pass cost several times (a 512 px frame is one pass of a hash-grid model)
        return FAST.rays_per_chunk(dev, model)

    for name in args.presets:
        m = untrained(name, dev)
        w, a = m.codes(torch.tensor([0], device=dev))

        def masks(intr, c2w):
            mask = np.zeros((intr.h, intr.w), bool)
            mask[intr.h // 4: 3 * intr.h // 4, intr.w // 3: 2 * intr.w // 3] = True
            return mask

        res["speed"] += speed_rows(f"{name} (untrained)", m, camera, w[0].detach(),
                                   a[0].detach(), torch.full((m.expr_dim,), 0.3), masks,
                                   args.sizes, args.repeats, cap(m))
    if args.run is not None:
        from flamenerf.data.prior import prior_mask
        from flamenerf.training.run import load_run

        run = load_run(args.run, str(dev))
        if args.refine_main >= 0:  # both renderers read it at render time
            run.model.cfg.sampler.refine_main = args.refine_main
        ds = run.dataset(args.dataset)
        fr = ds.frames[0]
        omega, phi = run.frame_codes(0)

        def cams(size):
            return ds.intrinsics.scaled(size / ds.intrinsics.w), fr.c2w

        def run_masks(intr, c2w):
            return prior_mask(ds, ds.face_vertices[fr.position], c2w, intr)

        res["speed"] += speed_rows(f"{run.config.preset} (trained)", run.model, cams, omega,
                                   phi, torch.as_tensor(fr.expression), run_masks, args.sizes,
                                   args.repeats, cap(run.model))
        res["run"] = str(args.run)
        res["refine_main"] = run.model.cfg.sampler.refine_main
        res["quality"] = quality(run, ds, args.frames)
        q = res["quality"]
        print(f"quality: reference {q['reference_psnr']:.3f} dB, inference "
              f"{q['inference_psnr']:.3f} dB ({q['psnr_difference_db']:+.3f}); inference vs "
              f"reference {q['inference_vs_reference_psnr']:.1f} dB; the viewer's "
              f"{q['viewer_psnr']:.3f} dB ({q['viewer_psnr_difference_db']:+.3f})", flush=True)
        res["viewer"] = viewer_latency(run, ds, args.viewer_height, steps=6)
    res.update(loadavg_before=[round(x, 2) for x in load_before],
               loadavg_after=[round(x, 2) for x in os.getloadavg()],
               python=platform.python_version(), torch=torch.__version__)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    js, md = args.out.with_suffix(".json"), args.out.with_suffix(".md")
    js.write_text(json.dumps(res, indent=1) + "\n")
    md.write_text(markdown(res))
    print(f"wrote {js} and {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
