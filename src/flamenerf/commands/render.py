"""`flamenerf render`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from typing import Annotated

import tyro

from flamenerf.rendering.videos import RenderOptions


def render(opts: Annotated[RenderOptions, tyro.conf.OmitArgPrefixes, tyro.conf.arg(name="")]
           ) -> None:
    """Render a re-animation video: frame 0's codes (a split's frames: their own), driven by
    expressions, along a camera path.

    Expressions come from one of: --expressions FILE (.json: a `flamenerf track` file, a
    list of vectors, or {name: value} objects; .npy; .csv with an optional header of
    control names) or --expressions KEYFRAME... (e.g. `jawOpen=0.8` `mouthSmileLeft=1,
    browInnerUp=0.5`: ease from the base expression to each keyframe in turn and back) or
    --expressions tour (each control the training frames show, in turn, to the end of
    its range and back: what the run can do);
    --split NAME (a dataset split's expressions, cameras and face meshes, e.g. reanimate;
    `capture`: the clip as filmed); --drive VIDEO (tracked like `flamenerf track`). Named
    controls are mapped onto the run's; missing ones are 0. Without any, frame 0's
    expression is held. --edit changes controls in every frame of the source: `--split
    capture --edit mouthSmile+=0.3 --side-by-side` is the clip with a broader smile (both
    sides), beside the frames as filmed; `--edit-during 2:4` only from 2 s to 4 s.

    Camera paths (--camera): static (frame 0's camera), orbit (around the head, at the
    capture's distance and height), spiral, dolly, or a JSON file of camera-to-world
    poses; `auto` uses a split's own cameras (`split` asks for them), else static. Paths
    keep the head (the centroid of frame 0's face mesh) where frame 0's camera sees it and
    stay where the capture filmed from unless --amplitude asks for more (for a moving
    head: where it filmed the head from too; a still camera gives a still path). The
    prior's mask
    for each frame is the face mesh of that frame's expression (the split's own meshes
    with --split, moved by --edit) rasterised for that camera with the dataset's dilation.

    Writes OUT (H.264 mp4), plus OUT_depth.mp4 with --depth and OUT_sbs.mp4 (driving |
    result | depth) with --side-by-side. See docs/evaluation.md.

    Example: flamenerf render runs/fast --expressions jawOpen=0.8 --camera orbit --depth
    """
    from flamenerf.rendering.videos import render_videos

    print(render_videos(opts).describe())
