"""`flamenerf synth`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro


MAX_FRAMES = 100_000  # about an hour at 30 fps, and a few GB of images at 256 px
MAX_WORKERS = 64  # one process each


def synth(
    out: Annotated[Path, tyro.conf.Positional],
    seed: int = 0,
    size: int = 256,
    frames: int = 300,
    sway: float | None = None,
    head_motion: bool = False,
    handheld: bool = False,
    entangled: bool = False,
    never: tuple[str, ...] = (),
    video: Path | None = None,
    reanimate: int | None = None,
    leakage_steps: int = 3,
    workers: int = 0,
    overwrite: bool = False,
) -> None:
    """Make the built-in synthetic portrait scene, with ground truth.

    A textured head and shoulders in front of a brick wall and furniture, filmed by a
    hand-held camera arcing +-25 deg in yaw and +-10 deg in pitch while the face talks
    (14 expression controls named after ARKit blendshapes). Writes RGB, z-depth, face
    masks, face-mesh vertices, cameras and expressions; splits train/val (the capture),
    reanimate (novel expressions from novel cameras) and leakage (one control at a time
    from a fixed camera). With --head-motion the head also turns (+-25 deg yaw, +-10 deg
    pitch) and shifts (a few cm) independently of the camera against a static room; each
    frame records its head pose, and a novel_pose split (novel head poses x cameras x
    expressions) is added. --handheld films that moving head as a phone held in the hand
    would (a few degrees of shake, a few cm of drift, little parallax) against a far
    skyline, with leaves swaying by themselves beside the head. --entangled moves the
    controls only in fixed groups, as people do (a surprise raises the brows, widens the
    eyes and opens the jaw together), and adds a pairs split; --never leaves controls out
    of the capture altogether; the leakage and pairs splits then command what the capture
    never showed. The same seed always gives the same bytes. See docs/synthetic_scene.md.

    Example: flamenerf synth scenes/portrait --size 128 --frames 120

    Example: flamenerf synth scenes/phone --handheld --video scenes/phone.mp4

    Example: flamenerf synth scenes/groups --entangled --never eyeBlinkLeft eyeBlinkRight

    Args:
        out: Output dataset directory.
        seed: Random seed (appearance, camera path, sway, expressions).
        size: Image width and height in pixels.
        frames: Number of capture frames (train + val; val is every 10th).
        sway: Body/background sway amplitude (about this many degrees, 3x this many mm);
            0 makes everything but the face static (default 1; 0 with --head-motion or
            --handheld, which need the room static).
        head_motion: The head turns and shifts independently of the camera (ground-truth
            head poses in transforms.json as head_pose).
        handheld: A phone's shaky capture of the moving head (implies --head-motion)
            against a far skyline and swaying leaves.
        entangled: The capture moves the controls only in fixed groups (surprise, smile,
            speech, anger, blinks of both eyes).
        never: Controls the capture never moves (e.g. eyeBlinkLeft eyeBlinkRight).
        video: Also write the capture frames (train and val, in time order) to this mp4
            at 30 fps, e.g. for `flamenerf preprocess`.
        reanimate: Number of re-animation frames (default: frames / 10, at least 3).
        leakage_steps: Values per control in the leakage sweep (1/steps .. 1).
        workers: Render processes (0: one per CPU core, at most 4).
        overwrite: Replace OUT (and the --video file) if it exists.
    """
    from tqdm import tqdm

    from flamenerf.data.dataset_writer import MAX_SIZE
    from flamenerf.errors import UserError
    from flamenerf.outdir import writable_dir
    from flamenerf.synthetic.scene import frame_specs, make_scene, write_capture_video

    if sway is None:
        sway = 0.0 if head_motion or handheld else 1.0
    elif (head_motion or handheld) and sway != 0:
        flag = "--handheld" if handheld else "--head-motion"
        raise UserError(f"--sway {sway}: with {flag} the room is the static world; "
                        "leave --sway out (or give 0)")
    if not 0 <= sway <= 10:  # a few degrees is the scene's idea; 90 turns the room away
        raise UserError(f"--sway {sway:g}: must be in 0..10 (degrees)")
    if not 16 <= size <= MAX_SIZE:
        raise UserError(f"--size {size}: must be between 16 and {MAX_SIZE}")
    if not 1 <= frames <= MAX_FRAMES:
        raise UserError(f"--frames {frames}: must be from 1 to {MAX_FRAMES}")
    if not 0 <= workers <= MAX_WORKERS:
        raise UserError(f"--workers {workers}: must be 0 (one per core) to {MAX_WORKERS}")
    if not 0 <= seed < 2 ** 63:
        raise UserError(f"--seed {seed}: must be in 0..2^63-1")
    if reanimate is not None and not 0 <= reanimate <= MAX_FRAMES:
        raise UserError(f"--reanimate {reanimate}: must be from 0 to {MAX_FRAMES}")
    if not 0 <= leakage_steps <= 100:
        raise UserError(f"--leakage-steps {leakage_steps}: must be from 0 to 100")
    from flamenerf.synthetic.head import CONTROLS

    unknown = [name for name in never if name not in CONTROLS]
    if unknown:
        raise UserError(f"--never {unknown[0]}: no such control (the scene's: "
                        f"{', '.join(CONTROLS)})")
    if out.exists() and not overwrite:
        raise UserError(f"{out}: already exists (pass --overwrite to replace it)")
    if video is not None:
        if video.suffix.lower() != ".mp4":
            raise UserError(f"{video}: the video must be an .mp4 file")
        if video.is_dir():
            raise UserError(f"{video}: is a folder, not a video file")
        if video.exists() and not overwrite:
            raise UserError(f"{video}: already exists (pass --overwrite to replace it)")
        # the dataset folder is replaced whole when it is written
        if video.absolute().is_relative_to(out.absolute()):
            raise UserError(f"--video {video}: must be outside the dataset folder {out}")
        writable_dir(video.absolute().parent, "video")
    total = len(frame_specs(seed, frames, sway, reanimate, leakage_steps, head_motion,
                            handheld, entangled, never))
    with tqdm(total=total, desc="synth", unit="frame") as bar:
        path = make_scene(out, seed=seed, size=size, frames=frames, sway=sway,
                          reanimate=reanimate, leakage_steps=leakage_steps,
                          overwrite=overwrite, workers=workers, head_motion=head_motion,
                          handheld=handheld, entangled=entangled, never=never,
                          progress=lambda n: bar.update(n - bar.n))
    print(f"wrote {path} ({total} frames)")
    if video is not None:
        print(f"wrote {write_capture_video(path, video)} ({frames} frames at 30 fps)")
