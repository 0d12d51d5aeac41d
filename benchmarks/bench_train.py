"""Training benchmark: quality-vs-time of one preset (`fast` unless
`--quality-preset` says otherwise), and the throughput and render time of every preset, on
the machine at hand. Prints figures and writes JSON.

    python benchmarks/bench_train.py --scene scenes/s128 --size 128 --budget 600 \
        --eval-every 100 --json docs/bench/train.json

(the scene is made first if missing: the built-in scene at `--size`, 300 capture frames,
i.e. `flamenerf synth scenes/s128 --size 128`).

Quality: the preset trains for `--budget` seconds of wall time (evaluation pauses
excluded) or its schedule (`--steps` overrides it), whichever ends first. Every
`--eval-every` seconds it is evaluated with the paper's held-out protocol on a subset of
`val` frames (ω fitted, everything else frozen), and as a driven re-animation on a subset
of the `reanimate` split (frame 0's codes, each frame's β and camera, against the scene's
ground truth: `eval`'s `reanimate` section, its face PSNR); at the end on every frame of
both. The time to each of `--targets` (default 25, 28, 30 dB) is read off those
evaluations (`time_to_db` held-out, `reanimate_time_to_db` the re-animation's face). The H100
figures in docs/presets.md came from, e.g., `--quality-preset flame-in-nerf --scene
scenes/s256 --size 256 --budget 290 --eval-every 60 --targets 25,28,29,30`.

Throughput: each preset trains a few steps at its own batch size (rays/s, after one warm-up
step) and renders one 256x256 frame (`--render-fraction` < 1 renders that fraction of the
rays and scales the time up linearly; the JSON says which).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def heldout_psnr(model, ds, intr, frames, fit_steps, batch_rays):
    """The paper's held-out protocol exactly as `flamenerf eval` runs it (PSNR averaged over
    frames) -> (mean MSE, mean PSNR)."""
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.protocol import EvalOptions, heldout

    res, _ = heldout(model, FrameSet(ds, frames, intr),
                     EvalOptions(fit_steps=fit_steps, fit_batch_rays=batch_rays))
    return res["mse"], res["psnr"]


def reanimation_face_psnr(model, ds, intr, frames) -> float:
    """The driven re-animation as `flamenerf eval` runs it (frame 0's codes, each frame's β,
    camera and mask, the reference renderer) -> its face PSNR averaged over `frames`."""
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.protocol import reanimation

    dev = next(model.parameters()).device
    omega0, phi0 = model.codes(torch.zeros(1, dtype=torch.long, device=dev))
    with model.outside_training():
        res, _ = reanimation(model, FrameSet(ds, frames, intr), omega0[0].detach(),
                             phi0[0].detach())
    return res["psnr_face"]


def quality_run(args, scene: Path, log) -> dict:
    from flamenerf.config import override, parse_overrides, preset
    from flamenerf.training.trainer import Trainer

    cfg = override(preset(args.quality_preset), parse_overrides(args.set))
    if args.steps:
        cfg.train.steps = args.steps
    if args.batch_rays:
        cfg.train.batch_rays = args.batch_rays
    cfg.train.seed = args.seed
    run_dir = Path(tempfile.mkdtemp(prefix="bench_fast_"))
    ds_w = __import__("flamenerf.data.dataset", fromlist=["x"]).load_dataset(scene).intrinsics.w
    cfg.train.downscale = ds_w / args.size
    cfg.train.image_every = 0
    t = Trainer(cfg, scene, run_dir / "run", quiet=True)
    val = t.ds.split("val")
    sub = val[:: max(1, len(val) // args.eval_frames)][: args.eval_frames]
    rean = t.ds.split("reanimate") if t.ds.splits.get("reanimate") else []
    rean_sub = rean[:: max(1, len(rean) // args.eval_frames)][: args.eval_frames]
    curve, train_s, next_eval = [], 0.0, args.eval_every
    log(f"{args.quality_preset} @ {args.size}px: budget {args.budget:.0f} s, {cfg.train.steps} "
        f"steps of {cfg.train.batch_rays} rays")
    while train_s < args.budget and t.step < cfg.train.steps:
        t0 = time.perf_counter()
        t.train_step()
        train_s += time.perf_counter() - t0
        if train_s >= next_eval or train_s >= args.budget or t.step >= cfg.train.steps:
            next_eval += args.eval_every
            m, p = heldout_psnr(t.model, t.ds, t.intr, sub, args.eval_fit_steps, 2048)
            point = {"train_seconds": round(train_s, 1), "step": t.step, "psnr": p}
            line = f"held-out PSNR ({len(sub)} val frames) {p:.2f} dB"
            if rean_sub:
                point["reanimate_psnr_face"] = reanimation_face_psnr(t.model, t.ds, t.intr,
                                                                     rean_sub)
                line += (f", re-animation face ({len(rean_sub)} frames) "
                         f"{point['reanimate_psnr_face']:.2f} dB")
            curve.append(point)
            log(f"  {train_s:6.0f} s  step {t.step:5d}  {line}")
    m, p = heldout_psnr(t.model, t.ds, t.intr, val, args.final_fit_steps, 4096)
    log(f"final: step {t.step}, {train_s:.0f} s, held-out PSNR on all {len(val)} val frames "
        f"{p:.2f} dB (MSE {m:.3e})")
    rean_final = reanimation_face_psnr(t.model, t.ds, t.intr, rean) if rean else None
    if rean:
        log(f"final: re-animation face PSNR on all {len(rean)} reanimate frames "
            f"{rean_final:.2f} dB")

    def first(th, key="psnr"):
        return next((c["train_seconds"] for c in curve if c.get(key, -1.0) >= th), None)

    if args.keep_run is not None:  # for bench_render.py --run
        t.save()
        shutil.rmtree(args.keep_run, ignore_errors=True)
        shutil.move(str(run_dir / "run"), args.keep_run)
    shutil.rmtree(run_dir, ignore_errors=True)
    return {"preset": args.quality_preset, "set": args.set, "seed": args.seed, "batch_rays": cfg.train.batch_rays, "size": args.size, "budget_seconds": args.budget, "steps": t.step,
            "train_seconds": round(train_s, 1), "final_heldout_psnr": p, "final_heldout_mse": m,
            "val_frames": len(val), "final_fit_steps": args.final_fit_steps,
            "curve": curve, "curve_val_frames": len(sub), "curve_fit_steps": args.eval_fit_steps,
            "time_to_db": {f"{th:g}": first(th) for th in args.targets},
            "final_reanimate_psnr_face": rean_final, "reanimate_frames": len(rean),
            "curve_reanimate_frames": len(rean_sub),
            "reanimate_time_to_db": ({f"{th:g}": first(th, "reanimate_psnr_face")
                                      for th in args.targets} if rean else None)}


def throughput(args, scene: Path, log) -> dict:
    from flamenerf.config import PRESETS, preset
    from flamenerf.data.rays import camera_rays
    from flamenerf.model.flame_nerf import RayBatch
    from flamenerf.training.trainer import Trainer

    res = {}
    for name in PRESETS:
        cfg = preset(name)
        cfg.train.image_every = 0
        run_dir = Path(tempfile.mkdtemp(prefix=f"bench_{name}_"))
        t = Trainer(cfg, scene, run_dir / "run", quiet=True)
        t.train_step()  # warm-up
        n = args.paper_steps if cfg.model.field.kind == "mlp" else args.fast_steps
        t0 = time.perf_counter()
        for _ in range(n):
            t.train_step()
        dt = (time.perf_counter() - t0) / n
        # render one 256x256 frame (or a fraction of its rays) with frame 0's codes
        intr = t.ds.intrinsics.scaled(256 / t.ds.intrinsics.w)
        fr = t.ds.split("train")[0]
        dev = t.device
        o, d = camera_rays(intr, fr.c2w, dev)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        k = int(len(o) * args.render_fraction)
        w, a = t.model.codes(torch.zeros(1, dtype=torch.long, device=dev))
        t.model.eval()
        e = torch.from_numpy(fr.expression).to(dev)
        sync()
        t0 = time.perf_counter()
        with torch.no_grad():
            for s in range(0, k, 8192):
                m = min(8192, k - s)
                t.model(RayBatch(o[s:s + m], d[s:s + m], w.expand(m, -1), a.expand(m, -1),
                                 e.expand(m, -1), torch.ones(m, dtype=torch.bool, device=dev)))
        sync()
        rt = (time.perf_counter() - t0) / args.render_fraction
        res[name] = {"batch_rays": cfg.train.batch_rays, "seconds_per_step": dt,
                     "rays_per_second": cfg.train.batch_rays / dt,
                     "render_256_seconds": rt, "render_fraction": args.render_fraction,
                     "steps_timed": n}
        log(f"{name:14s} {cfg.train.batch_rays / dt:9,.0f} rays/s  {dt:6.2f} s/step "
            f"(batch {cfg.train.batch_rays})  render 256x256: {rt:7.1f} s")
        shutil.rmtree(run_dir, ignore_errors=True)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=Path("scenes/s128"))
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--budget", type=float, default=600.0)
    ap.add_argument("--eval-every", type=float, default=100.0)
    ap.add_argument("--eval-frames", type=int, default=6)
    ap.add_argument("--eval-fit-steps", type=int, default=60)
    ap.add_argument("--final-fit-steps", type=int, default=200)
    ap.add_argument("--fast-steps", type=int, default=10)
    ap.add_argument("--paper-steps", type=int, default=2)
    ap.add_argument("--render-fraction", type=float, default=0.25)
    ap.add_argument("--quality-preset", default="fast",
                    help="preset of the quality run (the CPU target is `fast`'s)")
    ap.add_argument("--steps", type=int, default=0,
                    help="override the quality run's schedule length (0: the preset's)")
    ap.add_argument("--targets", type=lambda s: [float(v) for v in s.split(",")],
                    default=[25.0, 28.0, 30.0], help="PSNRs whose time-to is reported")
    ap.add_argument("--seed", type=int, default=0, help="the quality run's training seed")
    ap.add_argument("--batch-rays", type=int, default=0,
                    help="override the quality run's rays per step (0: the preset's)")
    ap.add_argument("--set", default="",
                    help="the quality run's configuration changes, `key=value,...` (e.g. "
                         "model.warp.still_head_only=true): a variant timed as the preset is")
    ap.add_argument("--keep-run", type=Path, default=None,
                    help="keep the quality run (checkpoint at its last step) in this folder")
    ap.add_argument("--skip-quality", action="store_true")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument("--json", type=Path, default=Path("docs/bench/train.json"))
    args = ap.parse_args()
    from flamenerf.runtime import reexec_with_tuned_allocator

    reexec_with_tuned_allocator([str(Path(__file__).resolve()), *sys.argv[1:]])

    if not (args.scene / "transforms.json").exists():
        from flamenerf.synthetic.scene import make_scene

        print(f"making the built-in scene in {args.scene} ({args.size}x{args.size}, 300 frames)")
        make_scene(args.scene, size=args.size, frames=300)
    out = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                       "torch": torch.__version__, "threads": torch.get_num_threads(),
                       "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available()
                       else None, "python": sys.version.split()[0]},
           "scene": str(args.scene)}
    if not args.skip_throughput:
        out["throughput"] = throughput(args, args.scene, print)
    if not args.skip_quality:
        out[f"quality_{args.quality_preset}"] = quality_run(args, args.scene, print)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    os.replace(tmp, args.json)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
