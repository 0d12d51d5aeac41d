"""`flamenerf track`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro


def track(
    video: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="VIDEO")],
    out: Path,
    fps: float | None = None,
    max_frames: int | None = None,
    relative_to: Path | None = None,
    driver_neutral_frame: int | None = None,
    landmarker: Path | None = None,
    face_model: Literal["mediapipe", "flame"] = "mediapipe",
    flame_dir: Path | None = None,
    flame_expr_dim: int = 50,
    min_tracked: float = 0.5,
    overwrite: bool = False,
) -> None:
    """Extract per-frame expression vectors from a driving video, for `render --drive`.

    Tracks the face in every selected frame (MediaPipe FaceLandmarker, IMAGE mode) and
    writes one expression vector per tracked frame as JSON: {"names": [...], "kind",
    "fps", "frames": [[...], ...], "source_frames", "times", "dropped": [...]} (see
    docs/preprocessing.md). Frames without a face are dropped and listed. With
    --relative-to DATASET the expressions are transferred relative to each subject's
    neutral face (what NerFACE recommends across subjects): subject_neutral + (driver -
    driver_neutral); neutral faces are estimated from the calmest frames unless
    --driver-neutral-frame is given. Use the same --face-model as the dataset's.

    Example: flamenerf track driver.mp4 --out drive.json --relative-to data/me

    Args:
        video: Driving video.
        out: Output JSON file.
        fps: Keep about this many frames per second (default: every frame).
        max_frames: Keep at most this many frames, spread evenly over the clip.
        relative_to: Dataset of the subject to drive; transfer expressions relative to
            the neutral faces of driver and subject.
        driver_neutral_frame: Video frame index where the driver's face is neutral
            (default: estimated).
        landmarker: face_landmarker.task to use (default: as for preprocess).
        face_model: mediapipe (52 ARKit blendshape scores) or flame (FLAME expression
            coefficients; needs --flame-dir).
        flame_dir: Folder with FLAME's model pickle and MediaPipe landmark embedding.
        flame_expr_dim: Number of FLAME expression coefficients (the jaw pose follows them).
        min_tracked: Fail unless at least this fraction of the selected frames is tracked.
        overwrite: Replace OUT if it exists.
    """
    import numpy as np

    from flamenerf.errors import UserError
    from flamenerf.tracking.expressions import (estimate_neutral, save_expressions,
                                                transfer_relative)
    from flamenerf.tracking.pipeline import track_expressions

    if out.exists() and not overwrite:
        raise UserError(f"{out}: already exists (pass --overwrite to replace it)")
    if out.is_dir():
        raise UserError(f"{out}: is a directory; --out names a .json file")
    subject = None
    if relative_to is not None:
        from flamenerf.data.dataset import load_dataset

        subject = load_dataset(relative_to, check_files=False)
    tr = track_expressions(video, fps, max_frames, landmarker, face_model, flame_dir,
                           flame_expr_dim, min_tracked)
    if subject is not None:
        if subject.expression_names != tr.names:
            raise UserError(
                f"{relative_to}: its expression model ({subject.expression_kind}, "
                f"{subject.expression_dim} values) differs from this track's ({tr.kind}, "
                f"{len(tr.names)}); use the same --face-model")
        capture = [f for f in subject.frames if f.frame_index is not None]
        s_neutral, s_used = estimate_neutral(subject.expression_matrix(capture))
        if driver_neutral_frame is not None:
            if driver_neutral_frame not in (tr.source_frames or []):
                raise UserError(f"{video}: frame {driver_neutral_frame} was not tracked "
                                "(pick a selected frame with a face)")
            d_neutral = tr.frames[tr.source_frames.index(driver_neutral_frame)].astype(
                np.float64)
            d_used = [driver_neutral_frame]
        else:
            d_neutral, used = estimate_neutral(tr.frames)
            d_used = [tr.source_frames[i] for i in used]
        tr.frames = transfer_relative(tr.frames, d_neutral, s_neutral, tr.kind)
        tr.transfer = {"mode": "relative", "subject": str(relative_to),
                       "subject_neutral": np.round(s_neutral, 6).tolist(),
                       "subject_neutral_frames": [capture[i].frame_index for i in s_used],
                       "driver_neutral": np.round(d_neutral, 6).tolist(),
                       "driver_neutral_frames": d_used}
    save_expressions(out, tr)
    print(f"wrote {out}: {len(tr.frames)} frames x {len(tr.names)} {tr.kind} values at "
          f"{tr.fps:g} fps; dropped {len(tr.dropped)}"
          + (f"; relative to {relative_to}" if subject is not None else ""))
    for d in tr.dropped[:10]:
        print(f"  dropped frame {d['source_frame']} ({d['time']:.2f}s): {d['reason']}")
