"""The preprocessing pipeline: portrait video -> flamenerf dataset (+ QA folder).

    decode (rotation honoured) -> select frames -> FaceLandmarker per frame (IMAGE mode)
    -> joint camera solve (focal, poses, template; robust, smooth) -> drop misfits
    -> cameras from the background (COLMAP, person masked) + head poses from the face
    -> [FLAME fit] -> one stable square crop -> resize -> silhouettes -> dataset + QA

Everything is written through `DatasetWriter` (a temp dir renamed into place), the QA files
included, so a failure at any point leaves nothing behind. See docs/preprocessing.md.
Tracking and the solve are `flamenerf.tracking.clip`'s; the report and QA figures
`flamenerf.tracking.report`'s.
"""

from __future__ import annotations

# imported to build `flamenerf --help` (PreprocessOptions): the tracking stack's steps are
# imported inside the functions that run them

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

import flamenerf
from flamenerf.data.dataset_checks import DatasetError, MAX_METRES
from flamenerf.data.dataset_writer import DatasetWriter, MAX_SIZE
from flamenerf.errors import UserError
from flamenerf.io import jsonable, write_json
from flamenerf.tracking.clip import (MAX_ERROR, progress_bar, require_enough, solve_scene,
                                     track_clip)
from flamenerf.data.video import VideoWriter, iter_frames
from flamenerf.outdir import check_replaceable, writable_dir


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
        cameras: scene: cameras from the static background (COLMAP, the person masked
            out) and the head's rigid pose per frame from the face; falls back to head
            when the background cannot be registered. head: the head is the world (every
            head turn becomes a camera motion; the paper's still-head capture).
        landmarker: face_landmarker.task to use (default: $FLAMENERF_LANDMARKER, then the
            copy installed by scripts/get_landmarker.py).
        face_model: mediapipe: MediaPipe face mesh + ARKit blendshapes; flame: fit
            FLAME (needs --flame-dir) and use its expression vector and mesh.
        flame_dir: Folder with FLAME's generic_model.pkl (or flame2020/2023 pkl) and a
            landmark embedding (mediapipe_landmark_embedding.npz). Only load files you
            trust: .pkl files can run code (see docs/preprocessing.md).
        flame_expr_dim: Number of FLAME expression coefficients to fit and store (β also
            holds the 3 jaw-pose angles after them).
        min_tracked: Fail unless at least this fraction of the selected frames is tracked.
        face: Whose face to follow where several are in view: the largest of the first
            frame with a face, or the leftmost or rightmost there (then the same person
            from frame to frame).
        max_error: Drop frames whose median reprojection error exceeds this fraction of
            the face size (and 3x the clip's median).
        verbose: Let the native libraries' own log lines (COLMAP, MediaPipe, glog)
            through to the terminal; without it their failures are said in one line of
            flamenerf's.
        qa: Write OUT/qa's overlay video, contact sheet and plots (the report,
            qa/tracking_report.json, is always written).
        consistent_expressions: Also fit the β -> mesh model so that each control commanded
            alone reads back through the tracker as that control, and store it with the
            dataset (expression_model.npz, which training then uses; MediaPipe meshes
            only; 1-3 min on 2 CPU cores). It raises what the mesh itself can show, not yet what
            a trained model shows (docs/results.md, "Controls"), so it is off.
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
    cameras: Literal["scene", "head"] = "scene"
    landmarker: Path | None = None
    face_model: Literal["mediapipe", "flame"] = "mediapipe"
    flame_dir: Path | None = None
    flame_expr_dim: int = 50
    min_tracked: float = 0.5
    face: Literal["largest", "left", "right"] = "largest"
    max_error: float = MAX_ERROR
    verbose: bool = False
    qa: bool = True
    consistent_expressions: bool = False
    overwrite: bool = False
    progress: Annotated[bool, tyro.conf.Suppress] = True



@dataclass
class FaceFit:
    """The expression vectors and the face geometry that makes the silhouettes."""

    expressions: np.ndarray  # (N, E)
    names: list[str]
    kind: str  # "arkit" or "flame"
    vertices: np.ndarray  # (N, V, 3) world
    faces: np.ndarray  # (F, 3)
    info: dict[str, Any]  # the dataset's expression_model entry


def preprocess_video(video: str | os.PathLike, out: str | os.PathLike,
                     opts: PreprocessOptions) -> dict:
    """Run the whole pipeline; returns the tracking report (also written to qa/)."""
    from flamenerf.tracking.crop import face_boxes, stable_square_crop
    from flamenerf.tracking.landmarker import find_model, load_canonical_mesh

    t_start = time.perf_counter()
    video, out = Path(video), Path(out)
    check_options(opts)
    if out.exists() and not opts.overwrite:
        raise DatasetError(f"{out}: already exists (pass --overwrite to replace it)")

    check_replaceable(out, "dataset")  # before the slow part, as DatasetWriter checks again
    writable_dir(out.parent, "dataset")
    flame = None
    if opts.face_model == "flame":
        from flamenerf.tracking.flame import load_flame_dir

        flame = load_flame_dir(opts.flame_dir)  # validate before the slow part
    model = find_model(opts.landmarker)
    mesh = load_canonical_mesh(model)

    clip = track_clip(video, opts.fps, opts.max_frames, model, opts.progress, opts.face)
    n_tracked = len(clip.frames)
    require_enough(clip, opts.min_tracked)
    t_track = time.perf_counter()
    clip, sol, scene = solve_scene(clip, mesh, opts.fov, opts.max_error, opts.min_tracked,
                                   background=opts.cameras == "scene", progress=opts.progress)
    t_solve = time.perf_counter()
    face = fit_face(clip, sol, mesh, flame, opts.flame_expr_dim)
    # from here on the solve's world is the scene's: cameras and posed face meshes
    sol, face = in_scene(sol, face, scene.world)
    t_fit = time.perf_counter()

    crop, crop_facts = stable_square_crop(face_boxes(clip.landmarks[:, :468]),
                                          clip.info.width, clip.info.height, opts.size,
                                          opts.crop_scale)
    intr = crop.intrinsics(sol.focal, sol.cx, sol.cy)
    near, far, cam_dist = scene_bounds(sol, face.vertices, opts, scene.world.head_pose)
    splits = assign_splits(len(clip.frames), opts.val_every)
    t = {"start": t_start, "track": t_track, "solve": t_solve, "fit": t_fit}
    report = write_dataset(video, out, opts, clip, sol, scene, face, crop, crop_facts, intr,
                           near, far, cam_dist, splits, n_tracked, t)
    if opts.consistent_expressions:
        from flamenerf.tracking.expression_model import add_to_dataset

        report["mesh_model"] = add_to_dataset(out, opts.progress)
    return report


def check_options(o: PreprocessOptions) -> None:
    if not 16 <= o.size <= MAX_SIZE:
        raise UserError(f"--size must be from 16 to {MAX_SIZE}, got {o.size}")
    for name, v in (("--near", o.near), ("--far", o.far)):
        if v is not None and not 0 <= v <= MAX_METRES:
            raise UserError(f"{name} {v}: must be from 0 to {MAX_METRES:g} (metres)")
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


def fit_face(clip, sol, mesh, flame, flame_expr_dim: int) -> FaceFit:
    """FLAME fitted to the landmarks (with `flame`), else MediaPipe's blendshape scores and
    the solve's per-frame face mesh."""
    from flamenerf.tracking.landmarker import SHA256

    if flame is not None:
        from flamenerf.tracking.flame import fit_flame

        fit = fit_flame(flame, clip, sol, num_expr=flame_expr_dim)
        return FaceFit(fit.expressions, fit.names, "flame", fit.vertices, flame.faces,
                       {"source": "FLAME fit to MediaPipe landmarks", "model": fit.model_info,
                        "shape": fit.shape.tolist(), "fit_error_px": fit.median_error_px})
    from flamenerf.tracking.irises import with_irises

    # the irises as vertices too (478), so that a gaze moves the mesh
    return FaceFit(clip.blendshapes, clip.names, "arkit",
                   with_irises(sol.vertices, clip.landmarks, mesh.faces), mesh.faces,
                   {"source": "MediaPipe FaceLandmarker blendshape scores (ARKit names)",
                    "range": [0.0, 1.0], "model_sha256": SHA256})


def in_scene(sol, face: FaceFit, world) -> tuple[Any, FaceFit]:
    """The solve and the face fit moved from the head's frame into the scene's world: the
    scene's cameras, and every frame's mesh posed by its head pose."""
    from dataclasses import replace

    if world.head_pose is None:  # the head is the world
        return replace(sol, c2w=world.c2w, w2c=np.linalg.inv(world.c2w)), face
    R, t = world.head_pose[:, None, :3, :3], world.head_pose[:, None, :3, 3]
    pose = lambda v: (R @ v[..., None])[..., 0] + t  # noqa: E731
    return (replace(sol, c2w=world.c2w, w2c=np.linalg.inv(world.c2w),
                    vertices=pose(sol.vertices)),
            replace(face, vertices=pose(face.vertices)))


def scene_bounds(sol, vertices: np.ndarray, opts: PreprocessOptions,
                 head_pose: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
    """near / far from the geometry (z-depth of the face mesh (N, V, 3), world, in every
    camera), unless given. -> near, far, camera distances from the head's origin (N,)
    (head_pose (N, 4, 4) world-from-head; None: the world's origin)"""
    w2c = sol.w2c
    depth = -(np.einsum("nab,nvb->nva", w2c[:, :3, :3], vertices)
              + w2c[:, None, :3, 3])[..., 2]
    head = 0.0 if head_pose is None else head_pose[:, :3, 3]
    cam_dist = np.linalg.norm(sol.c2w[:, :3, 3] - head, axis=1)
    near = opts.near if opts.near is not None else 0.5 * float(depth.min())
    far = opts.far if opts.far is not None else opts.far_scale * float(cam_dist.max())
    if not 0 <= near < far <= MAX_METRES:  # the bounds datasets are read with
        raise UserError(f"need 0 <= near < far <= {MAX_METRES:g} (metres), got "
                        f"near={near:.3f}, far={far:.3f}")
    return near, far, cam_dist


def assign_splits(n: int, val_every: int) -> list[str]:
    """Every val_every'th frame is "val" (none for val_every <= 1), the rest "train"."""
    return ["val" if (k % val_every == val_every - 1) else "train"
            for k in range(n)] if val_every > 1 else ["train"] * n


def moving_masks(reg, crop):
    """The background registration's masks of what moves by itself, cut like the frames:
    -> a function of the source frame's id giving (out, out) bool, or None without masks
    (the background was not registered, or was too plain to look, or nothing in it moved:
    the dataset is then as one made before such masks existed)."""
    if reg is None or getattr(reg, "moving", None) is None or not reg.moving.any():
        return None
    pos = {int(i): k for k, i in enumerate(reg.ids)}
    return lambda i: crop.mask(reg.moving[pos[int(i)]], reg.moving_scale)


def write_dataset(video: Path, out: Path, opts: PreprocessOptions, clip, sol, scene,
                  face: FaceFit, crop, crop_facts: dict, intr, near: float, far: float,
                  cam_dist: np.ndarray,
                  splits: list[str], n_tracked: int, t: dict[str, float]) -> dict:
    """Decode the kept frames again, crop them, rasterise their silhouettes and write the
    dataset with its QA folder (atomically). -> the tracking report"""
    from flamenerf.tracking import qa
    from flamenerf.tracking import report as R
    from flamenerf.data.prior import rasterize_silhouette

    info, N = clip.info, len(clip.frames)
    expressions, names, kind = face.expressions, face.names, face.kind
    verts_world, faces = face.vertices, face.faces
    head_pose = scene.world.head_pose
    lm_out = crop.points(clip.landmarks[..., :2])
    source = {
        "tool": "flamenerf preprocess", "version": flamenerf.__version__,
        # absolute: `render --split capture` takes the clip's sound from it
        "video": str(Path(video).resolve()), "video_frames": info.num_frames,
        "video_fps": info.fps,
        "video_size": [info.width, info.height], "rotation": info.rotation,
        "crop": crop.to_dict(), "focal_source_px": sol.focal, "face_model": opts.face_model,
        "options": jsonable(asdict(opts)),
    }
    writer = DatasetWriter(out, intr, near, far, names, kind, face.info, source,
                           overwrite=opts.overwrite, prior_dilation_px=opts.dilate)
    sheet_pos = set(np.round(np.linspace(0, N - 1, min(12, N))).astype(int).tolist())
    sheet_frames: list[np.ndarray] = []
    per_frame: list[dict] = []
    video_out = None
    try:
        if opts.qa:  # streamed, so long clips do not pile up overlay frames in memory
            (writer.tmp / "qa").mkdir(exist_ok=True)
            video_out = VideoWriter(writer.tmp / "qa" / "overlay.mp4", min(info.fps, 30.0),
                                    quality=7)

        seen = R.cameras_in_head(sol.c2w, head_pose)
        pos_of = {int(s): k for k, s in enumerate(clip.frames)}
        moving = moving_masks(scene.registration, crop)
        it = iter_frames(info, clip.frames)
        for i, rgb in progress_bar(it, N, "writing", opts.progress):
            k = pos_of[i]
            img = crop.apply(rgb)
            mask = rasterize_silhouette(verts_world[k], faces, intr, sol.c2w[k], opts.dilate)
            moves = None if moving is None else moving(i)
            writer.add_frame(
                img, mask, sol.c2w[k], expressions[k], frame_index=k, split=splits[k],
                verts=verts_world[k], head_pose=None if head_pose is None else head_pose[k],
                moving=moves,
                extra={"source_frame": i, "time": round(float(clip.times[k]), 6),
                       "reprojection_error_px": round(float(sol.rigid_error[k] * crop.scale),
                                                      4)})
            per_frame.append(R.frame_entry(k, i, clip, sol, crop, splits[k], mask,
                                           expressions[k], names))
            if opts.qa:
                label = f"{k:04d} src {i} {splits[k]} err {sol.rigid_error[k] * crop.scale:.2f}px"
                # head axes: the camera seen from the head
                shown = img if moves is None else qa.tint(img, moves, (40, 120, 255))
                ov = qa.overlay_frame(shown, mask, lm_out[k, :468], intr, seen[k], label)
                video_out.write(ov)
                if k in sheet_pos:
                    sheet_frames.append(ov)
        if len(per_frame) != N:
            raise UserError(f"{video}: decoding stopped early ({len(per_frame)} of {N} "
                            "frames) on the second pass")
        writer.set_faces(faces)
        axes = "MediaPipe canonical face axes: x left-of-subject, y up, z out of the face"
        writer.set_meta("scene", {
            "units": "metres", "case": scene.world.case,
            "world": f"head frame ({axes})" if head_pose is None else
                     f"the head's mean pose; cameras from the static background, the head's "
                     f"rigid pose per frame in head_pose ({axes})"})
        t_write = time.perf_counter()
        timings = {"track": t["track"] - t["start"],
                   "solve": t["solve"] - t["track"] - scene.seconds,
                   "background": scene.seconds,
                   "fit": t["fit"] - t["solve"], "write": t_write - t["fit"]}
        report = R.tracking_report(video, clip, sol, scene, intr, crop, crop_facts,
                                   n_tracked, cam_dist, near, far, kind, names, splits,
                                   per_frame, timings, expressions)
        if video_out is not None:
            video_out.close()
            R.write_qa(writer.tmp / "qa", report, sheet_frames, sol, scene, clip, splits,
                       expressions, names, kind)
        total = time.perf_counter() - t["start"]
        report["timings_s"]["total"] = total
        report["frames_per_second"] = len(clip.selected) / total
        (writer.tmp / "qa").mkdir(exist_ok=True)
        write_json(writer.tmp / "qa" / "tracking_report.json", report)
        writer.close()
    except BaseException:
        if video_out is not None:
            video_out.abort()
        writer.abort()
        raise
    return report
