"""How the tracker reads the β -> mesh model's own sweeps: the ceiling of `eval`'s control
sweep for a renderer that follows the mesh exactly.

For a preprocessed dataset (MediaPipe meshes with irises), each control that varies in the
training frames is swept as `eval` sweeps it (5 steps over its 5th-95th percentile, the
other controls at the reference frame's β, alone and with its companions), the mesh of each
step is projected into the reference camera and scored by MediaPipe's blendshape stage
(tracking/blendshapes.py): gain and correlation of the swept control's score. Compared:
the least-squares fit and the tracker-consistent one (the dataset's stored model, or
fitted here with --fit). Also each model's RMS miss of the train and val frames' meshes.

With --warp, each sweep is also rendered as the reference frame's own image warped in 2D
by the mesh's projected motion (piecewise linear over the projected vertices) and
re-tracked by the face landmarker, as `eval` re-tracks renders: how far a picture whose
geometry follows the mesh exactly, with the captured appearance, is read as commanded.
With --appearance, also with a linear appearance model of the clip (an active appearance
model's reading): each training frame warped onto the reference frame's tracked mesh, a
ridge regression of that shape-normalised image on β per pixel (the ridge chosen on the val
frames), and each sweep rendered as the reference image plus the regression's change for
its β, then warped as above: what the clip's frames say each control looks like, linearly.

    python benchmarks/bench_mesh_model.py DATASET [--fit] [--warp] [--appearance]
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--fit", action="store_true",
                    help="fit the tracker-consistent model here (default: the stored one)")
    ap.add_argument("--warp", action="store_true",
                    help="also re-track the reference image warped by each sweep's meshes")
    ap.add_argument("--appearance", action="store_true",
                    help="also with a linear appearance model of the clip (see above)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()

    from flamenerf.data.companions import dataset_companions
    from flamenerf.data.dataset import load_dataset, reference_position
    from flamenerf.data.mesh_model import expression_model_residual, fit_dataset_expression_model
    from flamenerf.evaluation.control import control_response
    from flamenerf.meshes import expression_mesh
    from flamenerf.tracking.blendshapes import BlendshapeStage
    from flamenerf.tracking.expression_model import (applies, fit_for_dataset,
                                                      pinhole_projection)

    ds = load_dataset(a.dataset)
    if not applies(ds):
        raise SystemExit(f"{a.dataset}: not MediaPipe meshes with irises (nothing to read)")
    stage = BlendshapeStage()
    models = {"least squares": fit_dataset_expression_model(ds, stored=False)}
    t0 = time.perf_counter()
    if a.fit:
        models["tracker-consistent"] = fit_for_dataset(ds, stage=stage)
    elif ds.mesh_model is not None:
        models["tracker-consistent"] = fit_dataset_expression_model(ds)
    fit_s = time.perf_counter() - t0

    ref = ds.frames[reference_position(ds)]
    project = pinhole_projection(ds.intrinsics, ref.c2w)
    train = ds.expression_matrix(ds.training_frames())
    comp = dataset_companions(ds)
    out = {"machine": platform.node(), "dataset": str(a.dataset), "fit_seconds": fit_s,
           "models": {}}
    change = None
    if a.appearance:
        change, out["appearance_model"] = appearance_change(ds, ref)
        print(f"linear appearance model: ridge {out['appearance_model']['ridge']}, val frames' "
              f"shape-normalised faces {out['appearance_model']['val_psnr']:.2f} dB "
              f"(their mean: {out['appearance_model']['val_psnr_mean']:.2f} dB)")
    for label, (neutral, basis) in models.items():
        def projected(beta, neutral=neutral, basis=basis):
            mesh = expression_mesh(neutral.double(), basis.double(), torch.as_tensor(beta))
            return project(mesh.numpy())[0]

        def read(beta):
            """The mesh of β scored by the tracker: `eval`'s sweep with a perfect render."""
            return dict(zip(stage.names, map(float, stage.scores(projected(beta)))))

        base = ref.expression.astype(np.float64)
        res = control_response(lambda beta: beta, ds.expression_names, base, train, read,
                               companions=comp)["controls"]
        misses = {split: float(expression_model_residual(ds, neutral, basis, ds.split(split))
                               .pow(2).mean().sqrt()) * 1e3
                  for split in ("train", "val") if ds.split(split)}
        out["models"][label] = {**summary(res), "rms_miss_mm": misses}
        m = out["models"][label]
        if a.warp:
            m["warp"] = image_sweeps(warp_renderer(ds, ref, projected, base),
                                     ds, base, train, comp)
        if change is not None:
            m["appearance"] = image_sweeps(warp_renderer(ds, ref, projected, base, change),
                                           ds, base, train, comp)
        print(f"{label:20s} sweeps read as commanded (gain >= 0.5, corr >= 0.9): "
              f"{m['passing_alone']} alone, {m['passing_with_companions']} with companions, "
              f"of {m['swept']}; mesh miss train {misses.get('train', float('nan')):.3f} mm, "
              f"val {misses.get('val', float('nan')):.3f} mm")
        for key, what in (("warp", "the reference image warped by them"),
                          ("appearance", "with the linear appearance model")):
            if key in m:
                print(f"{'':20s} {what}, re-tracked: {m[key]['passing_alone']} alone, "
                      f"{m[key]['passing_with_companions']} with companions")
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))


def _pixel_centres(h: int, w: int) -> np.ndarray:
    return np.stack(np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5), -1).reshape(-1, 2)


def _warp(image: np.ndarray, pixels: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Backward warp: output pixel p takes image at p + offsets[p], bilinearly.
    (H, W, 3) -> (H, W, 3)"""
    from scipy.ndimage import map_coordinates

    h, w = image.shape[:2]
    x, y = (pixels + offsets - 0.5).T  # pixel centres -> array indices
    return np.stack([map_coordinates(image[..., c], [y, x], order=1, mode="reflect")
                     .reshape(h, w) for c in range(image.shape[2])], -1)


def warp_renderer(ds, ref, projected, base, change=None):
    """β -> the reference image (plus change(β) - change(base) where given: (H·W, 3)
    colour) warped piecewise linearly by the projected mesh's motion from the base β."""
    from scipy.interpolate import LinearNDInterpolator

    image = ds.load_image(ref)
    start = projected(base)
    h, w = image.shape[:2]
    pixels = _pixel_centres(h, w)

    def render(beta):
        picture = image
        if change is not None:
            picture = np.clip(image + (change(beta) - change(base)).reshape(h, w, 3), 0, 1)
        now = projected(beta)
        # each output pixel looks up where its point of the mesh started
        back = LinearNDInterpolator(now, start - now, fill_value=0.0)(pixels)
        return _warp(picture.astype(np.float32), pixels, back)

    return render


def appearance_change(ds, ref, ridges=(1e-3, 1e-2, 1e-1, 1.0)):
    """A linear model of how the face's colours change with β on this clip: the training
    frames warped onto the reference frame's tracked mesh, regressed per pixel on β (ridge
    relative to the mean eigenvalue, chosen on the val frames). -> (β (E,) -> (H·W, 3)
    colour change from the training mean, {ridge, val_psnr, val_psnr_mean})."""
    from flamenerf.geometry import project_points
    from scipy.spatial import Delaunay
    from scipy.interpolate import LinearNDInterpolator

    def projected(frame):
        return project_points(ds.face_vertices[frame.position].astype(np.float64),
                              ds.intrinsics, frame.c2w)[0]

    h, w = ds.load_image(ref).shape[:2]
    pixels = _pixel_centres(h, w)
    target = projected(ref)
    tri = Delaunay(target)
    inside = tri.find_simplex(pixels) >= 0

    def normalised(frames):
        return np.stack([
            _warp(ds.load_image(f), pixels, LinearNDInterpolator(
                tri, projected(f) - target, fill_value=0.0)(pixels)).reshape(-1, 3)[inside]
            .ravel() for f in frames])

    train, val = ds.split("train"), ds.split("val")
    y, y_val = normalised(train), normalised(val)
    x, x_val = ds.expression_matrix(train).astype(np.float64), ds.expression_matrix(val)
    x_mean, y_mean = x.mean(0), y.mean(0)
    a = x - x_mean
    gram = a.T @ a
    mse = lambda pred: float(((pred - y_val) ** 2).mean())  # noqa: E731
    best = None
    for ridge in ridges:
        coef = np.linalg.solve(gram + ridge * np.trace(gram) / len(gram) * np.eye(len(gram)),
                               a.T @ (y - y_mean))
        err = mse(y_mean + (x_val - x_mean) @ coef)
        if best is None or err < best[0]:
            best = (err, ridge, coef)
    err, ridge, coef = best

    def change(beta):
        out = np.zeros((h * w, 3))
        out[inside] = ((np.asarray(beta, np.float64) - x_mean) @ coef).reshape(-1, 3)
        return out

    return change, {"ridge": ridge, "val_psnr": -10 * np.log10(err),
                    "val_psnr_mean": -10 * np.log10(mse(y_mean))}


def image_sweeps(render, ds, base, train, companions) -> dict:
    """`eval`'s sweeps of `render` (β -> image), re-tracked by the landmarker. -> summary"""
    from flamenerf.evaluation.control import Retracker, control_response

    track = Retracker()
    try:
        res = control_response(render, ds.expression_names, base, train, track,
                               companions=companions)["controls"]
    finally:
        track.close()
    return summary(res)


def summary(res: dict) -> dict:
    """A sweep's per-control gains and how many pass the bar (gain >= 0.5,
    correlation >= 0.9), alone and with companions."""
    def ok(r, suffix=""):
        g = r.get("gain" + suffix, r["gain"])
        return g >= 0.5 and r.get("correlation" + suffix, r["correlation"]) >= 0.9

    return {"controls": {n: {k: v for k, v in r.items() if "gain" in k or "correlation" in k}
                         for n, r in res.items()},
            "passing_alone": sum(ok(r) for r in res.values()),
            "passing_with_companions": sum(ok(r, "_with_companions") for r in res.values()),
            "swept": len(res)}


if __name__ == "__main__":
    main()
