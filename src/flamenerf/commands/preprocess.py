"""`flamenerf preprocess`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro


def preprocess(
    video: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="VIDEO")],
    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")],
    fps: float | None = None,
    max_frames: int | None = None,
    size: int = 256,
    crop_scale: float = 2.0,
    val_every: int = 8,
    dilate: int = 4,
    near: float | None = None,
    far: float | None = None,
    far_scale: float = 4.0,
    fov: float | None = None,
    landmarker: Path | None = None,
    face_model: Literal["mediapipe", "flame"] = "mediapipe",
    flame_dir: Path | None = None,
    flame_expr_dim: int = 50,
    min_tracked: float = 0.5,
    max_error: float = 0.03,
    qa: bool = True,
    overwrite: bool = False,
) -> None:
    """Turn a portrait video (head still, camera moving) into a flamenerf dataset.

    Decodes VIDEO (rotation metadata honoured), tracks the face in every selected frame
    with MediaPipe's FaceLandmarker (478 landmarks, head pose, 52 ARKit blendshape scores
    = the expression vector), solves one focal length and every camera pose jointly with a
    per-subject face template (world = the head's frame, metres), cuts one stable square
    crop around the face, resizes it, and rasterises the face mesh of each frame into the
    silhouette mask (the spatial prior). Frames without a face, or whose landmarks the
    solve cannot explain, are dropped and listed in OUT/qa/tracking_report.json, next to an
    overlay video and a camera-trajectory plot. Every --val-every'th frame goes to the val
    split. Needs the landmarker model once: python scripts/get_landmarker.py. See
    docs/preprocessing.md.

    Example: flamenerf preprocess selfie.mp4 data/me --fps 15 --max-frames 300

    Args:
        video: Input video (anything ffmpeg reads: mp4, mov, ...).
        out: Output dataset directory (written atomically).
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
    """
    from flamenerf.tracking.pipeline import PreprocessOptions, preprocess_video

    opts = PreprocessOptions(
        fps=fps, max_frames=max_frames, size=size, crop_scale=crop_scale,
        val_every=val_every, dilate=dilate, near=near, far=far, far_scale=far_scale, fov=fov,
        landmarker=landmarker, face_model=face_model, flame_dir=flame_dir,
        flame_expr_dim=flame_expr_dim, min_tracked=min_tracked, max_error=max_error, qa=qa,
        overwrite=overwrite)
    rep = preprocess_video(video, out, opts)
    err = rep["reprojection_error_px"]
    print(f"wrote {out}: {rep['kept_frames']} frames ({rep['splits']}), tracked "
          f"{rep['tracked_frames']}/{rep['selected_frames']} ({rep['tracked_percent']:.1f}%), "
          f"dropped {len(rep['dropped'])}; median reprojection error "
          f"{err['rigid_median_out']:.2f} px at {size}px ({err['rigid_median_source']:.2f} px "
          f"in the source); fov {rep['camera']['fov_x_deg']:.1f} deg; "
          f"{rep['frames_per_second']:.1f} frames/s")
    for d in rep["dropped"][:10]:
        print(f"  dropped frame {d['source_frame']} ({d['time']:.2f}s): {d['reason']}")
    if len(rep["dropped"]) > 10:
        print(f"  ... {len(rep['dropped']) - 10} more in {out}/qa/tracking_report.json")
