"""Tracked clips: FaceLandmarker over the selected frames of a video, the check that enough
of them have a face, and the camera solve with misfit frames dropped. Shared by the
preprocessing pipeline and the driving-video tracker."""

from __future__ import annotations

# imported (through tracking/pipeline.py) to build `flamenerf --help`: the landmarker, the
# camera solve and the background are imported inside the functions that run them

import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flamenerf.errors import UserError
from flamenerf.data.video import iter_frames, probe_video, select_frames

MAX_ERROR = 0.03
"""Default misfit limit of the camera solve, as a fraction of the face size."""

MAX_FACES = 4
"""Faces looked for in each frame; the clip's person is followed among them (MediaPipe's
one most prominent face changes to whoever is more prominent in that frame: a bystander who
comes closer, or the person turning away)."""

FOLLOW_LIMIT = 1.0
"""Once more than one face has been in view, a face whose centre is further than this many
face sizes from where the followed face was last, or whose size differs from its size then
by more than a factor SIZE_LIMIT, is taken for someone else's."""

SIZE_LIMIT = 1.5


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
    crowded: list[int] = field(default_factory=list)
    """Source frames where faces other than the followed one were found."""
    shots: np.ndarray | None = None
    """(T,) int64: the shot of each frame (tracking/shots.py); None: one shot."""
    cuts: list[int] = field(default_factory=list)
    """Source frames that begin a new shot."""


def face_box(landmarks: np.ndarray) -> tuple[np.ndarray, float]:
    """landmarks (K, ≥2) pixels -> the centre (2,) and size (the larger side) of their box
    (`crop.face_boxes`)."""
    from flamenerf.tracking.crop import face_boxes

    box = face_boxes(np.asarray(landmarks, np.float64)[None])[0]
    return (box[:2] + box[2:]) / 2, float((box[2:] - box[:2]).max())


FACE_CHOICES = ("largest", "left", "right")
"""Whose face a clip follows from its first frame with a face (`--face`)."""
FACE_WORDS = {"largest": "largest", "left": "leftmost", "right": "rightmost"}


def crowded_note(crowded: list[int], face: str) -> str | None:
    """The line `preprocess` and `track` print where other faces were in view (source
    frames `crowded`; `face`: the --face followed), or None."""
    if not crowded:
        return None
    return (f"note: other faces were in view in {len(crowded)} of the selected frames (the "
            f"first: frame {crowded[0]}); the {FACE_WORDS[face]} face of the first frame "
            f"with a face was followed (--face)")


def choose_face(faces: list[np.ndarray], last: tuple[np.ndarray, float] | None,
                crowd: bool, first: str = "largest") -> int | None:
    """Which of a frame's faces (landmarks (K, ≥2) each) is the followed person's: without
    a previous face (`last`: its `face_box`), the one `first` names (FACE_CHOICES: the
    largest, or the leftmost or rightmost in the picture); else the one nearest to it,
    unless `crowd` (other faces have been in view) and it lies further than FOLLOW_LIMIT
    face sizes away or its size differs by more than SIZE_LIMIT (then None: the person is
    not in this frame)."""
    if not faces:
        return None
    boxes = [face_box(f) for f in faces]
    if last is None:
        if first == "left":
            return int(np.argmin([c[0] for c, _ in boxes]))
        if first == "right":
            return int(np.argmax([c[0] for c, _ in boxes]))
        return int(np.argmax([size for _, size in boxes]))
    dist = [np.linalg.norm(c - last[0]) / max(last[1], 1e-9) for c, _ in boxes]
    k = int(np.argmin(dist))
    ratio = boxes[k][1] / max(last[1], 1e-9)
    if crowd and (dist[k] > FOLLOW_LIMIT or not 1 / SIZE_LIMIT <= ratio <= SIZE_LIMIT):
        return None
    return k


def progress_bar(it, total: int, desc: str, enabled: bool):
    if not enabled:
        return it
    from tqdm import tqdm

    # disable=None: only on a terminal, so logs and captured stderr stay clean
    return tqdm(it, total=total, desc=desc, unit="frame", leave=False, dynamic_ncols=True,
                disable=None)


def track_clip(video: str | os.PathLike, fps: float | None = None,
               max_frames: int | None = None, landmarker: str | os.PathLike | None = None,
               progress: bool = True, face: str = "largest") -> TrackedClip:
    """Decode the selected frames and run FaceLandmarker on each (IMAGE mode), following
    one person among other faces (`choose_face`; `face`: whose, FACE_CHOICES)."""
    if face not in FACE_CHOICES:
        raise UserError(f"--face {face}: one of {', '.join(FACE_CHOICES)}")
    from flamenerf.tracking.landmarker import FaceLandmarker, blendshape_names, find_model
    from flamenerf.tracking.shots import shot_indices, thumbnail

    model = find_model(landmarker)  # fail on a bad model path before decoding anything
    info = probe_video(video)
    sel = select_frames(info.num_frames, info.fps, fps, max_frames, info.times)
    t0 = time.perf_counter()
    frames, L, B, M, dropped, crowded = [], [], [], [], [], []
    seen, last, decoded, thumbs = set(), None, [], []
    with FaceLandmarker(model, num_faces=MAX_FACES) as lm:
        for i, rgb in progress_bar(iter_frames(info, sel), len(sel), "tracking", progress):
            seen.add(i)
            decoded.append(int(i))
            thumbs.append(thumbnail(rgb))
            found = lm.detect_all(rgb)
            if len(found) > 1:
                crowded.append(int(i))
            k = choose_face([d.landmarks for d in found], last, bool(crowded), face)
            if k is None:
                dropped.append({"source_frame": i, "time": float(info.frame_time(i)),
                                "reason": ("no face detected" if not found else
                                           "only faces other than the followed one")})
                continue
            det = found[k]
            last = face_box(det.landmarks)
            frames.append(i)
            L.append(det.landmarks)
            B.append(det.blendshapes)
            M.append(det.transform)
        names = lm.names or blendshape_names()
    for i in sel:
        if int(i) not in seen:
            dropped.append({"source_frame": int(i), "time": float(info.frame_time(int(i))),
                            "reason": "frame could not be decoded"})
    fr = np.asarray(frames, np.int64)
    shot_of = dict(zip(decoded, shot_indices(np.asarray(thumbs)).tolist()))
    shots = np.array([shot_of[int(i)] for i in fr], np.int64)
    cuts = [i for k, i in enumerate(decoded) if k and shot_of[i] != shot_of[decoded[k - 1]]]
    return TrackedClip(
        info=info, selected=sel, frames=fr, times=np.asarray(info.frame_time(fr), np.float64),
        landmarks=np.asarray(L, np.float64).reshape(-1, 478, 3),
        blendshapes=np.asarray(B, np.float32).reshape(len(frames), len(names)),
        transforms=np.asarray(M, np.float64).reshape(-1, 4, 4), names=list(names),
        dropped=sorted(dropped, key=lambda d: d["source_frame"]),
        seconds=time.perf_counter() - t0, crowded=crowded, shots=shots, cuts=cuts,
    )


def require_enough(clip: TrackedClip, min_fraction: float, minimum: int = 2) -> None:
    """UserError when too few of the selected frames have a face."""
    n_sel, n_ok = len(clip.selected), len(clip.frames)
    path = clip.info.path
    if n_sel < minimum:  # tracking is not what failed: say what is short
        raise UserError(f"{path}: only {n_sel} frame{'s' * (n_sel != 1)} selected from the "
                        f"video's {clip.info.num_frames} (need at least {minimum}; --fps and "
                        f"--max-frames select them)")
    if n_ok == 0:
        raise UserError(f"{path}: no face found in any of the {n_sel} selected frames")
    need = max(minimum, int(np.ceil(min_fraction * n_sel)))
    if n_ok < need:
        first = ", ".join(str(d["source_frame"]) for d in clip.dropped[:8])
        more = "..." if len(clip.dropped) > 8 else ""
        raise UserError(
            f"{path}: face tracked in only {n_ok} of {n_sel} selected frames (need at least "
            f"{need}; --min-tracked {min_fraction:g}); frames without a face: {first}{more}")


def drop_frames(clip: TrackedClip, keep: np.ndarray, reasons: dict[int, str]) -> TrackedClip:
    """A copy of `clip` without the frames where keep is False (reasons by position)."""
    dropped = clip.dropped + [
        {"source_frame": int(clip.frames[k]), "time": float(clip.times[k]), "reason": r}
        for k, r in reasons.items()]
    return TrackedClip(
        info=clip.info, selected=clip.selected, frames=clip.frames[keep],
        times=clip.times[keep], landmarks=clip.landmarks[keep],
        blendshapes=clip.blendshapes[keep], transforms=clip.transforms[keep],
        names=clip.names, dropped=sorted(dropped, key=lambda d: d["source_frame"]),
        seconds=clip.seconds, crowded=clip.crowded,
        shots=None if clip.shots is None else clip.shots[keep], cuts=clip.cuts)


def solve_clip(clip: TrackedClip, mesh, fov: float | None, max_error: float = MAX_ERROR,
               min_tracked: float = 0.5):
    """Camera solve (`fov`: fixed horizontal field of view in degrees, or None to estimate
    it); frames whose rigid reprojection error exceeds max_error x face size (and 3x the
    median) are dropped, listed, and the solve is rerun without them, if at least
    `min_tracked` of the selected frames remain. -> (clip, SolveResult)"""
    from flamenerf.tracking.cameras import SolveConfig, solve_cameras

    cfg = SolveConfig(fov_deg=fov)
    step = 1.0 / clip.info.fps

    def run(c: TrackedClip):
        return solve_cameras(c.landmarks, c.times, mesh.vertices, mesh.faces, mesh.weights,
                             c.info.width, c.info.height, c.transforms, cfg, step, c.shots)

    res = run(clip)
    limit = max(max_error * res.face_size, 3 * float(np.median(res.rigid_error)))
    bad = res.rigid_error > limit
    if bad.any():
        reasons = {int(k): f"camera-solve misfit: {res.rigid_error[k]:.1f} px > {limit:.1f} px"
                   for k in np.flatnonzero(bad)}
        clip = drop_frames(clip, ~bad, reasons)
        require_enough(clip, min_tracked)
        res = run(clip)
    return clip, res


@dataclass
class Scene:
    """The clip's cameras and head poses in one metric world (`flamenerf.tracking.world`),
    with the background registration they came from (None when it was not attempted)."""

    world: Any  # tracking.world.World
    registration: Any  # tracking.background.Registration | None
    seconds: float = 0.0


def solve_scene(clip: TrackedClip, mesh, fov: float | None, max_error: float = MAX_ERROR,
                min_tracked: float = 0.5, background: bool = True, bg_opts=None,
                progress: bool = False):
    """Face solve, then cameras from the background and head poses from the face.

    1. `solve_clip`: focal length (scan) and camera-from-head per frame, misfits dropped;
    2. the background (person masked out) registered by COLMAP from that focal length,
       which a final bundle adjustment refines (unless `fov` fixes it);
    3. frames the background did not register are dropped, and the face solve is rerun at
       the background's focal length, so that both agree on depth;
    4. `compose_world`: metric scale, head poses, the case, warnings.
    With background=False, or when the registration fails, the head is the world (as
    before). -> (clip, SolveResult, Scene)"""
    from flamenerf.tracking.background import (BackgroundOptions, person_mask,
                                               register_background)
    from flamenerf.tracking.world import compose_world

    clip, sol = solve_clip(clip, mesh, fov, max_error, min_tracked)
    centre = sol.template.mean(0)
    if not background:
        return clip, sol, Scene(compose_world(sol.w2c, None, centre, head_asked=True), None)
    t0 = time.perf_counter()
    opts = bg_opts or BackgroundOptions()
    if fov is not None:
        opts = BackgroundOptions(**{**opts.__dict__, "refine_focal": False})
    info = clip.info
    pos = {int(s): k for k, s in enumerate(clip.frames)}
    frames = ((i, rgb, person_mask(clip.landmarks[pos[i], :, :2], info.width, info.height))
              for i, rgb in progress_bar(iter_frames(info, clip.frames), len(clip.frames),
                                         "background", progress))
    reg = register_background(frames, opts, focal=sol.focal, still_head_c2w=sol.c2w)
    if reg.status == "registered":
        keep = np.isin(clip.frames, reg.ids[reg.registered])
        if not keep.all():
            clip = drop_frames(clip, keep, {int(k): "not registered against the background"
                                            for k in np.flatnonzero(~keep)})
            require_enough(clip, min_tracked)
        bg_fov = float(np.degrees(2 * np.arctan(0.5 * info.width / reg.focal)))
        clip, sol = solve_clip(clip, mesh, bg_fov if fov is None else fov, max_error,
                               min_tracked)
        reg = reg.subset(clip.frames)
    world = compose_world(sol.w2c, reg, sol.template.mean(0))
    return clip, sol, Scene(world, reg, time.perf_counter() - t0)
