"""`flamenerf render`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro


def render(
    run: Annotated[Path, tyro.conf.Positional],
    out: Path | None = None,
    expressions: list[str] | None = None,
    split: str | None = None,
    drive: Path | None = None,
    camera: str = "auto",
    frames: int = 60,
    fps: float | None = None,
    size: int | None = None,
    amplitude: float | None = None,
    expression_base: Literal["reference", "zero"] = "reference",
    depth: bool = False,
    side_by_side: bool = False,
    dataset: Path | None = None,
    dilate_px: int | None = None,
    max_frames: int | None = None,
    relative: bool = True,
    landmarker: Path | None = None,
    chunk: int = 16384,
    device: str = "auto",
    threads: int = 0,
    overwrite: bool = False,
) -> None:
    """Render a re-animation video: frame 0's codes, driven by expressions, along a camera
    path.

    Expressions come from one of: --expressions FILE (.json: a `flamenerf track` file, a
    list of vectors, or {name: value} objects; .npy; .csv with an optional header of
    control names) or --expressions KEYFRAME... (e.g. `jawOpen=0.8` `mouthSmileLeft=1,
    browInnerUp=0.5`: ease from the base expression to each keyframe in turn and back);
    --split NAME (a dataset split's expressions, cameras and face meshes, e.g. reanimate);
    --drive VIDEO (tracked like `flamenerf track`). Named controls are mapped onto the
    run's; missing ones are 0. Without any, frame 0's expression is held.

    Camera paths (--camera): static (frame 0's camera), orbit (an arc around the head),
    spiral, dolly, or a JSON file of camera-to-world poses; `auto` uses a split's own
    cameras, else static. Paths look at the head (the centroid of frame 0's face mesh)
    and take their radius and swing from the training cameras. The spatial prior's mask
    for each frame is the face mesh (frame 0's, or the split's per-frame mesh) rasterised
    for that camera with the dataset's dilation.

    Writes OUT (H.264 mp4), plus OUT_depth.mp4 with --depth and OUT_sbs.mp4 (driving |
    result | depth) with --side-by-side. See docs/evaluation.md.

    Example: flamenerf render runs/fast --expressions jawOpen=0.8 --camera orbit --depth

    Args:
        run: Run directory (made by `flamenerf train`).
        out: Output video (default: RUN/renders/SOURCE_CAMERA.mp4).
        expressions: An expression file, or name=value[,name=value] keyframes.
        split: Take expressions, cameras and face meshes from this dataset split.
        drive: Track the expressions of this driving video.
        camera: static, orbit, spiral, dolly, a JSON file of poses, or auto.
        frames: Number of frames when the source does not fix it (keyframes, held
            expression, a named camera path).
        fps: Frames per second (default: the source's, else 30). With --drive the video is
            sampled at this rate.
        size: Render width in pixels (default: the run's training width).
        amplitude: Path amplitude: degrees for orbit/spiral, a fraction of the distance for
            dolly (default: from the training cameras; dolly 0.2).
        expression_base: What keyframes start from and return to, and which controls they
            leave unchanged: frame 0's expression (reference) or all zeros.
        depth: Also write a colour-mapped depth video.
        side_by_side: Also write driving | result | depth (the expression as bars when
            there is no driving image).
        dataset: Dataset with the face mesh and cameras (default: the run's own).
        dilate_px: Dilation of the prior's mask in dataset pixels (default: estimated from
            the dataset's masks).
        max_frames: Render at most this many frames (with --drive: this many spread over
            the clip).
        relative: With --drive on a dataset of the same expression model, transfer
            expressions relative to each subject's neutral face.
        landmarker: face_landmarker.task for --drive (default: as for preprocess).
        chunk: Rays per forward pass (lower it if memory runs out).
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        overwrite: Replace existing output videos.
    """
    import numpy as np
    import torch
    from tqdm import tqdm

    from flamenerf.errors import UserError
    from flamenerf.rendering import cameras as C
    from flamenerf.rendering import expressions as X
    from flamenerf.rendering.prior import estimate_dilation, mesh_function
    from flamenerf.training.run import load_run

    given = [n for n, v in (("--expressions", expressions), ("--split", split),
                            ("--drive", drive)) if v]
    if len(given) > 1:
        raise UserError(f"give one expression source, not {' and '.join(given)}")
    if frames < 1:
        raise UserError(f"--frames {frames}: must be at least 1")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"--max-frames {max_frames}: must be at least 1")
    if chunk < 1:
        raise UserError(f"--chunk {chunk}: must be positive")
    if dilate_px is not None and dilate_px < 0:
        raise UserError(f"--dilate-px {dilate_px}: must be >= 0")
    if threads > 0:
        torch.set_num_threads(threads)
    r = load_run(run, device)
    ds = r.dataset(dataset)
    names = r.expression_names
    if size is None:
        intr = r.train_intrinsics(ds)
    else:
        if not 8 <= size <= 8192:
            raise UserError(f"--size {size}: must be between 8 and 8192")
        intr = ds.intrinsics.scaled(size / ds.intrinsics.w)
    ref = C.reference_position(ds)
    base = (ds.frames[ref].expression.astype(np.float32) if expression_base == "reference"
            else np.zeros(len(names), np.float32))

    # ------------------------------------------------------------ expression source
    if split:
        seq = X.from_split(ds, split, (intr.h, intr.w))
    elif drive:
        seq = X.from_video(drive, ds, names, relative=relative, fps=fps, max_frames=max_frames,
                           panel_height=intr.h, landmarker=landmarker)
        if max_frames is not None and fps is None:
            print(f"note: --max-frames spreads the {len(seq)} frames over the clip; the video "
                  f"plays at their rate ({seq.fps:.3g} fps) unless --fps is given")
    elif expressions:
        seq = X.from_items(expressions, names, base, frames)
    else:
        seq = X.ExpressionSequence(np.repeat(base[None], frames, 0), label="reference",
                                   resizable=True)
    for note in seq.notes:
        print(f"note: {note}")

    # ------------------------------------------------------------ cameras
    rig = C.rig_from_dataset(ds)
    cam_label = camera
    if camera in ("auto", "split"):
        if seq.cameras is not None:
            poses, cam_label = seq.cameras, "split"
        elif camera == "split":
            raise UserError("--camera split: needs --split")
        else:
            poses, cam_label = C.camera_path("static", len(seq), rig), "static"
    elif camera in C.PATH_KINDS:
        poses = C.camera_path(camera, len(seq), rig, amplitude)
    else:
        poses = C.load_poses(Path(camera))
        cam_label = Path(camera).stem
        if seq.resizable and len(poses) != len(seq):
            seq = _resized(seq, len(poses), base, expressions, names, X)
        elif len(poses) != len(seq):
            print(f"note: {camera} has {len(poses)} poses for {len(seq)} frames; resampled")
            poses = C.resample(poses, len(seq))
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    values, poses = seq.values[:n], poses[:n]
    if seq.vertices is not None:  # a split with its own (ground-truth) meshes
        verts = seq.vertices[:n]
    else:  # the prior's silhouette follows the driven expression's mesh, not frame 0's
        mesh_of = mesh_function(r.model, ds)
        verts = np.stack([mesh_of(v) for v in values])
    dil = estimate_dilation(ds) if dilate_px is None else dilate_px
    rate = fps or seq.fps or 30.0

    # ------------------------------------------------------------ outputs
    out = out if out is not None else Path(run) / "renders" / f"{seq.label}_{cam_label}.mp4"
    if out.suffix.lower() != ".mp4":
        raise UserError(f"{out}: the output must be an .mp4 file")
    paths = {"rgb": out}
    if depth:
        paths["depth"] = out.with_name(f"{out.stem}_depth.mp4")
    if side_by_side:
        paths["sbs"] = out.with_name(f"{out.stem}_sbs.mp4")
    for p in paths.values():
        if p.exists() and not overwrite:
            raise UserError(f"{p}: already exists (pass --overwrite to replace it)")
    _render_videos(r, ds, intr, poses, values, verts, dil, chunk, rate, paths, seq, names,
                   tqdm)
    print(f"wrote {', '.join(str(p) for p in paths.values())}: {n} frames at {intr.w}x{intr.h}, "
          f"{rate:g} fps (expressions: {seq.label}; camera: {cam_label}; prior mask dilation "
          f"{dil} px)")


def _resized(seq, num, base, expressions, names, X):
    """Re-make a keyframe/held sequence with `num` frames (to match a pose file)."""
    import numpy as np

    if expressions:
        return X.from_items(expressions, names, base, num)
    return X.ExpressionSequence(np.repeat(base[None], num, 0), label=seq.label,
                                resizable=True)


def _render_videos(r, ds, intr, poses, values, verts, dil, chunk, rate, paths, seq, names,
                   tqdm) -> None:
    import contextlib

    from flamenerf.images import expression_panel, hstack, resize_to_height
    from flamenerf.rendering.reanimate import depth_image, depth_range, render_sequence
    from flamenerf.data.video import VideoWriter

    omega, phi = r.frame_codes(0)
    frames = render_sequence(r.model, ds, intr, poses, values, verts, omega, phi, dil, chunk)
    with contextlib.ExitStack() as stack:
        writers = {k: stack.enter_context(VideoWriter(p, rate)) for k, p in paths.items()}
        lo = hi = None
        for i, fr in enumerate(tqdm(frames, total=len(poses), desc="render", unit="frame")):
            writers["rgb"].write(fr.rgb)
            if lo is None:
                lo, hi = depth_range(fr, r.model.near, r.model.far)
            if "depth" in writers or "sbs" in writers:
                dimg = depth_image(fr, lo, hi)
            if "depth" in writers:
                writers["depth"].write(dimg)
            if "sbs" in writers:
                if seq.driving is not None:
                    left = resize_to_height(seq.driving(i), intr.h)
                else:
                    left = expression_panel(values[i], names, intr.h, intr.w)
                writers["sbs"].write(hstack([left, fr.rgb, dimg], gap=2))
