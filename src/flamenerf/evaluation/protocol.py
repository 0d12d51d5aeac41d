"""The evaluation protocol behind `flamenerf eval` (docs/evaluation.md).

Everything is measured at the run's training resolution (ground truth area-resized).

held-out (`val`)  the paper's protocol: freeze the model, fit only each frame's deformation
                  code ω (from ω_0, with φ_0; `fit_deformation_codes`), render, compare:
                  MSE, PSNR, SSIM, and PSNR inside / outside the face mask and on the
                  *scene* (outside a generous region around the person: `scene_masks`,
                  whether the static world registers apart from hair and body). All frames are
                  fitted together: each frame's ω gets `fit_steps` Adam updates from about
                  fit_batch_rays / N of its own rays each (stated in the results).
driven (`val`)    the same frames with nothing fitted: frame 0's codes and each frame's own
                  β (evaluation/control.py); whole / face / background / expressive region;
                  with `control` on ARKit-named controls, the renders and the frames
                  re-tracked (`retracked`: do the controls follow the frames' β?).
control           re-tracked response of the renders to commanded controls (control.py): on
                  the built-in scene's leakage sweep, against the same re-tracking of its
                  ground truth; elsewhere a sweep over each control's training range.
reanimate         the built-in scene only: frame 0's codes, the split's expressions, novel
                  cameras and masks, compared with the rendered ground truth.
novel_pose        the built-in scene with --head-motion only: as reanimate, with novel head
                  poses too (each frame's ground-truth pose as the head-pose control).
leakage           the built-in scene only: frame 0's camera and codes while the expression
                  sweeps one control at a time. Leakage = mean absolute per-pixel change
                  (0-255) outside the dilated union of the sweep's face masks, relative to
                  the sweep's first (neutral) frame, averaged over the other frames.
separation        the built-in scene only: on the same sweep (and `synth --entangled`'s
                  pairs split), the share of each control's true effect that the render
                  reproduces and how much of its change falls outside its own part of the
                  face (evaluation/separation.py).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import flamenerf
from flamenerf.data.dataset import Dataset
from flamenerf.data.scene import FrameSet
from flamenerf.evaluation import control as C
from flamenerf.evaluation import metrics as M
from flamenerf.evaluation.metrics import (SUMMARY_KEYS, beyond_head, image_metrics, scene_masks,
                                         summarize)
from flamenerf.evaluation.report import FORMAT, VERSION, eval_markdown
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.render_image import render_image
from flamenerf.data.companions import dataset_companions
from flamenerf.data.expression_range import training_range
from flamenerf.errors import UserError
from flamenerf.evaluation.heldout import fit_deformation_codes
from flamenerf.evaluation.separation import separation
from flamenerf.images import abs_diff, hstack, resize_to_height, vstack
from flamenerf.io import atomic_write_text, save_png, write_json
from flamenerf.rendering.expressions import from_video


METHOD_NAMES = {"masked": "FLAME-in-NeRF", "none": "Nerfies", "everywhere": "No prior"}
"""Method label of a run, from its model's `expression_mode`."""

DIFF_GAIN = 4.0
"""|diff| images are amplified this much."""


@dataclass
class EvalOptions:
    split: str = "val"
    fit_steps: int = 300
    fit_batch_rays: int = 1024
    fit_lr: float = 1e-2
    seed: int = 0
    control: bool = True
    """Measure the control response (re-tracks renders with MediaPipe's landmarker): the
    sweep, and the driven held-out renders against their frames' β."""
    control_steps: int = 5
    """Values per control in the control sweep (datasets without a leakage split)."""
    leakage_dilate_px: int = 3
    """Pixels (at the evaluation resolution) by which the union of the sweep's face masks is
    grown before measuring change outside it."""
    num_images: int = 3
    """Held-out and re-animation frames saved as GT | render | |diff| PNGs."""
    drive: str | None = None
    """A driving video: render its tracked expressions at the reference frame's camera,
    re-track the renders, report the correlation over time (`drive` section, drive.png)."""
    drive_frames: int = 40
    drive_match_range: bool = False
    """The drive's transfer with each control's reach matched (`render --match-range`)."""
    """Frames of the driving video used, spread over the clip."""
    chunk: int = 16384
    captured_directions: bool = True
    """Colour at new cameras as the nearest captured view saw it, as `render` and the
    viewer show it (data/captured_views.py); False: at the direction asked."""


# ------------------------------------------------------------------------- per image


def render_frames(model: FlameNeRF, fs: FrameSet, omega: torch.Tensor, phi: torch.Tensor,
                  chunk: int = 16384) -> list[np.ndarray]:
    """Render every frame of `fs` (its cameras, expressions and masks) with per-frame codes
    omega (N, D), phi (N, A). -> list of (H, W, 3) float32."""
    out = []
    for i in range(fs.n):
        r = render_image(model, fs.intr, fs.c2w[i], omega[i], phi[i], fs.expressions[i],
                         fs.masks[i], chunk=chunk, head=fs.head_of(i))
        out.append(r["rgb"].numpy())
    return out


HEAD_KEYS = ("psnr_face_on_head", "psnr_face_beyond_head", "face_error_beyond_head")


def _compare(fs: FrameSet, preds: list[np.ndarray], split_head: bool = False
             ) -> list[dict[str, Any]]:
    """Per-frame `image_metrics`; with `split_head` and ground-truth depth, also the face
    split at the head's silhouette (`HEAD_KEYS`: PSNR of the face's pixels on the head and
    beyond it, and the share of the face's squared error beyond it)."""
    rows = []
    scenes = scene_masks(fs)
    depths = fs.true_depths() if split_head else None
    for i, pred in enumerate(preds):
        fr = fs.frames[i]
        gt, face = fs.images[i].numpy(), fs.masks[i].numpy()
        row = {"position": fr.position, "frame_index": fr.frame_index}
        row.update(image_metrics(pred, gt, face, scenes[i]))
        if depths is not None:
            far = beyond_head(face, depths[i])
            err = ((pred - gt) ** 2).mean(-1)
            share = (float(err[far].sum() / max(err[face].sum(), 1e-12)) if face.any()
                     else float("nan"))  # NaN: the frame is left out of the mean
            row.update(psnr_face_on_head=M.psnr(pred, gt, face & ~far),
                       psnr_face_beyond_head=M.psnr(pred, gt, far),
                       face_error_beyond_head=share)
        rows.append(row)
    return rows


# ------------------------------------------------------------------------- sections


def heldout(model: FlameNeRF, fs: FrameSet, opts: EvalOptions, quiet: bool = True
            ) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The paper's protocol on frames `fs` -> (summary with per-frame rows, renders)."""
    t0 = time.perf_counter()
    omega, phi = fit_deformation_codes(model, fs, steps=opts.fit_steps,
                                       batch_rays=opts.fit_batch_rays, lr=opts.fit_lr,
                                       seed=opts.seed, quiet=quiet)
    t1 = time.perf_counter()
    preds = render_frames(model, fs, omega, phi, opts.chunk)
    rows = _compare(fs, preds)
    res = summarize(rows)
    res.update(fit_seconds=t1 - t0, render_seconds=time.perf_counter() - t1, frames=rows)
    return res, preds


def reanimation(model: FlameNeRF, fs: FrameSet, omega0: torch.Tensor, phi0: torch.Tensor,
                chunk: int = 16384) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Frame 0's codes with each frame's expression, camera and mask, against ground truth."""
    t0 = time.perf_counter()
    preds = render_frames(model, fs, omega0.expand(fs.n, -1), phi0.expand(fs.n, -1), chunk)
    rows = _compare(fs, preds, split_head=True)
    keys = SUMMARY_KEYS + (HEAD_KEYS if "psnr_face_on_head" in rows[0] else ())
    res = summarize(rows, keys)
    res.update(render_seconds=time.perf_counter() - t0, frames=rows)
    return res, preds


def leakage_region(masks: np.ndarray, dilate_px: int) -> np.ndarray:
    """Pixels where leakage is measured: outside the union of the masks (N, H, W), grown
    by `dilate_px`. -> (H, W) bool."""
    from scipy import ndimage

    union = np.asarray(masks, bool).any(0)
    if dilate_px > 0:
        union = ndimage.binary_dilation(union, iterations=int(dilate_px))
    return ~union


def leakage(model: FlameNeRF, fs: FrameSet, omega0: torch.Tensor, phi0: torch.Tensor,
            dilate_px: int = 3, chunk: int = 16384
            ) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Background change across an expression sweep at a fixed camera (see module doc).
    Frame 0 of `fs` is the reference (neutral) frame. -> (summary, renders)."""
    t0 = time.perf_counter()
    preds = render_frames(model, fs, omega0.expand(fs.n, -1), phi0.expand(fs.n, -1), chunk)
    masks = fs.masks.numpy()
    outside = leakage_region(masks, dilate_px)
    inside = masks.any(0)
    gt = fs.images.numpy()
    rows = []
    for i in range(1, fs.n):
        fr = fs.frames[i]
        rows.append({
            "position": fr.position,
            "control": fr.extra.get("leakage_control"),
            "value": fr.extra.get("leakage_value"),
            "background_change": M.mean_abs_change(preds[i], preds[0], outside),
            "face_change": M.mean_abs_change(preds[i], preds[0], inside),
            "gt_background_change": M.mean_abs_change(gt[i], gt[0], outside),
        })

    def mean(key, sel=rows):
        v = np.array([r[key] for r in sel], np.float64)
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else float("nan")

    per_control: dict[str, float] = {}
    for r in rows:
        if r["control"] is not None:
            per_control.setdefault(r["control"], [])
            per_control[r["control"]].append(r["background_change"])
    res = {
        "num_frames": fs.n,
        "reference_position": fs.frames[0].position,
        "dilate_px": int(dilate_px),
        "background_fraction": float(outside.mean()),
        "mean": mean("background_change"),
        "max": float(max((r["background_change"] for r in rows), default=float("nan"))),
        "face_change": mean("face_change"),
        "gt_mean": mean("gt_background_change"),
        "per_control": {k: float(np.mean(v)) for k, v in per_control.items()},
        "render_seconds": time.perf_counter() - t0,
        "frames": rows,
    }
    return res, preds


# ------------------------------------------------------------------------- the whole run


def method_name(expression_mode: str) -> str:
    return METHOD_NAMES.get(expression_mode, expression_mode)


def evaluate_run(run, ds: Dataset, opts: EvalOptions, out_dir: Path | None = None,
                 quiet: bool = False, log=print) -> dict[str, Any]:
    """Every section that `ds` supports; writes metrics.json, metrics.md and PNGs to
    `out_dir` (atomic writes) when given. -> the results dict (the JSON's content)."""
    model = run.model
    run.attach(ds, opts.captured_directions)  # `ds` need not come from run.dataset
    intr = run.train_intrinsics(ds)
    t_start = time.perf_counter()
    res: dict[str, Any] = {
        "format": FORMAT, "version": VERSION,
        "flamenerf_version": flamenerf.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "run": str(Path(run.run_dir).resolve()),
        "method": method_name(run.config.model.expression_mode),
        "preset": run.config.preset,
        "expression_mode": run.config.model.expression_mode,
        "step": run.step,
        "view_directions": "captured" if model.captured is not None else "as asked",
        "dataset": str(Path(ds.root).resolve()),
        "resolution": [intr.w, intr.h],
        "device": str(run.device),
        "protocol": asdict(opts),
        "heldout": None, "driven": None, "reanimate": None, "novel_pose": None,
        "leakage": None, "separation": None, "control": None, "drive": None,
    }
    images: dict[str, np.ndarray] = {}
    frames = ds.split(opts.split)
    if not frames:
        raise UserError(f"{ds.root / 'transforms.json'}: split {opts.split!r} is empty")
    why = run.codes_error(ds, frames)
    if why is not None:
        raise UserError(f"--split {opts.split}: {why}")
    torch.manual_seed(opts.seed)
    log(f"held-out: fitting ω of {len(frames)} {opts.split} frames "
        f"({opts.fit_steps} steps x {opts.fit_batch_rays} rays) at {intr.w}x{intr.h}")
    fs = FrameSet(ds, frames, intr)
    res["heldout"], preds = heldout(model, fs, opts, quiet=quiet)
    res["heldout"]["split"] = opts.split
    res["heldout"]["budget"] = {
        "fitted_together": fs.n, "updates_per_frame": opts.fit_steps,
        "rays_per_frame_per_update": opts.fit_batch_rays / max(fs.n, 1),
        "note": "each frame's ω is its own parameter: every Adam step updates it from the "
                "batch's rays of that frame (about fit_batch_rays / N)"}
    for k in range(min(opts.num_images, fs.n)):
        images[f"{opts.split}_{k:02d}.png"] = _triptych(fs, k, preds[k])
    omega0, phi0 = run.frame_codes(0)

    log(f"driven: {fs.n} {opts.split} frames with their own β and frame 0's codes")
    res["driven"], preds = C.driven(model, ds, fs, omega0, phi0, opts.chunk)
    res["driven"]["split"] = opts.split
    for k in range(min(opts.num_images, fs.n)):
        images[f"driven_{k:02d}.png"] = _triptych(fs, k, preds[k])
    if opts.control and C.trackable_controls(run.expression_names):
        log(f"driven, re-tracked: {fs.n} renders and their frames")
        res["driven"]["retracked"] = driven_retracked(run, ds, fs, preds)
    leak_preds = None
    if ds.splits.get("reanimate"):
        fs = FrameSet(ds, ds.split("reanimate"), intr)
        log(f"re-animation: {fs.n} frames (novel expressions and cameras)")
        res["reanimate"], preds = reanimation(model, fs, omega0, phi0, opts.chunk)
        for k in range(min(opts.num_images, fs.n)):
            images[f"reanimate_{k:02d}.png"] = _triptych(fs, k, preds[k])
    if ds.splits.get("novel_pose"):
        fs = FrameSet(ds, ds.split("novel_pose"), intr)
        log(f"novel-pose re-animation: {fs.n} frames (novel head poses, cameras and "
            "expressions)")
        res["novel_pose"], preds = reanimation(model, fs, omega0, phi0, opts.chunk)
        for k in range(min(opts.num_images, fs.n)):
            images[f"novel_pose_{k:02d}.png"] = _triptych(fs, k, preds[k])
    if ds.splits.get("leakage") and len(ds.splits["leakage"]) >= 2:
        fs = FrameSet(ds, ds.split("leakage"), intr)
        log(f"leakage: {fs.n} frames (expression sweep, fixed camera)")
        res["leakage"], preds = leakage(model, fs, omega0, phi0, opts.leakage_dilate_px,
                                        opts.chunk)
        images["leakage.png"] = _sweep_figure(fs, preds, opts.leakage_dilate_px)
        leak_preds = (fs, preds)
        pairs = pair_preds = None
        if ds.splits.get("pairs"):
            pairs = FrameSet(ds, ds.split("pairs"), intr)
            log(f"pairs: {pairs.n} frames (two controls the capture never combined)")
            pair_preds = render_frames(model, pairs, omega0.expand(pairs.n, -1),
                                       phi0.expand(pairs.n, -1), opts.chunk)
        res["separation"] = separation(fs, preds, pairs, pair_preds)
    if opts.control:
        log("control response: re-tracking renders with the face landmarker")
        res["control"] = control_section(run, ds, intr, omega0, phi0, opts, leak_preds,
                                         images)
    if opts.drive is not None:
        log(f"drive: tracking {opts.drive}, rendering and re-tracking {opts.drive_frames} "
            "frames")
        res["drive"], images["drive.png"] = drive_section(run, ds, intr, omega0, phi0, opts)
    res["seconds"] = time.perf_counter() - t_start
    if out_dir is not None:
        write_results(Path(out_dir), res, images)
    return res


def driven_retracked(run, ds: Dataset, fs: FrameSet, preds: list[np.ndarray]
                     ) -> dict[str, Any]:
    """The driven renders and their frames re-tracked (control.driven_response)."""

    track = C.Retracker()
    try:
        return C.driven_response(preds, [im.numpy() for im in fs.images],
                                 fs.expressions.numpy(), run.expression_names,
                                 ds.expression_matrix(ds.split("train")), track)
    finally:
        track.close()


def control_section(run, ds: Dataset, intr, omega0, phi0, opts: EvalOptions,
                    leak_preds, images: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The control response (see module doc): the leakage sweep's renders against its ground
    truth when the dataset has one, else a sweep at the reference frame's camera (its
    picture, control.png, goes into `images`)."""

    names = run.expression_names
    train_e = ds.expression_matrix(ds.split("train"))
    track = C.Retracker()
    try:
        if leak_preds is not None:
            fs, preds = leak_preds
            return C.sweep_response(fs, preds, track)
        render, fr, mesh_of = C.reference_renderer(run.model, ds, intr, omega0, phi0)
        motion = C.landmark_motion(ds, mesh_of, intr, fr.c2w, track.read)
        renders: list[np.ndarray] = []

        def keep(beta):
            renders.append(render(beta))
            return renders[-1]

        res = C.control_response(keep, names, ds.expression_matrix([fr])[0], train_e, track,
                                 opts.control_steps, companions=dataset_companions(ds),
                                 motion=motion, generic=run.model.generic_controls)
        res["source"] = f"sweep over the training range at frame {fr.position}'s camera"
        if images is not None and res["controls"]:
            images["control.png"], res["figure_rows"] = _control_figure(res, renders)
        return res
    finally:
        track.close()


def _control_figure(res: dict[str, Any], renders: list[np.ndarray], rows: int = 6
                    ) -> tuple[np.ndarray, list[str]]:
    """The sweep's renders, one row per control (the `rows` with the largest gain), from the
    low end of its range to the high end; with its companions where it has some (what a
    keyframe renders). -> image, the rows' control names."""
    per, at, gain = {}, 0, {}
    for name, c in res["controls"].items():
        n = len(c["commanded"])
        both = "gain_with_companions" in c
        per[name] = renders[at + n * both:at + n * (1 + both)]
        at += n * (1 + both)
        g = c["gain_with_companions"] if both else c["gain"]
        gain[name] = g if np.isfinite(g) else -np.inf
    names = sorted(per, key=lambda n: -gain[n])[:rows]
    return vstack([hstack(per[n], gap=2) for n in names], gap=2), names


def drive_section(run, ds: Dataset, intr, omega0, phi0, opts: EvalOptions
                  ) -> tuple[dict[str, Any], np.ndarray]:
    """The drive correlation (see module doc) at the reference frame's camera, and a
    picture: six driving frames spread over the sequence, each over its render."""
    names = run.expression_names
    seq = from_video(Path(opts.drive), ds, names, max_frames=opts.drive_frames,
                     panel_height=intr.h, match_range=opts.drive_match_range)
    render = C.reference_renderer(run.model, ds, intr, omega0, phi0)[0]
    rendered, notes = seq.values, list(seq.notes)
    if ds.expression_names == names:  # as `render` does by default
        rng = training_range(ds, run.model.generic_controls)
        if over := rng.beyond(seq.values):
            rendered = rng.clamp(seq.values)
            notes.append("rendered " + rng.note(over, "as `render` does unless "
                                                 "--extrapolate"))
    track = C.Retracker()
    try:
        res, preds = C.drive_response(render, names, seq.values, track, rendered=rendered)
        res["geometry"] = C.geometry_response([seq.driving(i) for i in range(len(preds))],
                                              preds, track.detect)
        truth = C.ground_truth_renderer(ds, intr) if ds.expression_names == names else None
        if truth is not None:  # the built-in scene driven the same way: the figures' ceiling
            gt, _ = C.drive_response(truth, names, seq.values, track, rendered=rendered)
            res["ground_truth"] = {
                "controls": {n: {k: c[k] for k in ("gain", "correlation", "detected")}
                             for n, c in gt["controls"].items()},
                "mean_gain": gt["mean_gain"], "mean_correlation": gt["mean_correlation"]}
    finally:
        track.close()
    res["video"] = str(opts.drive)
    res["notes"] = notes
    pick = np.unique(np.linspace(0, len(preds) - 1, min(6, len(preds))).round().astype(int))
    return res, hstack([vstack([seq.driving(int(i)), preds[i]], gap=2) for i in pick], gap=4)


def _triptych(fs: FrameSet, k: int, pred: np.ndarray) -> np.ndarray:
    gt = fs.images[k].numpy()
    img = hstack([gt, pred, abs_diff(pred, gt, DIFF_GAIN)], gap=2)
    return resize_to_height(img, max(img.shape[0], 128))


SHOWCASE = ("jawOpen", "mouthSmileLeft", "browInnerUp", "eyeBlinkLeft", "mouthPucker",
            "cheekPuff", "mouthFrownRight", "eyeWideRight")
"""Controls shown first in sweep figures (visibly different parts of the face)."""


def pick_sweep_frames(fs: FrameSet, limit: int = 8) -> list[int]:
    """Frames of a leakage sweep to show: the reference, then controls at their largest
    value, `SHOWCASE` ones first (at most `limit` frames in all)."""
    best: dict[str, tuple[float, int]] = {}
    for i, fr in enumerate(fs.frames[1:], start=1):
        c, v = fr.extra.get("leakage_control"), fr.extra.get("leakage_value")
        if c is None or v is None:
            continue
        if c not in best or v > best[c][0]:
            best[c] = (v, i)
    order = [c for c in SHOWCASE if c in best] + [c for c in best if c not in SHOWCASE]
    picks = [best[c][1] for c in order] or list(range(1, fs.n))
    return [0] + picks[: limit - 1]


def _sweep_figure(fs: FrameSet, preds: list[np.ndarray], dilate_px: int) -> np.ndarray:
    """Row 1: renders across the sweep; row 2: |render - reference| x gain, with the region
    where leakage is not measured tinted blue."""
    idx = pick_sweep_frames(fs)
    outside = leakage_region(fs.masks.numpy(), dilate_px)
    diffs = []
    for i in idx:
        d = abs_diff(preds[i], preds[idx[0]], DIFF_GAIN)
        d[~outside] = d[~outside] * 0.5 + np.array([0.0, 0.0, 0.5])
        diffs.append(d)
    fig = vstack([hstack([preds[i] for i in idx], gap=2), hstack(diffs, gap=2)], gap=2)
    return resize_to_height(fig, max(fig.shape[0], 256))


def write_results(out_dir: Path, res: dict[str, Any], images: dict[str, np.ndarray]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, img in images.items():
        save_png(out_dir / "images" / name, img)
    res["images"] = sorted(f"images/{n}" for n in images)
    write_json(out_dir / "metrics.json", res)
    atomic_write_text(out_dir / "metrics.md", eval_markdown(res))
