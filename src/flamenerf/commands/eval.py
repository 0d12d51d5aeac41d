"""`flamenerf eval`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro


def eval(  # noqa: A001 - the subcommand's name
    run: Annotated[Path, tyro.conf.Positional],
    dataset: Path | None = None,
    fit_steps: int | None = None,
    fit_batch_rays: int = 1024,
    fit_lr: float = 1e-2,
    split: str = "val",
    leakage_dilate_px: int = 3,
    control: bool = True,
    control_steps: int = 5,
    images: int = 3,
    drive: Path | None = None,
    drive_frames: int = 40,
    drive_match_range: bool = False,
    captured_directions: bool = True,
    out: Path | None = None,
    device: str = "auto",
    threads: int = 0,
    seed: int = 0,
) -> None:
    """Evaluate a trained run with the paper's protocol (and more on the built-in scene).

    Held-out frames (`val`): the model is frozen and only each frame's deformation code ω
    is optimised, from frame 0's, with frame 0's appearance code (the paper runs 2000
    steps); then MSE, PSNR, SSIM and PSNR inside/outside the face mask. What a
    re-animation gets: the same frames with frame 0's codes and their own β, nothing fitted
    (driven), and the re-tracked response of renders to commanded controls. On the built-in
    scene also: re-animation PSNR/SSIM against ground truth (frame 0's codes, novel
    expressions and cameras) and background leakage (mean |change| in 0-255 outside the
    dilated face mask while the expression sweeps at a fixed camera). Everything at the
    run's training resolution. Writes OUT/metrics.json, OUT/metrics.md and OUT/images/
    (GT | render | |diff|). See docs/evaluation.md.

    Example: flamenerf eval runs/fast --fit-steps 500

    Args:
        run: Run directory (made by `flamenerf train`).
        dataset: Dataset to evaluate on (default: the run's own).
        fit_steps: Steps of the per-frame ω fit (default: 2000, the paper's, on CUDA; 300 on
            CPU).
        fit_batch_rays: Rays per step of the ω fit (all held-out frames share a batch).
        fit_lr: Adam learning rate of the ω fit.
        split: The held-out split (frames with their own codes).
        leakage_dilate_px: Grow the face masks by this many pixels before measuring
            background change outside them.
        control: Measure the control response: renders re-tracked with MediaPipe's face
            landmarker, gain and correlation of re-tracked vs commanded controls (a sweep
            of each control, and the driven held-out renders against their frames' β).
        control_steps: Values per control in the control sweep (datasets without a
            leakage split).
        images: Number of held-out and re-animation frames saved as PNGs.
        drive: A driving video (another person, or the subject on another day): its tracked
            expressions drive frame 0's camera and codes, the renders are re-tracked, and
            the correlation over time of driving and re-tracked controls is reported
            (section `drive`, images/drive.png: driving over result).
        drive_frames: Frames of the driving video used, spread over the clip.
        drive_match_range: Transfer the drive with each control's reach matched to the
            subject's (`render --match-range`).
        captured_directions: Colour at new cameras as the nearest captured view saw it
            (within 2 degrees of one, as asked), as `render` and `view` show it; off: at
            the direction asked, as training renders.
        out: Output directory (default: RUN/eval).
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        seed: Seed of the ω fit's ray sampling.
    """

    from flamenerf.data.dataset import CAPTURE
    from flamenerf.errors import UserError
    from flamenerf.evaluation.protocol import EvalOptions, evaluate_run
    from flamenerf.evaluation.report import compare_markdown
    from flamenerf.runtime import set_threads
    from flamenerf.training.run import load_run

    set_threads(threads)
    if fit_batch_rays <= 0:
        raise UserError(f"--fit-batch-rays {fit_batch_rays}: must be positive")
    if not fit_lr > 0:
        raise UserError(f"--fit-lr {fit_lr}: must be positive")
    if drive is not None:
        from flamenerf.data.video import probe_video

        probe_video(drive)  # not a video: said now, not after the held-out fit
    if drive_frames < 3:
        raise UserError(f"--drive-frames {drive_frames}: must be at least 3")
    if not 0 <= seed < 2 ** 63:  # as train's and synth's
        raise UserError(f"--seed {seed}: must be in 0..2^63-1")
    if control_steps < 2:
        raise UserError(f"--control-steps {control_steps}: must be at least 2")
    for name, v in (("--fit-steps", fit_steps), ("--images", images),
                    ("--leakage-dilate-px", leakage_dilate_px)):
        if v is not None and v < 0:
            raise UserError(f"{name} {v}: must be >= 0")
    from flamenerf.lock import folder_lock
    from flamenerf.outdir import folders_kept_only_on_success

    out_dir = out if out is not None else Path(run) / "eval"
    r = load_run(run, device)  # first: a folder that is no run gets no eval/ folder
    ds = r.dataset(dataset, captured_directions)
    if split == CAPTURE:
        raise UserError("--split capture: holds the training frames, which the held-out "
                        "protocol must not see; evaluate on val (the default)")
    try:
        ds.split(split)  # before any work
    except UserError as e:
        raise UserError(f"{e}; --split chooses the frames to evaluate on") from None
    if fit_steps is None:
        fit_steps = 2000 if r.device.type == "cuda" else 300
    opts = EvalOptions(split=split, fit_steps=fit_steps, fit_batch_rays=fit_batch_rays,
                       fit_lr=fit_lr, seed=seed, leakage_dilate_px=leakage_dilate_px,
                       num_images=images, control=control, control_steps=control_steps,
                       drive=None if drive is None else str(drive), drive_frames=drive_frames,
                       drive_match_range=drive_match_range,
                       captured_directions=captured_directions)
    # one eval writes a folder at a time (its lock, taken before minutes of fitting), and
    # a failed or interrupted one leaves no empty folder behind
    with folders_kept_only_on_success(out_dir), folder_lock(out_dir, "evaluation"):
        res = evaluate_run(r, ds, opts, out_dir)
    print()
    print(compare_markdown([res]), end="")
    print(f"wrote {out_dir / 'metrics.json'}, {out_dir / 'metrics.md'} and "
          f"{len(res.get('images', []))} images in {res['seconds']:.0f} s")
