"""The preprocessing pipeline: portrait video -> flamenerf dataset (+ QA folder).

    decode (rotation honoured) -> select frames -> FaceLandmarker per frame (IMAGE mode)
    -> joint camera solve (focal, poses, template; robust, smooth) -> drop misfits
    -> [FLAME fit] -> one stable square crop -> resize -> silhouettes -> dataset + QA

Everything is written through `DatasetWriter` (a temp dir renamed into place), the QA files
included, so a failure at any point leaves nothing behind. See docs/preprocessing.md.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from flamenerf.errors import UserError
from flamenerf.io import jsonable

GROUPS_ARKIT = {  # channels plotted in qa/expressions.png (groups are averaged)
    "jawOpen": ["jawOpen"],
    "smile (mouthSmileLeft+Right)/2": ["mouthSmileLeft", "mouthSmileRight"],
    "eyeBlinkLeft": ["eyeBlinkLeft"],
    "eyeBlinkRight": ["eyeBlinkRight"],
}


@dataclass
class PreprocessOptions:
    """Options of `flamenerf preprocess` (its flags, same names; the help text below is
    their --help).

    Attributes:
        fps: Keep about this many frames per second (default: every frame).
        max_frames: Keep at most this many frames, spread evenly over the clip.
        size: Output image width and height in pixels.
        crop_scale: Crop side as a multiple of the largest face box (hair, neck, some
            background); limited to the frame.
        val_every: Hold out every k-th kept frame as the val split (0: none).
        dilate: Grow the silhouette masks by this many output pixels.
        near: Near bound in metres (default: half the nearest face-mesh depth).
        far: Far bound in metres, i.e. how far the background reaches (default:
            far-scale x the largest camera-head distance).
        far_scale: See --far.
        fov: Fix the horizontal field of view in degrees instead of estimating it.
        landmarker: face_landmarker.task to use (default: $FLAMENERF_LANDMARKER, then the
            copy installed by scripts/get_landmarker.py).
        face_model: mediapipe: MediaPipe face mesh + ARKit blendshapes; flame: fit FLAME
            (needs --flame-dir) and use its expression vector and mesh.
        flame_dir: Folder with FLAME's generic_model.pkl (or flame2020/2023 pkl) and a
            landmark embedding (mediapipe_landmark_embedding.npz). Only load files you
            trust: .pkl files can run code (see docs/preprocessing.md).
        flame_expr_dim: Number of FLAME expression coefficients to fit and store (β also
            holds the 3 jaw-pose angles after them).
        min_tracked: Fail unless at least this fraction of the selected frames is tracked.
        max_error: Drop frames whose median reprojection error exceeds this fraction of
            the face size (and 3x the clip's median).
        qa: Write OUT/qa (overlay video, contact sheet, camera plot, report).
        overwrite: Replace OUT if it exists.
        progress: Show progress bars (not a flag: the command always does).
    """

    fps: float | None = None
    max_frames: int | None = None
    size: int = 256
    crop_scale: float = 2.0
    val_every: int = 8
    dilate: int = 4
    near: float | None = None
    far: float | None = None
    far_scale: float = 4.0
    fov: float | None = None
    landmarker: Path | None = None
    face_model: Literal["mediapipe", "flame"] = "mediapipe"
    flame_dir: Path | None = None
    flame_expr_dim: int = 50
    min_tracked: float = 0.5
    max_error: float = 0.03
    qa: bool = True
    overwrite: bool = False
    progress: Annotated[bool, tyro.conf.Suppress] = True


@dataclass
class TrackedClip:
    """Per-frame FaceLandmarker output for the selected frames of a video."""

    info: Any  # VideoInfo
    selected: np.ndarray  # (S,) source frame indices that were looked at
    frames: np.ndarray  # (T,) source frame indices where a face was found
    times: np.ndarray  # (T,) seconds
    landmarks: np.ndarray  # (T, 478, 3) source pixels
    blendshapes: np.ndarray  # (T, 52)
    transforms: np.ndarray  # (T, 4, 4)
    names: list[str]
    dropped: list[dict] = field(default_factory=list)  # {"source_frame", "time", "reason"}
    seconds: float = 0.0


def _progress(it, total: int, desc: str, enabled: bool):
    if not enabled:
        return it
    from tqdm import tqdm

    # disable=None: only on a terminal, so logs and captured stderr stay clean
    return tqdm(it, total=total, desc=desc, unit="frame", leave=False, dynamic_ncols=True,
                disable=None)


def track_clip(video: str | os.PathLike, fps: float | None = None,
               max_frames: int | None = None, landmarker: str | os.PathLike | None = None,
               progress: bool = True) -> TrackedClip:
    """Decode the selected frames and run FaceLandmarker on each (IMAGE mode)."""
    from flamenerf.data.video import iter_frames, probe_video, select_frames
    from flamenerf.tracking.landmarker import FaceLandmarker, blendshape_names, find_model

    model = find_model(landmarker)  # fail on a bad model path before decoding anything
    info = probe_video(video)
    sel = select_frames(info.num_frames, info.fps, fps, max_frames)
    t0 = time.perf_counter()
    frames, L, B, M, dropped = [], [], [], [], []
    seen = set()
    with FaceLandmarker(model) as lm:
        for i, rgb in _progress(iter_frames(info, sel), len(sel), "tracking", progress):
            seen.add(i)
            det = lm.detect(rgb)
            if det is None:
                dropped.append({"source_frame": i, "time": i / info.fps,
                                "reason": "no face detected"})
                continue
            frames.append(i)
            L.append(det.landmarks)
            B.append(det.blendshapes)
            M.append(det.transform)
        names = lm.names or blendshape_names()
    for i in sel:
        if int(i) not in seen:
            dropped.append({"source_frame": int(i), "time": int(i) / info.fps,
                            "reason": "frame could not be decoded"})
    fr = np.asarray(frames, np.int64)
    return TrackedClip(
        info=info, selected=sel, frames=fr, times=fr / info.fps,
        landmarks=np.asarray(L, np.float64).reshape(-1, 478, 3),
        blendshapes=np.asarray(B, np.float32).reshape(len(frames), len(names)),
        transforms=np.asarray(M, np.float64).reshape(-1, 4, 4), names=list(names),
        dropped=sorted(dropped, key=lambda d: d["source_frame"]),
        seconds=time.perf_counter() - t0,
    )


def require_enough(clip: TrackedClip, min_fraction: float, minimum: int = 2) -> None:
    """UserError when too few of the selected frames have a face."""
    n_sel, n_ok = len(clip.selected), len(clip.frames)
    path = clip.info.path
    if n_ok == 0:
        raise UserError(f"{path}: no face found in any of the {n_sel} selected frames")
    need = max(minimum, int(np.ceil(min_fraction * n_sel)))
    if n_ok < need:
        first = ", ".join(str(d["source_frame"]) for d in clip.dropped[:8])
        more = "..." if len(clip.dropped) > 8 else ""
        raise UserError(
            f"{path}: face tracked in only {n_ok} of {n_sel} selected frames (need at least "
            f"{need}; --min-tracked {min_fraction:g}); frames without a face: {first}{more}")


def _drop(clip: TrackedClip, keep: np.ndarray, reasons: dict[int, str]) -> TrackedClip:
    """A copy of `clip` without the frames where keep is False (reasons by position)."""
    dropped = clip.dropped + [
        {"source_frame": int(clip.frames[k]), "time": float(clip.times[k]), "reason": r}
        for k, r in reasons.items()]
    return TrackedClip(
        info=clip.info, selected=clip.selected, frames=clip.frames[keep],
        times=clip.times[keep], landmarks=clip.landmarks[keep],
        blendshapes=clip.blendshapes[keep], transforms=clip.transforms[keep],
        names=clip.names, dropped=sorted(dropped, key=lambda d: d["source_frame"]),
        seconds=clip.seconds)


def solve_clip(clip: TrackedClip, mesh, opts: PreprocessOptions):
    """Camera solve; frames whose rigid reprojection error exceeds max_error x face size
    (and 3x the median) are dropped, listed, and the solve is rerun without them."""
    from flamenerf.tracking.cameras import SolveConfig, solve_cameras

    cfg = SolveConfig(fov_deg=opts.fov)
    step = 1.0 / clip.info.fps

    def run(c: TrackedClip):
        return solve_cameras(c.landmarks, c.times, mesh.vertices, mesh.faces, mesh.weights,
                             c.info.width, c.info.height, c.transforms, cfg, step)

    res = run(clip)
    limit = max(opts.max_error * res.face_size, 3 * float(np.median(res.rigid_error)))
    bad = res.rigid_error > limit
    if bad.any():
        reasons = {int(k): f"camera-solve misfit: {res.rigid_error[k]:.1f} px > {limit:.1f} px"
                   for k in np.flatnonzero(bad)}
        clip = _drop(clip, ~bad, reasons)
        require_enough(clip, opts.min_tracked)
        res = run(clip)
    return clip, res


def preprocess_video(video: str | os.PathLike, out: str | os.PathLike,
                     opts: PreprocessOptions) -> dict:
    """Run the whole pipeline; returns the tracking report (also written to qa/)."""
    import flamenerf
    from flamenerf.data.dataset import DatasetError, DatasetWriter
    from flamenerf.data.video import iter_frames
    from flamenerf.tracking.crop import face_boxes, stable_square_crop
    from flamenerf.tracking.landmarker import SHA256, find_model, load_canonical_mesh
    from flamenerf.tracking.silhouette import rasterize_silhouette

    t_start = time.perf_counter()
    video, out = Path(video), Path(out)
    _check_options(opts)
    if out.exists() and not opts.overwrite:
        raise DatasetError(f"{out}: already exists (pass --overwrite to replace it)")
    flame = None
    if opts.face_model == "flame":
        from flamenerf.tracking.flame import load_flame_dir

        flame = load_flame_dir(opts.flame_dir)  # validate before the slow part
    model = find_model(opts.landmarker)
    mesh = load_canonical_mesh(model)

    clip = track_clip(video, opts.fps, opts.max_frames, model, opts.progress)
    n_tracked = len(clip.frames)
    require_enough(clip, opts.min_tracked)
    t_track = time.perf_counter()
    clip, sol = solve_clip(clip, mesh, opts)
    t_solve = time.perf_counter()
    info = clip.info
    N = len(clip.frames)

    # expressions and the face geometry that makes the silhouettes
    if flame is not None:
        from flamenerf.tracking.flame import fit_flame

        fit = fit_flame(flame, clip, sol, num_expr=opts.flame_expr_dim)
        expressions, names, kind = fit.expressions, fit.names, "flame"
        verts_world, faces = fit.vertices, flame.faces
        expr_info = {"source": "FLAME fit to MediaPipe landmarks", "model": fit.model_info,
                     "shape": fit.shape.tolist(), "fit_error_px": fit.median_error_px}
    else:
        expressions, names, kind = clip.blendshapes, clip.names, "arkit"
        verts_world, faces = sol.vertices, mesh.faces
        expr_info = {"source": "MediaPipe FaceLandmarker blendshape scores (ARKit names)",
                     "range": [0.0, 1.0], "model_sha256": SHA256}
    t_fit = time.perf_counter()

    crop, crop_facts = stable_square_crop(face_boxes(clip.landmarks[:, :468]), info.width,
                                          info.height, opts.size, opts.crop_scale)
    intr = crop.intrinsics(sol.focal, sol.cx, sol.cy)

    # near / far from the geometry (z-depth of the face mesh in every camera)
    w2c = sol.w2c
    depth = -(np.einsum("nab,nvb->nva", w2c[:, :3, :3], verts_world)
              + w2c[:, None, :3, 3])[..., 2]
    cam_dist = np.linalg.norm(sol.c2w[:, :3, 3], axis=1)
    near = opts.near if opts.near is not None else 0.5 * float(depth.min())
    far = opts.far if opts.far is not None else opts.far_scale * float(cam_dist.max())
    if not 0 <= near < far:
        raise UserError(f"need 0 <= near < far, got near={near:.3f}, far={far:.3f}")

    splits = ["val" if (k % opts.val_every == opts.val_every - 1) else "train"
              for k in range(N)] if opts.val_every > 1 else ["train"] * N
    lm_out = crop.points(clip.landmarks[..., :2])
    source = {
        "tool": "flamenerf preprocess", "version": flamenerf.__version__,
        "video": str(video), "video_frames": info.num_frames, "video_fps": info.fps,
        "video_size": [info.width, info.height], "rotation": info.rotation,
        "crop": crop.to_dict(), "focal_source_px": sol.focal, "face_model": opts.face_model,
        "options": jsonable(asdict(opts)),
    }
    writer = DatasetWriter(out, intr, near, far, names, kind, expr_info, source,
                           overwrite=opts.overwrite)
    sheet_pos = set(np.round(np.linspace(0, N - 1, min(12, N))).astype(int).tolist())
    sheet_frames: list[np.ndarray] = []
    per_frame: list[dict] = []
    video_out = None
    try:
        from flamenerf.data.video import VideoWriter
        from flamenerf.tracking import qa

        if opts.qa:  # streamed, so long clips do not pile up overlay frames in memory
            (writer.tmp / "qa").mkdir(exist_ok=True)
            video_out = VideoWriter(writer.tmp / "qa" / "overlay.mp4", min(info.fps, 30.0),
                                    quality=7)

        pos_of = {int(s): k for k, s in enumerate(clip.frames)}
        it = iter_frames(info, clip.frames)
        for i, rgb in _progress(it, N, "writing", opts.progress):
            k = pos_of[i]
            img = crop.apply(rgb)
            mask = rasterize_silhouette(verts_world[k], faces, intr, sol.c2w[k], opts.dilate)
            writer.add_frame(
                img, mask, sol.c2w[k], expressions[k], frame_index=k, split=splits[k],
                verts=verts_world[k],
                extra={"source_frame": i, "time": round(float(clip.times[k]), 6),
                       "reprojection_error_px": round(float(sol.rigid_error[k] * crop.scale),
                                                      4)})
            per_frame.append({
                "position": k, "source_frame": i, "time": float(clip.times[k]),
                "split": splits[k],
                "rigid_error_px_source": float(sol.rigid_error[k]),
                "rigid_error_px_out": float(sol.rigid_error[k] * crop.scale),
                "mesh_error_px_out": float(sol.mesh_error[k] * crop.scale),
                "camera_center": sol.c2w[k, :3, 3].round(5).tolist(),
                "mask_fraction": float(mask.mean()),
                "top_expressions": _top(expressions[k], names),
            })
            if opts.qa:
                label = f"{k:04d} src {i} {splits[k]} err {sol.rigid_error[k] * crop.scale:.2f}px"
                ov = qa.overlay_frame(img, mask, lm_out[k, :468], intr, sol.c2w[k], label)
                video_out.write(ov)
                if k in sheet_pos:
                    sheet_frames.append(ov)
        if len(per_frame) != N:
            raise UserError(f"{video}: decoding stopped early ({len(per_frame)} of {N} "
                            "frames) on the second pass")
        writer.set_faces(faces)
        writer.set_meta("scene", {"units": "metres", "world": "head frame (MediaPipe "
                                  "canonical face axes: x left-of-subject, y up, z out of "
                                  "the face)"})
        t_write = time.perf_counter()
        report = {
            "video": {"path": str(video), "width": info.width, "height": info.height,
                      "fps": info.fps, "frames": info.num_frames, "rotation": info.rotation,
                      "codec": info.codec},
            "selected_frames": int(len(clip.selected)),
            "tracked_frames": n_tracked,
            "kept_frames": N,
            "tracked_percent": 100.0 * n_tracked / max(1, len(clip.selected)),
            "kept_percent": 100.0 * N / max(1, len(clip.selected)),
            "dropped": clip.dropped,
            "camera": {
                "focal_px_source": sol.focal, "fov_x_deg": _fov(sol.focal, info.width),
                "fov_y_deg": _fov(sol.focal, info.height),
                "focal_scan": sol.history.get("focal_scan"),
                "intrinsics_out": asdict(intr),
                "camera_distance_m": [float(cam_dist.min()), float(cam_dist.max())],
                "azimuth_range_deg": _azimuth_range(sol.c2w),
            },
            "crop": {**crop.to_dict(), **crop_facts},
            "reprojection_error_px": {
                "what": "median over landmarks of |projection - landmark|, per frame; "
                        "rigid = shared template + camera, mesh = per-frame face mesh",
                "rigid_median_source": float(np.median(sol.rigid_error)),
                "rigid_median_out": float(np.median(sol.rigid_error) * crop.scale),
                "rigid_p95_out": float(np.percentile(sol.rigid_error, 95) * crop.scale),
                "mesh_median_out": float(np.median(sol.mesh_error) * crop.scale),
            },
            "near": near, "far": far,
            "expression_model": {"kind": kind, "dim": len(names)},
            "splits": {s: splits.count(s) for s in sorted(set(splits))},
            "timings_s": {"track": t_track - t_start, "solve": t_solve - t_track,
                          "fit": t_fit - t_solve, "write": t_write - t_fit},
            "frames": per_frame,
        }
        if video_out is not None:
            video_out.close()
            _write_qa(writer.tmp / "qa", report, sheet_frames, sol, clip, splits,
                      expressions, names, kind)
        total = time.perf_counter() - t_start
        report["timings_s"]["total"] = total
        report["frames_per_second"] = len(clip.selected) / total
        (writer.tmp / "qa").mkdir(exist_ok=True)
        (writer.tmp / "qa" / "tracking_report.json").write_text(json.dumps(
            jsonable(report), indent=1))
        writer.close()
    except BaseException:
        if video_out is not None:
            video_out.abort()
        writer.abort()
        raise
    return report


def _write_qa(qa_dir: Path, report: dict, sheet_frames: list[np.ndarray], sol, clip, splits,
              expressions, names, kind) -> None:
    import imageio.v3 as iio

    from flamenerf.tracking import qa

    qa_dir.mkdir(exist_ok=True)
    iio.imwrite(qa_dir / "contact_sheet.png", qa.contact_sheet(sheet_frames, cols=4))
    rep = report["reprojection_error_px"]
    qa.plot_cameras(qa_dir / "cameras.png", sol.c2w, sol.template, clip.times, splits,
                    title=f"{len(sol.c2w)} cameras, focal {sol.focal:.0f} px (source), "
                          f"median reprojection error {rep['rigid_median_out']:.2f} px "
                          f"(output)")
    if kind == "arkit":
        qa.plot_expression_traces(qa_dir / "expressions.png", clip.times, expressions, names,
                                  GROUPS_ARKIT, title="expression trace")


def _check_options(o: PreprocessOptions) -> None:
    if o.size < 16:
        raise UserError(f"--size must be at least 16, got {o.size}")
    if o.crop_scale <= 0:
        raise UserError(f"--crop-scale must be positive, got {o.crop_scale}")
    if o.val_every < 0 or o.val_every == 1:
        raise UserError(f"--val-every must be 0 (no val split) or >= 2, got {o.val_every}")
    if o.dilate < 0:
        raise UserError(f"--dilate must be >= 0, got {o.dilate}")
    if not 0 <= o.min_tracked <= 1:
        raise UserError(f"--min-tracked is a fraction in [0, 1], got {o.min_tracked}")
    if o.fov is not None and not 1 < o.fov < 170:
        raise UserError(f"--fov is a horizontal field of view in degrees, got {o.fov}")
    if o.face_model == "flame" and o.flame_dir is None:
        raise UserError("--face-model flame needs --flame-dir DIR (FLAME's model files)")


def _fov(f: float, extent: float) -> float:
    return float(np.degrees(2 * np.arctan(0.5 * extent / f)))


def _azimuth_range(c2w: np.ndarray) -> list[float]:
    C = c2w[:, :3, 3]
    az = np.degrees(np.arctan2(C[:, 0], C[:, 2]))
    return [float(az.min()), float(az.max())]


def _top(vec: np.ndarray, names: list[str], k: int = 3) -> dict[str, float]:
    idx = np.argsort(-np.abs(vec))[:k]
    return {names[i]: round(float(vec[i]), 3) for i in idx}


def track_expressions(video: str | os.PathLike, fps: float | None = None,
                      max_frames: int | None = None, landmarker: str | os.PathLike | None = None,
                      face_model: Literal["mediapipe", "flame"] = "mediapipe",
                      flame_dir: str | os.PathLike | None = None, flame_expr_dim: int = 50,
                      min_tracked: float = 0.5, progress: bool = True):
    """Per-frame expression vectors of a (driving) video -> ExpressionTrack."""
    import flamenerf
    from flamenerf.tracking.expressions import ExpressionTrack

    flame = None
    if face_model == "flame":
        from flamenerf.tracking.flame import load_flame_dir

        flame = load_flame_dir(flame_dir)
    clip = track_clip(video, fps, max_frames, landmarker, progress)
    require_enough(clip, min_tracked, minimum=1)
    if flame is not None:
        from flamenerf.tracking.flame import fit_flame
        from flamenerf.tracking.landmarker import find_model, load_canonical_mesh

        if len(clip.frames) < 2:
            raise UserError(f"{video}: the FLAME fit needs at least 2 tracked frames")
        mesh = load_canonical_mesh(find_model(landmarker))
        opts = PreprocessOptions(min_tracked=min_tracked)
        clip, sol = solve_clip(clip, mesh, opts)
        fit = fit_flame(flame, clip, sol, num_expr=flame_expr_dim)
        frames, names, kind = fit.expressions, fit.names, "flame"
    else:
        frames, names, kind = clip.blendshapes, clip.names, "arkit"
    rate = clip.info.fps
    if len(clip.selected) > 1:  # the rate of the selected frames
        rate = clip.info.fps / float(np.median(np.diff(clip.selected)))
    return ExpressionTrack(
        names=list(names), frames=np.asarray(frames, np.float32), fps=float(rate), kind=kind,
        source_frames=[int(i) for i in clip.frames],
        times=[round(float(t), 6) for t in clip.times], dropped=clip.dropped,
        source={"video": str(video), "tool": "flamenerf track",
                "version": flamenerf.__version__, "video_fps": clip.info.fps,
                "selected_frames": int(len(clip.selected))})
