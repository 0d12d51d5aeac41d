"""A strip of chosen frames of `flamenerf render` videos, one row per video (the README's
docs/real_keyframes.png and docs/builtin_blink_leak.png), or one column per video with
`--columns` (docs/demo_reanimation_frames.png, from the demo's side-by-side video).

    python scripts/video_strip.py R/kf.mp4 R/kf_depth.mp4 --frames 0 15 29 30 45 59 \
        --out docs/real_keyframes.png
    python scripts/video_strip.py R/blink.mp4 R/brow.mp4 --frames 0 1 --diff \
        --out docs/builtin_blink_leak.png
    python scripts/video_strip.py demo/reanimation_sbs.mp4 --frames 0 3 6 9 --columns \
        --scale 3 --out docs/demo_reanimation_frames.png

`--diff` appends |last frame - first frame| x 4 (grey) to each row; `--scale K` enlarges
every pixel to K x K (a 64 px demo is small on a page).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description="A strip of chosen frames of videos: one row per "
                                 "video (one column with --columns).")
    ap.add_argument("videos", type=Path, nargs="+")
    ap.add_argument("--frames", type=int, nargs="+", required=True,
                    help="frame numbers (from 0) to show from each video")
    ap.add_argument("--diff", action="store_true",
                    help="append |last frame - first frame| x 4 (grey) to each row")
    ap.add_argument("--columns", action="store_true", help="one column per video")
    ap.add_argument("--scale", type=int, default=1,
                    help="enlarge every pixel to K x K (a 64 px video is small on a page)")
    ap.add_argument("--out", type=Path, required=True, help="the PNG to write")
    a = ap.parse_args()
    from flamenerf.data.video import read_frames
    from flamenerf.images import abs_diff, hstack, vstack
    from flamenerf.io import save_png

    rows = []
    for video in a.videos:
        frames = read_frames(video)
        if max(a.frames) >= len(frames):
            raise SystemExit(f"{video}: {len(frames)} frames, asked for frame {max(a.frames)}")
        picked = [frames[i].astype(np.float32) / 255 for i in a.frames]
        if a.diff:
            picked.append(abs_diff(picked[-1], picked[0], 4.0))
        rows.append(vstack(picked) if a.columns else hstack(picked))
    img = hstack(rows) if a.columns else vstack(rows)
    save_png(a.out, np.clip(img.repeat(a.scale, 0).repeat(a.scale, 1), 0, 1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
