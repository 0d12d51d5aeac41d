"""`make_scene`: write the built-in synthetic portrait scene as a flamenerf dataset.

Splits (positions in the one frame list, in this order):
  train, val   the capture: frame t (t = 0 .. frames-1) has frame_index t; val is every
               10th frame (t % 10 == 5; with 2-5 frames, the last one), so frame 0, the
               reference frame, is trained on;
  reanimate    novel expressions (an independent trajectory) seen from cameras off the
               capture path, with frame 0's body pose; frame_index null;
  leakage      frame 0's camera and body pose; neutral, then each control alone at
               1/steps .. 1; frame_index null; each frame records `leakage_control` and
               `leakage_value`.
  pairs        with `entangled` only: as leakage, two controls at 1 that the capture never
               shows together (expressions.PAIRS); each frame records `pair`.
  novel_pose   with --head-motion only: novel head poses x novel cameras x novel
               expressions (independent draws); frame_index null.
Every frame records its world-from-body pose (`body_pose`), so `scene_from_dataset(ds)`
can re-render ground truth for any frame, camera or expression.

With `head_motion`, the world is the room (static: body_pose is the identity) and the head
turns and shifts in it (synthetic/motion.py): every frame stores its world-from-head pose
as the dataset's `head_pose`, and its face mesh posed by it. The reanimate and leakage
splits keep frame 0's head pose. Without it the head is the world, as in the paper's
capture, and frames carry no head_pose.

With `handheld` (which implies head_motion), the capture is a phone held in front of the
face (cameras.handheld_path: a few degrees of shake, a few cm of drift) and the room is far
away: a skyline 4 m behind the head and a panel of leaves beside it whose texture sways by
itself (background.py). Capture frame t is rendered at time t (the leaves' motion); the
other splits at time 0. `handheld_capture` gives the capture with its ground truth (the
person and moving masks, true cameras, head poses, landmarks) for testing camera solvers.

With `entangled`, the capture moves the controls only in fixed groups, as people do
(expressions.GROUPS: a surprise raises the brows, widens the eyes and opens the jaw
together), so the leakage split's controls alone and the pairs split are what it never
showed; `never` names controls the capture leaves at 0 (e.g. no blink). Both change only
the capture's expressions; the re-animation splits keep their independent trajectories.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from flamenerf.synthetic.cameras import capture_path, handheld_path, intrinsics, novel_path
from flamenerf.synthetic.expressions import (PAIRS, entangled_trajectory, leakage_sweep,
                                             speech_trajectory)
from flamenerf.synthetic.head import CONTROL_INDEX, CONTROLS, mesh_landmarks
from flamenerf import __version__
from flamenerf.data.dataset import Intrinsics, load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.dataset_writer import DatasetWriter
from flamenerf.data.video import VideoWriter
from flamenerf.geometry import project_points
from flamenerf.synthetic.background import sway_pose
from flamenerf.synthetic.motion import head_motion_path, novel_head_poses
from flamenerf.synthetic.render import SyntheticScene, mask_dilation

SOURCE_NAME = "flamenerf synth"


@dataclass
class FrameSpec:
    """What to render for one dataset frame."""

    split: str
    frame_index: int | None
    c2w: np.ndarray  # (4, 4)
    expression: np.ndarray  # (num_controls,)
    body_pose: np.ndarray  # (4, 4) world-from-body
    extra: dict[str, Any] = field(default_factory=dict)
    head_pose: np.ndarray | None = None  # (4, 4) world-from-head; None: the head is the world
    time: float | None = None  # capture frames, for what moves by itself (SyntheticScene.render)


def capture_split(t: int, frames: int) -> str:
    """'val' for every 10th capture frame (t % 10 == 5; the last frame when there are 2 to 5
    frames), else 'train'. Frame 0 is always trained on."""
    if t % 10 == 5 or (2 <= frames < 6 and t == frames - 1):
        return "val"
    return "train"


def default_reanimate(frames: int) -> int:
    """Number of re-animation frames: 30 for the default 300-frame capture."""
    return max(3, round(frames / 10))


def frame_specs(seed: int, frames: int, sway: float, reanimate: int | None = None,
                leakage_steps: int = 3, head_motion: bool = False,
                handheld: bool = False, entangled: bool = False,
                never: tuple[str, ...] = ()) -> list[FrameSpec]:
    """Every frame of the scene, in dataset order (train/val, reanimate, leakage, with
    entangled pairs, and with head_motion novel_pose). `handheld` implies head_motion;
    `entangled`: the capture moves the controls in fixed groups (expressions.GROUPS);
    `never`: controls the capture never moves (the other splits still command them)."""
    head_motion = head_motion or handheld
    specs: list[FrameSpec] = []
    c2ws = handheld_path(frames, seed) if handheld else capture_path(frames, seed)[0]
    exprs = (entangled_trajectory(frames, seed) if entangled
             else speech_trajectory(frames, seed, stream=0))
    exprs[:, [CONTROL_INDEX[name] for name in never]] = 0.0
    heads = head_motion_path(frames, seed) if head_motion else [None] * frames
    for t in range(frames):
        pose = sway_pose(t, sway, seed)
        specs.append(FrameSpec(capture_split(t, frames), t, c2ws[t], exprs[t], pose,
                               {"body_pose": pose.tolist()}, heads[t], float(t)))
    pose0, head0 = sway_pose(0, sway, seed), heads[0] if frames else None
    n_re = default_reanimate(frames) if reanimate is None else reanimate
    if n_re > 0:
        cams = novel_path(n_re, seed)
        # an independent trajectory, sampled every 3rd frame so that it covers more
        ex = speech_trajectory(3 * n_re, seed, stream=1)[::3]
        for i in range(n_re):
            specs.append(FrameSpec("reanimate", None, cams[i], ex[i], pose0,
                                   {"body_pose": pose0.tolist()}, head0))
    if leakage_steps > 0:
        sweep, labels = leakage_sweep(leakage_steps)
        for x, (name, value) in zip(sweep, labels):
            specs.append(FrameSpec("leakage", None, c2ws[0], x, pose0,
                                   {"body_pose": pose0.tolist(), "leakage_control": name,
                                    "leakage_value": float(value)}, head0))
    if entangled and leakage_steps > 0:
        for pair in PAIRS:
            x = np.zeros(len(CONTROLS), np.float32)
            x[[CONTROL_INDEX[name] for name in pair]] = 1.0
            specs.append(FrameSpec("pairs", None, c2ws[0], x, pose0,
                                   {"body_pose": pose0.tolist(), "pair": list(pair)}, head0))
    if head_motion and n_re > 0:
        # novel cameras (the re-animation loop, shifted by half a step), expressions (a
        # third independent trajectory) and head poses
        cams = novel_path(2 * n_re, seed)[1::2]
        ex = speech_trajectory(3 * n_re, seed, stream=2)[::3]
        for i, hp in enumerate(novel_head_poses(n_re, seed)):
            specs.append(FrameSpec("novel_pose", None, cams[i], ex[i], pose0,
                                   {"body_pose": pose0.tolist()}, hp))
    return specs


# ----------------------------------------------------------------------------- rendering workers

_WORKER_SCENE = None


def _init_worker(seed: int, size: int, sway: float, handheld: bool = False) -> None:
    import torch

    global _WORKER_SCENE
    torch.set_num_threads(1)
    _WORKER_SCENE = SyntheticScene(seed, size, sway, handheld)


def _render_spec(spec: FrameSpec):
    v = _WORKER_SCENE.render(spec.c2w, spec.expression, spec.body_pose,
                             head_pose=spec.head_pose, time=spec.time)
    rgb = (np.clip(v.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    return rgb, v.depth, v.mask, v.face_vertices, v.person, v.moving


def render_frames(seed: int, size: int, sway: float, specs: list[FrameSpec],
                  workers: int = 0, handheld: bool = False) -> Iterator[tuple]:
    """Render specs in order -> (rgb uint8, depth, mask, face vertices, person, moving) per
    frame.

    Frames are independent, so `workers` processes (0: one per CPU core, at most 4) render
    them in parallel with one torch thread each; the bytes do not depend on `workers`."""
    import torch

    if workers <= 0:
        workers = max(1, min(4, os.cpu_count() or 1))
    workers = min(workers, max(1, len(specs)))
    if workers == 1:
        threads = torch.get_num_threads()
        try:
            _init_worker(seed, size, sway, handheld)
            for s in specs:
                yield _render_spec(s)
        finally:
            torch.set_num_threads(threads)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                               initializer=_init_worker, initargs=(seed, size, sway, handheld))
    try:
        yield from pool.map(_render_spec, specs, chunksize=2)
    except BaseException:  # an error, Ctrl-C or the consumer stopping: drop pending frames
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()


# ----------------------------------------------------------------------------- the dataset


def make_scene(out: str | os.PathLike, seed: int = 0, size: int = 256, frames: int = 300,
               sway: float | None = None, reanimate: int | None = None, leakage_steps: int = 3,
               overwrite: bool = False, workers: int = 0,
               progress: Callable[[int], None] | None = None, head_motion: bool = False,
               handheld: bool = False, entangled: bool = False,
               never: tuple[str, ...] = ()) -> Path:
    """Render the synthetic portrait scene into a dataset directory `out`.

    seed: appearance, camera path, sway and expressions; size: image width = height;
    frames: capture length; sway: body sway amplitude (0 = static scene; default 1, and 0
    with head_motion or handheld, which need the room static); reanimate:
    re-animation frames (default frames / 10); leakage_steps: values per control in the
    leakage sweep; workers: render processes (0 = auto; they are spawned, so a script
    calling this with workers != 1 needs the usual `if __name__ == "__main__":` guard);
    progress(n): called after each frame is written; head_motion: the head turns and
    shifts independently of the camera against a static room (needs sway = 0; adds the
    novel_pose split); handheld: a phone's shaky capture of that moving head against a far
    skyline and swaying leaves (implies head_motion; needs sway = 0); entangled: the
    capture moves the controls only in fixed groups (adds the pairs split); never: controls
    the capture leaves at 0. Returns the dataset path."""
    if size < 16:
        raise DatasetError(f"{out}: size must be at least 16 pixels, got {size}")
    if frames < 1:
        raise DatasetError(f"{out}: frames must be at least 1, got {frames}")
    if sway is None:
        sway = 0.0 if head_motion or handheld else 1.0
    if handheld and sway != 0:
        raise DatasetError(f"{out}: a handheld capture films a static world (the head moves "
                           f"in it); sway must be 0, got {sway}")
    if head_motion and sway != 0:
        raise DatasetError(f"{out}: with head motion the room is the static world; sway must "
                           f"be 0, got {sway}")
    unknown = [name for name in never if name not in CONTROLS]
    if unknown:
        raise DatasetError(f"{out}: no control named {unknown[0]!r} (the scene's controls: "
                           f"{', '.join(CONTROLS)})")
    never = tuple(dict.fromkeys(never))
    head_motion = head_motion or handheld
    specs = frame_specs(seed, frames, sway, reanimate, leakage_steps, head_motion, handheld,
                        entangled, never)
    intr = intrinsics(size)
    source = {"name": SOURCE_NAME, "version": __version__, "seed": int(seed), "size": int(size),
              "frames": int(frames), "sway": float(sway),
              "reanimate": sum(s.split == "reanimate" for s in specs),
              "leakage_steps": int(leakage_steps),
              **({"head_motion": True} if head_motion else {}),
              **({"handheld": True} if handheld else {}),
              **({"entangled": True} if entangled else {}),
              **({"never": list(never)} if never else {})}
    info = {"description": "synthetic face rig; controls named after ARKit blendshapes, "
                           "each in [0, 1] ('Left' = the subject's left, +x)"}

    writer = DatasetWriter(out, intr, 0.1, 10.0, list(CONTROLS), "synthetic",
                           expression_info=info, source=source, overwrite=overwrite,
                           prior_dilation_px=mask_dilation(intr))
    try:
        lo, hi = np.inf, 0.0
        for i, (spec, (rgb, depth, mask, verts, _, moving)) in enumerate(
                zip(specs, render_frames(seed, size, sway, specs, workers, handheld))):
            fin = depth[np.isfinite(depth)]
            if fin.size != depth.size:
                raise RuntimeError(f"frame {i}: some rays see nothing (infinite depth)")
            lo, hi = min(lo, float(fin.min())), max(hi, float(fin.max()))
            # the handheld capture's leaves, for training to weigh down; no mask for the
            # other splits and scenes (so the default scene's files stay as they were)
            capture_moving = moving if handheld and spec.frame_index is not None else None
            writer.add_frame(rgb, mask, spec.c2w, spec.expression, spec.frame_index, spec.split,
                             verts=verts, depth=depth, extra=spec.extra,
                             head_pose=spec.head_pose, moving=capture_moving)
            if progress is not None:
                progress(i + 1)
        writer.set_faces(SyntheticScene.mesh_faces())
        writer.set_meta("face_landmarks", mesh_landmarks())
        writer.set_meta("near", round(0.9 * lo, 4))
        writer.set_meta("far", round(1.05 * hi, 4))
        return writer.close()
    except BaseException:
        writer.abort()
        raise


def scene_from_dataset(ds) -> "SyntheticScene":  # noqa: F821
    """The SyntheticScene that made dataset `ds` (a loaded Dataset), to render ground truth
    for any camera/expression: `scene.render(c2w, expr, frame.extra["body_pose"],
    head_pose=frame.head_pose, time=frame.frame_index)` re-renders a frame."""
    src = ds.source or {}
    if src.get("name") != SOURCE_NAME:
        raise DatasetError(f"{ds.root / 'transforms.json'}: not made by `flamenerf synth`")
    return SyntheticScene(int(src["seed"]), int(src["size"]), float(src.get("sway", 1.0)),
                          bool(src.get("handheld", False)))


# ----------------------------------------------------------------------------- handheld ground truth


@dataclass
class CaptureFrame:
    """One frame of the handheld capture with its ground truth (`handheld_capture`).
    Pixel coordinates are (x right, y down) with the image's top-left corner at (0, 0), so
    pixel (i, j)'s centre is at (j + 0.5, i + 0.5)."""

    index: int  # capture frame (its time: 30 per second)
    rgb: np.ndarray  # (H, W, 3) uint8, the dataset's image
    depth: np.ndarray  # (H, W) float32 z-depth, metres
    mask: np.ndarray  # (H, W) bool, the face mesh's dilated silhouette (the dataset's mask)
    person: np.ndarray  # (H, W) bool, head, neck or torso seen
    moving: np.ndarray  # (H, W) bool, the swaying leaves seen
    c2w: np.ndarray  # (4, 4) camera-to-world, OpenGL axes; the world is the room
    head_pose: np.ndarray  # (4, 4) world-from-head
    expression: np.ndarray  # (num_controls,) in [0, 1], order CONTROLS
    intrinsics: Intrinsics
    face_vertices: np.ndarray  # (V, 3) world, posed by head_pose
    face_pixels: np.ndarray  # (V, 2) the face vertices projected (pixels)
    landmarks: dict[str, np.ndarray]  # eye_left, eye_right, mouth -> (2,) pixels


def handheld_capture(seed: int = 0, size: int = 128, frames: int = 60, workers: int = 1
                     ) -> Iterator[CaptureFrame]:
    """The capture of `make_scene(..., handheld=True)` with the same seed, size and frames
    (the same images), frame by frame with its ground truth, for tests and benchmarks of
    camera solvers; workers as in `render_frames`."""
    specs = frame_specs(seed, frames, 0.0, reanimate=0, leakage_steps=0, handheld=True)
    intr = intrinsics(size)
    marks = mesh_landmarks()
    for spec, (rgb, depth, mask, verts, person, moving) in zip(
            specs, render_frames(seed, size, 0.0, specs, workers, handheld=True)):
        px, _ = project_points(verts.astype(np.float64), intr, spec.c2w)
        yield CaptureFrame(index=spec.frame_index, rgb=rgb, depth=depth, mask=mask,
                           person=person, moving=moving, c2w=np.array(spec.c2w),
                           head_pose=np.array(spec.head_pose), expression=spec.expression,
                           intrinsics=intr, face_vertices=verts, face_pixels=px,
                           landmarks={k: px[v].mean(0) for k, v in marks.items()})


def write_capture_video(dataset: str | os.PathLike, out: str | os.PathLike,
                        fps: float = 30.0) -> Path:
    """The capture frames (train and val, in time order) of a synthetic dataset as an
    H.264 mp4 at `fps`, e.g. to run `flamenerf preprocess` on. -> the video's path."""
    ds = load_dataset(dataset)
    cap = sorted((f for f in ds.frames if f.frame_index is not None), key=lambda f: f.frame_index)
    with VideoWriter(out, fps) as vw:
        for f in cap:
            vw.write((ds.load_image(f) * 255 + 0.5).astype(np.uint8))
    return Path(out)
