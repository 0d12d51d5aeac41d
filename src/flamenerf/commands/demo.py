"""`flamenerf demo`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path


def demo(
    out: Path = Path("demo"),
    size: int = 96,
    frames: int = 100,
    steps: int = 300,
    train_size: int = 64,
    batch_rays: int = 2048,
    seed: int = 0,
) -> None:
    """Try flamenerf end to end on the built-in scene: a few minutes on a laptop CPU.

    Synthesizes the scene, trains the `demo` preset (`fast` with fewer, smaller steps),
    then renders two videos at the scene's resolution, each with its depth video and a
    side-by-side: a tour of the expression controls along an orbiting camera (`render
    --expressions tour`: each control in turn, from frame 0's expression up to its 99th
    percentile in the training frames and back), and the re-animation of the scene's
    `reanimate` split (novel expressions from novel cameras, one video frame each at 4
    fps; its side-by-side puts the ground truth beside the render).

    Writes OUT/scene (dataset), OUT/run (trained run), OUT/expressions.mp4 and
    OUT/reanimation.mp4, each with _depth.mp4 and _sbs.mp4. Re-running reuses what exists.

    Example: flamenerf demo --out demo

    Args:
        out: Output folder.
        size: Resolution of the synthesized scene and of the videos.
        frames: Capture frames of the synthesized scene.
        steps: Training steps.
        train_size: Training resolution.
        batch_rays: Rays per training step.
        seed: Scene seed.
    """
    from flamenerf.commands.render import render
    from flamenerf.commands.synth import synth
    from flamenerf.errors import UserError

    # before the scene is made: a bad training option would otherwise stop the demo later
    for flag, v in (("--steps", steps), ("--batch-rays", batch_rays)):
        if v < 1:
            raise UserError(f"{flag} {v}: must be at least 1")
    if not 1 <= train_size <= size:
        raise UserError(f"--train-size {train_size}: must be in 1..{size} (--size)")
    from flamenerf.rendering.videos import RenderOptions
    from flamenerf.config import preset
    from flamenerf.training.checkpoint import latest_checkpoint
    from flamenerf.training.trainer import train

    scene, run = out / "scene", out / "run"
    if not (scene / "transforms.json").exists():
        print(f"[1/3] synthesizing the built-in scene into {scene}")
        synth(scene, seed=seed, size=size, frames=frames, overwrite=True)
    else:
        print(f"[1/3] reusing {scene}")
    cfg = preset("demo")
    cfg.train.downscale = size / train_size
    cfg.train.batch_rays = batch_rays
    ck = latest_checkpoint(run)
    print(f"[2/3] training the demo preset (fast, smaller) for {steps} steps into {run}")
    if train(scene, run, cfg, resume=ck is not None, steps=steps).interrupted:
        from flamenerf.errors import Interrupted

        raise Interrupted(f"run saved in {run}; the same `flamenerf demo` command resumes it")
    print("[3/3] rendering the videos")
    videos = dict(size=size, depth=True, side_by_side=True, overwrite=True)
    render(RenderOptions(run, out=out / "expressions.mp4", expressions=["tour"],
                         camera="orbit", **videos))
    # the split's own cameras: its side-by-side is then the ground truth beside the render
    # (at render's rate for frames that are not a clip's, expressions.STILLS_FPS)
    render(RenderOptions(run, out=out / "reanimation.mp4", split="reanimate", camera="auto",
                         **videos))
    print(f"done: {out / 'expressions.mp4'} and {out / 'reanimation.mp4'} (each + _depth, "
          f"_sbs); `flamenerf view {run}` to play with it; `flamenerf render {run} --split "
          "capture --edit jawOpen+=0.5 --side-by-side` renders the filmed clip with its jaw "
          "opened wider, beside its frames")
