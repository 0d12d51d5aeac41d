"""How much of an edit of the filmed clip (`render --split S --edit ...`) shows.

Built-in scene runs (`--run`, ground truth): the split's frames (default `val`, which no
run trained on), each edit applied as `render` applies it (its own plan: the codes
`--codes` names, the edited expressions, the prior's meshes moved by the edit), against the
scene rendered again with the edited expressions at the same cameras. Reported per edit:
the face's PSNR of the edited render, of the unedited render against the same truth (what
a model that ignores the edit shows), and the mean change the edit makes on the face's
pixels. A Nerfies-variant run (no β) shows no edit: its two figures are equal.

`--codes first own` renders each with frame 0's codes and with each frame's own (render's
`--codes`); results are keyed by it.

Real-clip runs (`--retrack-run`): the capture rendered as filmed, with a broader smile,
with raised brows and with every control stilled (`all*=0`; render's plans again), each
re-tracked by MediaPipe's face landmarker; reported: the plain render's PSNR against the
filmed frames (training and held-out frames apart), per control the clip's tracked mean,
the re-tracked means of each render, each edit's commanded mean, and the plain render's
correlation with the clip; and per edit where it repainted the face: the mean change of
colour inside the eyes', brows' and lips' outlines (the plain render's re-tracked
landmarks; `control.part_change`), and in the prior silhouette's last 2 pixels, where β
stops (`control.edge_change`: a seam). A brow edit that leaves the brows and repaints the
eyes, or the hair at the silhouette's edge, shows there.

    python benchmarks/bench_edit.py --run RUN... [--retrack-run RUN...] [--split val]
        [--codes auto|first|own ...] [--threads 2] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BUILTIN_EDITS = {
    "jawOpen+=0.5": ["jawOpen+=0.5"],
    "smiles=1": ["mouthSmileLeft=1,mouthSmileRight=1"],
    "browInnerUp=1": ["browInnerUp=1"],
    "mouthPucker=1": ["mouthPucker=1"],
    "frowns=1": ["mouthFrownLeft=1,mouthFrownRight=1"],
}
# re-tracked edits of a real clip: two that add (a smile, raised brows) and one that removes
# every expression (what a frame's own ω could keep, if it had learnt part of the frame's
# face)
REAL_EDITS = {"edited": ["mouthSmileLeft+=0.3,mouthSmileRight+=0.3"],
              "brows": ["browInnerUp+=0.2"], "stilled": ["all*=0"]}
REAL_REPORTED = ("mouthSmileLeft", "mouthSmileRight", "mouthUpperUpLeft", "mouthUpperUpRight",
                 "jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "eyeWideLeft", "eyeWideRight",
                 "eyeSquintLeft", "eyeSquintRight", "browInnerUp", "browOuterUpLeft",
                 "browOuterUpRight", "mouthFrownLeft", "mouthFrownRight")


def plan(run: Path, split: str, edit: list[str] | None, threads: int, out: Path,
         codes: str = "auto"):
    from flamenerf.rendering.videos import RenderOptions, plan_render

    return plan_render(RenderOptions(run, out=out, split=split, edit=edit, device="cpu",
                                     threads=threads, overwrite=True, codes=codes),
                       log=lambda _: None)


def builtin(run: Path, split: str, threads: int, tmp: Path, codes: str) -> dict:
    from flamenerf.evaluation.metrics import psnr
    from flamenerf.synthetic.scene import scene_from_dataset

    plain = plan(run, split, None, threads, tmp / "x.mp4", codes)
    scene = scene_from_dataset(plain.ds)
    frames = plain.ds.split(split)
    plain_rgb = [f.rgb for f in plain.frames()]
    out = {}
    for label, items in BUILTIN_EDITS.items():
        p = plan(run, split, items, threads, tmp / "x.mp4", codes)
        rows = []
        for fr, pred, before, values in zip(frames, p.frames(), plain_rgb, p.values):
            body = fr.extra.get("body_pose")
            gt = scene.render(fr.c2w, np.clip(values, 0, 1),
                              None if body is None else np.asarray(body), p.intr)
            face = gt.mask
            rows.append((psnr(pred.rgb, gt.rgb, face), psnr(before, gt.rgb, face),
                         float(np.abs(pred.rgb - before)[face].mean())))
        r = np.mean(rows, 0)
        out[label] = {"psnr_face_edited": round(float(r[0]), 2),
                      "psnr_face_unedited": round(float(r[1]), 2),
                      "mean_change_on_face": round(float(r[2]), 4)}
        print(f"{run.name} {codes} codes {label}: edited {r[0]:.2f} dB, unedited {r[1]:.2f} dB against "
              f"the edited truth; change {r[2]:.4f}", flush=True)
    return out


def clip_psnr(p, frame, rgb: np.ndarray) -> tuple[float, float]:
    """PSNR of a render of a capture frame against the filmed frame: whole, and on the
    face's silhouette."""
    from flamenerf.evaluation.metrics import psnr
    from flamenerf.images import resize_image

    h, w = rgb.shape[:2]
    img, mask = p.ds.load_image(frame), p.ds.load_mask(frame)
    if img.shape[:2] != (h, w):
        img = resize_image(img, w, h)
        mask = resize_image(mask.astype(np.float32)[..., None].repeat(3, -1), w, h)[..., 0] > 0.5
    return psnr(rgb, img), psnr(rgb, img, mask)


def retracked(run: Path, threads: int, tmp: Path, codes: str) -> dict:
    from flamenerf.data.dataset import CAPTURE
    from flamenerf.evaluation.control import (Retracker, edge_change, part_change,
                                              part_outlines)

    track, outlines = Retracker(), part_outlines()
    try:
        reads, commanded, fidelity, changes, seams = {}, {}, [], {}, {}
        trained, plain = None, []  # the plain render's images and re-tracked landmarks
        for label, edit in (("plain", None), *REAL_EDITS.items()):
            p = plan(run, CAPTURE, edit, threads, tmp / "x.mp4", codes)
            trained = {f.frame_index for f in p.ds.training_frames()}
            scores, changed, edges = [], [], []
            for i, (fr, rendered) in enumerate(zip(p.ds.split(CAPTURE), p.frames())):
                got = track.read(rendered.rgb)
                scores.append(None if got is None else got[0])
                if label == "plain":  # the filmed frame is the plain render's truth
                    fidelity.append((*clip_psnr(p, fr, rendered.rgb), fr.frame_index in
                                     trained))
                    plain.append((rendered.rgb, None if got is None else got[1],
                                  rendered.mask))
                else:
                    edges.append(edge_change(plain[i][0], rendered.rgb, plain[i][2],
                                             rendered.mask))
                    if plain[i][1] is not None:
                        changed.append(part_change(plain[i][0], rendered.rgb, plain[i][1],
                                                   outlines))
            reads[label], commanded[label] = scores, p.values
            if changed:
                changes[label] = {k: round(float(np.nanmean([c[k] for c in changed])), 4)
                                  for k in outlines}
                print(f"{run.name} {codes} codes {label}: mean change of colour in the "
                      + ", ".join(f"{k} {v}" for k, v in changes[label].items()), flush=True)
            if edges:
                seams[label] = round(float(np.nanmean(edges)), 4)
                print(f"{run.name} {codes} codes {label}: mean change of colour in the "
                      f"silhouette's last 2 px {seams[label]}", flush=True)
        clip = p.ds.expression_matrix(p.ds.split(CAPTURE))
        names = p.ds.expression_names
    finally:
        track.close()
    fid = np.asarray(fidelity)
    vs_clip = {}
    for part, rows in (("all", fid), ("train", fid[fid[:, 2] == 1]),
                       ("held_out", fid[fid[:, 2] == 0])):
        if len(rows):
            m = rows[:, :2].mean(0)
            vs_clip[part] = {"frames": len(rows), "psnr": round(float(m[0]), 2),
                             "psnr_face": round(float(m[1]), 2)}
            print(f"{run.name} {codes} codes: plain render against the clip, {part} frames "
                  f"({len(rows)}): {m[0]:.2f} dB, face {m[1]:.2f} dB", flush=True)
    out = {"edits": REAL_EDITS, "frames": len(clip), "plain_vs_clip": vs_clip,
           "detected": {k: sum(s is not None for s in v) for k, v in reads.items()},
           "part_change": changes, "edge_change": seams}
    for name in REAL_REPORTED:
        if name not in names:
            continue
        j = names.index(name)
        ok = [i for i in range(len(clip)) if all(r[i] is not None for r in reads.values())]
        got = {k: np.array([r[i][name] for i in ok]) for k, r in reads.items()}
        out[name] = {"clip": round(float(clip[ok, j].mean()), 3),
                     "plain_vs_clip_correlation": round(float(np.corrcoef(got["plain"],
                                                                          clip[ok, j])[0, 1]), 3)}
        for k, v in got.items():
            out[name][k] = round(float(v.mean()), 3)
            if k in REAL_EDITS:
                out[name][f"{k}_commanded"] = round(float(commanded[k][ok, j].mean()), 3)
        print(f"{run.name} {codes} codes {name}: clip {out[name]['clip']}, plain render "
              f"{out[name]['plain']}, " + ", ".join(
                  f"{k} {out[name][k]} (commanded {out[name][f'{k}_commanded']})"
                  for k in REAL_EDITS), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, nargs="*", default=[],
                    help="built-in scene runs (ground truth)")
    ap.add_argument("--retrack-run", type=Path, nargs="*", default=[],
                    help="runs of real clips (re-tracked)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--codes", nargs="+", default=["auto"], choices=["auto", "first", "own"],
                    help="render's --codes: each frame's own or frame 0's (several: each)")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    t0 = time.perf_counter()
    res = {"what": __doc__.splitlines()[0],
           "machine": {"cpu": platform.processor() or platform.machine(),
                       "platform": platform.platform(), "cpus": os.cpu_count()},
           "command": "python benchmarks/bench_edit.py " + " ".join(sys.argv[1:]),
           "split": a.split, "builtin": {}, "retracked": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for codes in a.codes:
            for run in a.run:
                res["builtin"].setdefault(codes, {})[str(run)] = builtin(
                    run, a.split, a.threads, Path(tmp), codes)
            for run in a.retrack_run:
                res["retracked"].setdefault(codes, {})[str(run)] = retracked(
                    run, a.threads, Path(tmp), codes)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
