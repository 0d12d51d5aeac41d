"""The driving-video tracker behind `flamenerf track` and `render --drive`: per-frame
expression vectors of a video (ARKit blendshape scores, or a FLAME fit)."""

from __future__ import annotations

import os
from typing import Literal

import numpy as np

import flamenerf
from flamenerf.errors import UserError
from flamenerf.tracking.clip import require_enough, solve_clip, track_clip
from flamenerf.geometry import head_euler
from flamenerf.tracking.crop import face_boxes
from flamenerf.tracking.expressions import ExpressionTrack
from flamenerf.tracking.flame import fit_flame, load_flame_dir
from flamenerf.tracking.landmarker import find_model, load_canonical_mesh


def track_expressions(video: str | os.PathLike, fps: float | None = None,
                      max_frames: int | None = None, landmarker: str | os.PathLike | None = None,
                      face_model: Literal["mediapipe", "flame"] = "mediapipe",
                      flame_dir: str | os.PathLike | None = None, flame_expr_dim: int = 50,
                      min_tracked: float = 0.5, progress: bool = True,
                      face: str = "largest"):
    """Per-frame expression vectors of a (driving) video -> ExpressionTrack."""
    flame = None
    if face_model == "flame":
        flame = load_flame_dir(flame_dir)
    clip = track_clip(video, fps, max_frames, landmarker, progress, face)
    require_enough(clip, min_tracked, minimum=1)
    if flame is not None:
        if len(clip.frames) < 2:
            raise UserError(f"{video}: the FLAME fit needs at least 2 tracked frames")
        mesh = load_canonical_mesh(find_model(landmarker))
        clip, sol = solve_clip(clip, mesh, fov=None, min_tracked=min_tracked)
        fit = fit_flame(flame, clip, sol, num_expr=flame_expr_dim)
        frames, names, kind = fit.expressions, fit.names, "flame"
    else:
        frames, names, kind = clip.blendshapes, clip.names, "arkit"
    rate = clip.info.fps
    head = relative_head_pose(clip.transforms)
    if len(clip.selected) > 1:  # the rate of the selected frames
        rate = clip.info.fps / float(np.median(np.diff(clip.selected)))
    return ExpressionTrack(
        names=list(names), frames=np.asarray(frames, np.float32), fps=float(rate), kind=kind,
        head_pose=head, face_box=face_boxes(clip.landmarks),
        source_frames=[int(i) for i in clip.frames],
        times=[round(float(t), 6) for t in clip.times], dropped=clip.dropped,
        source={"video": str(video), "tool": "flamenerf track",
                "version": flamenerf.__version__, "video_fps": clip.info.fps,
                "selected_frames": int(len(clip.selected)),
                # frames with other faces in view (the driver followed among them)
                "crowded_frames": list(clip.crowded)})


def relative_head_pose(transforms: np.ndarray) -> np.ndarray:
    """The landmarker's face poses in the camera (T, 4, 4) -> each frame's head rotation
    relative to the first, in the head's own axes (x: the subject's left, y: up, z: out of
    the face, as the canonical face model's), as rows (T, 6) of yaw, pitch, roll (degrees)
    and x, y, z = 0 (`render --head-pose drive`: turns, not the driver's distance to
    the camera)."""
    R = np.asarray(transforms, np.float64)[:, :3, :3]
    u, _, vt = np.linalg.svd(R)  # the landmarker's matrices carry a scale: keep the rotation
    R = u @ vt
    rel = np.einsum("ji,tjk->tik", R[0], R)  # R_0ᵀ R_t: the motion in frame 0's head axes
    out = np.zeros((len(R), 6), np.float32)
    out[:, :3] = head_euler(rel)
    return out
