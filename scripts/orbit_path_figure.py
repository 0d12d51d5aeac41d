"""Orbit renders of a run along three camera paths, and how far each leaves the capture.

    python scripts/orbit_path_figure.py RUN [--dataset D] [--fractions 0 0.33 0.67 1]
        [--out docs/orbit_paths.png] [--json docs/bench/orbit_paths.json]
        [--paths before capture default] [--frame0]

Rows (RGB above depth): (1) an arc at frame 0's distance and height swinging out to the end
of the room's captured azimuths, looking at the head (the default orbit before
2026-11-25); (2) the capture's distance and height at each azimuth, the same swing, the head
kept where frame 0's camera sees it; (3) the default orbit now: as (2), within the azimuths
the head was also seen from (`rendering/cameras.py`). Columns: fractions of each path's
swing towards its far end. The head is held at frame 0's pose and frame 0's expression and
codes are used, as `flamenerf render RUN --camera orbit` does. `--paths` picks rows,
`--frame0` puts frame 0's training image (over black) before them.

The JSON gives, per path, the largest distance of its cameras from the nearest training
camera centre, and the largest view of the head beyond the azimuths it was seen from.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.33, 0.67, 1.0])
    ap.add_argument("--scale", type=int, default=2, help="pixel repetition of the figure")
    ap.add_argument("--out", type=Path, default=Path("docs/orbit_paths.png"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--paths", nargs="+", choices=["before", "capture", "default"],
                    default=["before", "capture", "default"])
    ap.add_argument("--frame0", action="store_true", help="frame 0's image in front")
    ap.add_argument("--made-by", default="", help="how the run was made (kept in the JSON)")
    args = ap.parse_args()
    from flamenerf.data.dataset import reference_position
    from flamenerf.data.head_pose import canonical_from_world, transform_points
    from flamenerf.data.prior import dataset_dilation
    from flamenerf.geometry import look_at
    from flamenerf.images import colorize_depth, hstack, resize_image, vstack
    from flamenerf.io import save_png
    from flamenerf.rendering import cameras as C
    from flamenerf.rendering.reanimate import depth_range, render_sequence
    from flamenerf.training.run import load_run

    torch.set_num_threads(2)
    run = load_run(args.run, "cpu")
    ds = run.dataset(args.dataset)
    run.attach(ds, True)
    intr = run.train_intrinsics(ds)
    rig = C.rig_from_dataset(ds)
    ref = reference_position(ds)
    room = (float(rig.captured[:, 0].min()), float(rig.captured[:, 0].max()))
    far_room = room[1] if abs(room[1]) >= abs(room[0]) else room[0]
    lo, hi = rig.azimuth_range
    far_now = hi if abs(hi) >= abs(lo) else lo
    fr = np.asarray(args.fractions)
    e0, e1 = rig.basis()
    v0 = rig.eye - rig.center

    def arc(a: float) -> np.ndarray:  # frame 0's camera turned about the head's `up` axis
        turn = Rotation.from_rotvec(np.radians(a) * rig.up).as_matrix()
        return look_at(rig.center + turn @ v0, rig.center, rig.up)

    every = {
        "before": ("arc at frame 0's distance, the room's azimuths (before)",
                   lambda f: arc(f * far_room)),
        "capture": ("the capture's distance and height, the room's azimuths",
                    lambda f: rig.aim(rig.clamp(rig.orbit_eye(f * far_room)))),
        "default": ("default orbit (the capture's, within the head's azimuths)",
                    lambda f: rig.aim(rig.clamp(rig.orbit_eye(f * far_now)))),
    }
    paths = {every[k][0]: np.stack([every[k][1](f) for f in fr]) for k in args.paths}
    train = ds.split("train")
    eyes = np.stack([f.c2w[:3, 3] for f in train])
    T = canonical_from_world(ds, train)
    head_eyes = eyes if T is None else transform_points(T, eyes[:, None])[:, 0]

    def azimuth(p: np.ndarray) -> np.ndarray:
        v = p - rig.center
        return np.degrees(np.arctan2(v @ e1, v @ e0))

    seen = azimuth(head_eyes)
    om, ph = run.frame_codes(ds.frames[ref].frame_index)
    beta = np.repeat(ds.frames[ref].expression[None], len(fr), 0)
    rows, report = [], {}
    rng = None
    for name, poses in paths.items():
        frames = list(render_sequence(run.model, ds, intr, poses, beta,
                                      ds.face_vertices[ref], om, ph, dataset_dilation(ds)))
        rng = rng or depth_range(frames[0], ds.near, ds.far)
        lead = [[resize_image(ds.load_image(ds.frames[ref]), intr.w, intr.h)],
                [np.zeros_like(frames[0].rgb)]] if args.frame0 else [[], []]
        rows.append(hstack(lead[0] + [f.rgb for f in frames]))
        rows.append(hstack(lead[1] + [colorize_depth(f.depth, *rng) for f in frames]))
        cams = poses[:, :3, 3]
        off = np.linalg.norm(cams[:, None] - eyes[None], axis=-1).min(1)
        az = azimuth(cams)
        beyond = np.maximum(0, np.maximum(az - seen.max(), seen.min() - az))
        report[name] = {"azimuths_deg": np.round(az, 2).tolist(),
                        "max_distance_from_capture_cm": round(100 * float(off.max()), 2),
                        "max_beyond_head_azimuths_deg": round(float(beyond.max()), 2)}
        print(f"{name}: farthest {100 * off.max():.1f} cm from a training camera, "
              f"{beyond.max():.1f} deg beyond the head's captured azimuths")
    img = vstack(rows).repeat(args.scale, 0).repeat(args.scale, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(args.out, img)
    print(f"wrote {args.out}: rows (RGB, depth) = {'; '.join(paths)}")
    if args.json:
        out = {"command": "python scripts/orbit_path_figure.py " + " ".join(
            str(a) for a in [args.run] + (["--dataset", args.dataset] if args.dataset else [])),
            "run": str(args.run), "run_made_by": args.made_by, "fractions": fr.tolist(),
            "head_azimuths_seen_deg": [round(float(seen.min()), 2), round(float(seen.max()), 2)],
            "room_azimuths_deg": [round(x, 2) for x in room], "paths": report}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
