#!/usr/bin/env python
"""Handheld benchmark: cameras of a low-parallax clip with a background that sways.

Renders the built-in handheld scene's capture (`flamenerf synth --handheld`: a phone held in
the hand shakes a few degrees and centimetres, the head moves on its own, a far backdrop,
leaves that sway by themselves) and registers its background as preprocessing does (the
person masked out, the scene's true focal length standing in for the face solve's), once
with both camera models and once with structure from motion alone (what preprocessing did
before the rotation model). Against the ground truth, after the one rotation that takes the
solved world onto the true one:

  camera rotation error    median / max over frames (deg)
  head rotation error      the head's pose composed from the face's true camera-from-head
  moving background        precision / recall of the flagged pixels against the leaves
                           (on the background: the person is masked), share flagged

    python benchmarks/bench_handheld.py --size 128 --frames 60 --json docs/bench/handheld.json

Prints the figures next to the targets and writes JSON. With `--dataset DIR` it also writes
the handheld scene (`make_scene(handheld=True)`) with the cameras and head poses replaced by
the solved ones (both models; the world put onto the true one by the head's mean pose) and
its moving masks by the detected ones, to train and evaluate on as a preprocessed clip
would be:

    python benchmarks/bench_handheld.py --size 128 --frames 60 --dataset scenes/handheld_solved
    python benchmarks/bench_head_pose.py --scene scenes/handheld_solved --size 128 \
        --variants "weighted:;unweighted:loss.moving_weight=1.0" --json docs/bench/handheld_train.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from flamenerf.geometry import rotation_angle_deg
from flamenerf.synthetic.scene import handheld_capture
from flamenerf.tracking.background import BackgroundOptions, register_background
from flamenerf.tracking.world import compose_world

CV_GL = np.diag([1.0, -1.0, -1.0, 1.0])




def grow(mask: np.ndarray, px: int) -> np.ndarray:
    """The person mask a little generous, as preprocessing's is."""
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def run(frames: list, models: tuple[str, ...], keep: dict | None = None) -> dict:
    size = frames[0].rgb.shape[1]
    person = [grow(f.person, max(2, size // 40)) for f in frames]
    truth_c2w = np.stack([f.c2w for f in frames])
    truth_head = np.stack([f.head_pose for f in frames])
    cam_from_head = np.linalg.inv(truth_c2w) @ truth_head
    opts = BackgroundOptions(camera_models=models)
    t0 = time.perf_counter()
    reg = register_background(((k, f.rgb, p) for k, (f, p) in enumerate(zip(frames, person))),
                              opts, focal=float(frames[0].intrinsics.fx))
    out = {"models_tried": list(models), "status": reg.status, "reason": reg.reason,
           "camera_model": reg.camera_model, "seconds": time.perf_counter() - t0,
           "reprojection_error_px": reg.reprojection_error_px,
           "choice": reg.details.get("camera_model_choice")}
    if reg.status != "registered":
        return out
    ok = reg.registered
    world = compose_world(cam_from_head[ok], reg.subset(reg.ids[ok]), np.zeros(3))
    if keep is not None:
        keep.update(world=world, registered=ok, moving=reg.moving)
    gt_c, gt_h = truth_c2w[ok], truth_head[ok]
    G = Rotation.from_matrix(np.einsum("nab,ncb->nac", gt_c[:, :3, :3],
                                       world.c2w[:, :3, :3])).mean().as_matrix()
    cam_err = rotation_angle_deg(G @ world.c2w[:, :3, :3], gt_c[:, :3, :3])
    out.update(registered=int(ok.sum()), frames=len(frames), case=world.case,
               camera_rotation_error_deg={"median": float(np.median(cam_err)),
                                          "max": float(cam_err.max())},
               true_camera_rotation_max_deg=float(rotation_angle_deg(
                   gt_c[:, :3, :3], np.repeat(gt_c[:1, :3, :3], len(gt_c), 0)).max()))
    if world.head_pose is not None:
        head_err = rotation_angle_deg(G @ world.head_pose[:, :3, :3], gt_h[:, :3, :3])
        out["head_rotation_error_deg"] = {"median": float(np.median(head_err)),
                                          "max": float(head_err.max())}
    if reg.moving is not None:
        est = np.stack([np.asarray(Image.fromarray(m.astype(np.uint8) * 255).resize(
            (size, size), Image.Resampling.NEAREST)) > 0 for m in reg.moving])
        truth = np.stack([f.moving for f in frames]) & ~np.stack(person)
        hit = float((est & truth).sum())
        out["moving"] = {"precision": hit / max(est.sum(), 1),
                         "recall": hit / max(truth.sum(), 1),
                         "share_flagged": reg.details.get("moving_background_share"),
                         "share_true": float(truth.sum() / max((~np.stack(person)).sum(), 1))}
    return out


def write_solved(out: Path, frames: list, world, registered: np.ndarray, seed: int,
                 moving: np.ndarray | None) -> None:
    """The handheld scene with the capture's cameras, head poses and face meshes replaced
    by the solved world's (put onto the true world by the head's mean pose), and its
    moving masks by the detected ones (none where nothing was detected)."""
    import imageio.v3 as iio

    from flamenerf.synthetic.scene import make_scene
    from flamenerf.tracking.world import mean_pose

    if not registered.all():
        raise SystemExit("not every frame registered: nothing to write")
    size = frames[0].rgb.shape[1]
    make_scene(out, seed=seed, size=size, frames=len(frames), handheld=True, overwrite=True)
    truth = np.stack([f.head_pose for f in frames])
    align = mean_pose(truth) @ np.linalg.inv(mean_pose(world.head_pose))
    c2w, head = align @ world.c2w, align @ world.head_pose
    tj = out / "transforms.json"
    meta = json.loads(tj.read_text())
    mesh = dict(np.load(out / "face_mesh.npz"))
    for pos, fr in enumerate(meta["frames"]):
        k = fr.get("frame_index")
        if k is None:
            continue
        fr["transform_matrix"] = c2w[k].tolist()
        if moving is not None and fr.get("moving_path"):
            m = Image.fromarray(moving[k].astype(np.uint8) * 255).resize(
                (size, size), Image.Resampling.NEAREST)
            iio.imwrite(out / fr["moving_path"], np.asarray(m))
        fr["head_pose"] = head[k].tolist()
        move = head[k] @ np.linalg.inv(truth[k])
        v = mesh["vertices"][pos]
        mesh["vertices"][pos] = (v @ move[:3, :3].T + move[:3, 3]).astype(v.dtype)
    meta.setdefault("source", {})["cameras"] = "solved (bench_handheld.py)"
    tj.write_text(json.dumps(meta, indent=1))
    np.savez(out / "face_mesh.npz", **mesh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--dataset", type=Path, default=None)
    a = ap.parse_args()
    t0 = time.perf_counter()
    frames = list(handheld_capture(a.seed, a.size, a.frames, workers=0))
    render_s = time.perf_counter() - t0
    solved: dict = {}
    results = {"both models": run(frames, ("sfm", "rotation"), solved),
               "structure from motion alone": run(frames, ("sfm",))}
    for name, r in results.items():
        print(f"{name}: {r['status']} ({r['camera_model']}): {r['reason']}")
        if "camera_rotation_error_deg" in r:
            c, h = r["camera_rotation_error_deg"], r.get("head_rotation_error_deg", {})
            print(f"  camera rotation error median {c['median']:.3f} deg (target <= 0.3), max "
                  f"{c['max']:.3f}; true shake up to {r['true_camera_rotation_max_deg']:.1f} "
                  f"deg; head rotation error median {h.get('median', float('nan')):.3f} deg "
                  f"(target <= 1)")
        if "moving" in r:
            m = r["moving"]
            print(f"  moving background: precision {m['precision']:.2f}, recall "
                  f"{m['recall']:.2f}; flagged {100 * (m['share_flagged'] or 0):.1f}% of the "
                  f"background (true {100 * m['share_true']:.1f}%)")
    if a.dataset is not None:
        write_solved(a.dataset, frames, solved["world"], solved["registered"], a.seed,
                     solved.get("moving"))
        print(f"wrote {a.dataset} (the solved cameras)")
    if a.json:
        doc = {"command": f"python benchmarks/bench_handheld.py --size {a.size} --frames "
                          f"{a.frames} --seed {a.seed}",
               "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
               "cpus": __import__("os").cpu_count(), "render_seconds": render_s,
               "results": results}
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1)
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
