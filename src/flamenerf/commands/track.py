"""`flamenerf track`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

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
    face: Literal["largest", "left", "right"] = "largest",
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
        face: Whose face to follow where several are in view: the largest of the first
            frame with a face, or the leftmost or rightmost there.
        overwrite: Replace OUT if it exists.
    """
    from flamenerf.errors import UserError
    from flamenerf.outdir import folders_kept_only_on_success, writable_dir
    from flamenerf.tracking.expressions import save_expressions, transfer_to_subject
    from flamenerf.tracking.clip import crowded_note
    from flamenerf.tracking.driving import track_expressions

    if out.is_dir():
        raise UserError(f"{out}: is a directory; --out names a .json file")
    if driver_neutral_frame is not None and relative_to is None:
        raise UserError("--driver-neutral-frame: only with --relative-to (it picks the "
                        "driver's neutral face for the transfer to that subject)")
    if driver_neutral_frame is not None:
        from flamenerf.data.video import probe_video

        n = probe_video(video).num_frames  # before tracking it, not after
        if not 0 <= driver_neutral_frame < n:
            raise UserError(f"--driver-neutral-frame {driver_neutral_frame}: {video} has "
                            f"frames 0 to {n - 1}")
    if out.exists() and not overwrite:
        raise UserError(f"{out}: already exists (pass --overwrite to replace it)")
    with folders_kept_only_on_success(out.parent):
        writable_dir(out.parent, "expressions file")  # before tracking the video, not after
        subject = None
        if relative_to is not None:
            from flamenerf.data.dataset import load_dataset

            subject = load_dataset(relative_to, check_files=False)
        tr = track_expressions(video, fps, max_frames, landmarker, face_model, flame_dir,
                               flame_expr_dim, min_tracked, face=face)
        if subject is not None:
            tr = transfer_to_subject(tr, subject, driver_neutral_frame)
        save_expressions(out, tr)
    print(f"wrote {out}: {len(tr.frames)} frames x {len(tr.names)} {tr.kind} values at "
          f"{tr.fps:g} fps; dropped {len(tr.dropped)}"
          + (f"; relative to {relative_to}" if subject is not None else ""))
    note = crowded_note((tr.source or {}).get("crowded_frames") or [], face)
    if note:
        print(note)
    for d in tr.dropped[:10]:
        print(f"  dropped frame {d['source_frame']} ({d['time']:.2f}s): {d['reason']}")
