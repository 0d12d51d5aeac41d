"""The subject's β -> mesh model made to mean what the tracker means by each control.

The per-subject linear model (meshes.fit_expression_model) is a least-squares fit of the
training frames' tracked meshes on their β. Its meshes of those frames' β read back through
MediaPipe's blendshape stage as the tracker read the frames (26 of the 27 controls that vary
on the shared expressions clip with gain 0.65-1.26), but the controls co-vary in real
frames, so each control's own column is only its share of a joint motion: a control
commanded alone from frame 0's expression, as `render --expressions` keyframes and the
viewer's sliders do, moves the mesh in a way the tracker scores as that control for only 13
of the 27 (19 with the companions that move along; docs/results.md, "Controls").
A renderer that follows the mesh exactly could do no better.

This fit adds that reading to the least-squares one: for each control that varies, its
sweep over the training range at the reference frame's camera, projected and scored by the
blendshape stage (tracking/blendshapes.py), should raise that control's score by the
commanded amount and leave the other varying controls' scores as they were. The scores
are a smooth function of the landmarks, so Gauss-Newton steps on the residuals at the
sweep's ends and middle, each a linear least-squares problem with the mesh fit's own normal
equations (solved by conjugate gradients preconditioned with them), settle it in a few
iterations. `strength` weighs one unit of score error against a 1 mm RMS miss of the
training meshes per frame; each control keeps moving only its part of the face.

It raises what the mesh can show (19 -> 23 of 27 there), not yet what a trained model
shows (11 -> 12 at 128 px, 13 -> 14 at 256 px, one training each): the renders' landmarks
follow the mesh's main motion but not the small components the scores weigh. So
`preprocess` fits it only when asked (`--consistent-expressions`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flamenerf.data.dataset import StoredMeshModel, load_dataset, reference_position
from flamenerf.data.dataset_writer import write_mesh_model
from flamenerf.data.expression_range import span, training_expressions, varies
from flamenerf.data.face_parts import control_weights
from flamenerf.data.head_pose import canonical_vertices
from flamenerf.geometry import project_points
from flamenerf.meshes import expression_model_system, model_from_coefficients
from flamenerf.tracking.blendshapes import BlendshapeStage
from flamenerf.tracking.landmarker import NUM_LANDMARKS, blendshape_names

MM = 1e-3
"""The scale of the fit term: world units are metres (preprocess)."""


@dataclass
class Sweep:
    """One control's commanded sweep: `control` its index in β, `row` its index among the
    scored rows, `betas` (P, E) the β at the sweep's points (low end first)."""

    control: int
    row: int
    betas: np.ndarray


def consistent_coefficients(gram: np.ndarray, rhs: np.ndarray, scale: np.ndarray,
                            num_frames: int, sweeps: list[Sweep],
                            score: Callable[[np.ndarray], np.ndarray],
                            jacobian: Callable[[np.ndarray], np.ndarray],
                            project: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                            strength: float = 10.0, iterations: int = 3,
                            progress: Callable[[int, int], None] | None = None
                            ) -> np.ndarray:
    """The mesh model's coefficients with the tracker's reading added (module doc).

    gram (V or 1, 1+E, 1+E), rhs (V, 1+E, 3), scale (V, 1+E): meshes.expression_model_system.
    score: landmarks (L, 2) -> the scored rows (R,); jacobian: landmarks -> (R, L, 2);
    project: mesh (V, 3) -> its first L vertices in the camera's pixels (L, 2) and their
    derivatives (L, 2, 3). -> coefficients (V, 1+E, 3) float64 (meshes.model_from_coefficients).
    """
    n = float(num_frames) * MM ** 2
    gram = np.broadcast_to(gram, (len(rhs),) + gram.shape[1:])
    coef = np.linalg.solve(gram, rhs)
    if not sweeps:
        return coef
    precond = np.linalg.inv(gram / n)
    steps = iterations * len(sweeps)
    done = 0
    for _ in range(iterations):
        terms = []
        for sw in sweeps:
            k = sw.control
            grads, reads = [], []
            for beta in sw.betas:
                mesh = coef[:, 0] + np.einsum("e,vec->vc", beta, coef[:, 1:] * scale[:, 1:, None])
                pts, dpts = project(mesh)
                grads.append(np.einsum("rlp,lpc->rlc", jacobian(pts), dpts) * beta[k])
                reads.append(score(pts))
            for j in range(1, len(sw.betas)):
                want = np.zeros_like(reads[0])
                want[sw.row] = sw.betas[j, k] - sw.betas[0, k]
                terms.append((k, grads[j] - grads[0], reads[j] - reads[0] - want))
            done += 1
            if progress is not None:
                progress(done, steps)
        coef = coef + _step(gram / n, rhs / n, coef, scale, terms, strength, precond)
    return coef


def _step(gram, rhs, coef, scale, terms, strength, precond, max_iter: int = 400,
          tol: float = 1e-8) -> np.ndarray:
    """One Gauss-Newton step d (V, 1+E, 3): minimises the mesh fit at coef + d plus
    strength * Σ ||r0 + G (scale_k d_k)||² over the terms (k, G (R, L, 3), r0 (R,))."""
    lv = terms[0][1].shape[1] if terms else 0

    def apply(d):
        out = np.einsum("vef,vfc->vec", gram, d)
        for k, g, _ in terms:
            dk = d[:lv, 1 + k] * scale[:lv, 1 + k, None]
            r = np.einsum("rlc,lc->r", g, dk)
            out[:lv, 1 + k] += strength * np.einsum("rlc,r->lc", g, r) * scale[:lv, 1 + k, None]
        return out

    b = rhs - np.einsum("vef,vfc->vec", gram, coef)
    for k, g, r0 in terms:
        b[:lv, 1 + k] -= strength * np.einsum("rlc,r->lc", g, r0) * scale[:lv, 1 + k, None]
    d = np.zeros_like(coef)
    r = b.copy()
    z = np.einsum("vef,vfc->vec", precond, r)
    p = z.copy()
    rz = float((r * z).sum())
    stop = tol * float(np.sqrt((b * b).sum()))
    for _ in range(max_iter):
        q = apply(p)
        a = rz / float((p * q).sum())
        d += a * p
        r -= a * q
        if float(np.sqrt((r * r).sum())) < stop:
            break
        z = np.einsum("vef,vfc->vec", precond, r)
        rz_next = float((r * z).sum())
        p = z + rz_next / rz * p
        rz = rz_next
    return d


# ----------------------------------------------------------------------------- datasets


def pinhole_projection(intr, c2w: np.ndarray
                       ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """mesh (V, 3) world -> its pixels (V, 2) in camera c2w (geometry.project_points) and
    their derivatives (V, 2, 3)."""
    w2c = np.linalg.inv(np.asarray(c2w, np.float64))

    def project(mesh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pc = mesh @ w2c[:3, :3].T + w2c[:3, 3]
        z = -pc[:, 2]
        d = np.zeros((len(mesh), 2, 3))
        d[:, 0, 0] = intr.fx / z
        d[:, 0, 2] = intr.fx * pc[:, 0] / z ** 2
        d[:, 1, 1] = -intr.fy / z
        d[:, 1, 2] = -intr.fy * pc[:, 1] / z ** 2
        return project_points(mesh, intr, c2w)[0], d @ w2c[:3, :3]

    return project


def applies(ds) -> bool:
    """Whether the tracker can read the dataset's meshes: MediaPipe's blendshape scores on
    its full mesh, irises included (the blendshape stage reads them)."""
    return ds.expression_kind == "arkit" and ds.face_vertices.shape[1] == NUM_LANDMARKS


def dataset_sweeps(ds, stage_names: list[str]) -> tuple[list[Sweep], list[int]]:
    """The sweeps `eval` makes (each control that varies in the training frames and that the
    tracker scores, alone, over its training span, at the reference frame's expression),
    at their low end, middle and high end; and the scored rows' indices in `stage_names`."""
    x = training_expressions(ds)
    base = ds.frames[reference_position(ds)].expression.astype(np.float64)
    known = set(stage_names)
    ks = [k for k, n in enumerate(ds.expression_names) if n in known and varies(x[:, k])]
    sweeps = []
    for row, k in enumerate(ks):
        betas = np.repeat(base[None], 3, 0)
        betas[:, k] = np.linspace(*span(x[:, k]), 3)
        sweeps.append(Sweep(k, row, betas))
    return sweeps, [stage_names.index(ds.expression_names[k]) for k in ks]


def fit_for_dataset(ds, strength: float = 10.0, iterations: int = 3, ridge: float = 1e-3,
                    progress: Callable[[int, int], None] | None = None, stage=None):
    """The tracker-consistent β -> mesh model of a dataset's training frames (module doc),
    with each control on its part of the face. -> neutral (V, 3), basis (E, V, 3) float32
    tensors in the canonical frame, as data/mesh_model.fit_dataset_expression_model returns."""
    import torch

    stage = stage or BlendshapeStage()
    train = ds.training_frames()
    verts = canonical_vertices(ds, train)
    weights = control_weights(ds.expression_kind, ds.expression_names, verts.mean(0),
                              ds.face_landmarks)
    gram, rhs, scale = expression_model_system(
        torch.from_numpy(ds.expression_matrix(train)), torch.from_numpy(verts), ridge,
        None if weights is None else torch.from_numpy(weights))
    sweeps, rows = dataset_sweeps(ds, stage.names)
    ref = ds.frames[reference_position(ds)]
    coef = consistent_coefficients(
        gram.numpy(), rhs.numpy(), scale.numpy(), len(train), sweeps,
        score=lambda p: stage.scores(p)[rows], jacobian=lambda p: stage.jacobian(p)[rows],
        project=pinhole_projection(ds.intrinsics, ref.c2w), strength=strength,
        iterations=iterations, progress=progress)
    return model_from_coefficients(torch.from_numpy(coef), scale)


STRENGTH = 10.0
"""One unit of score error weighs as much as a 1 mm RMS miss of the training meshes per
frame. On the shared expressions clip (128 px, 27 controls vary) the sweeps the tracker reads
as commanded (gain >= 0.5, correlation >= 0.9) went 13 -> 18 alone and 19 -> 23 of 27 with
companions, the training meshes' RMS miss 0.870 -> 0.874 mm, the val frames' 0.877 ->
0.883 mm (3 iterations; 1 gave 17 / 24 at 0.872 mm, 100 gave 20-24 / 23-25 at 0.92-0.95 mm
and val misses up to 1.04 mm)."""


def add_to_dataset(root, progress: bool = True) -> dict | None:
    """Fit the tracker-consistent model of a written dataset and store it there
    (`expression_model.npz`, read by data/dataset.load_dataset); None where the tracker
    cannot read the dataset's meshes (`applies`). -> {"method", "controls", "seconds"}."""
    import time

    ds = load_dataset(root)
    if not applies(ds):
        return None
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=1, desc="expression model", unit="sweep", leave=False,
                   dynamic_ncols=True, disable=None)

    def tick(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()

    ridge = 1e-3
    try:
        neutral, basis = fit_for_dataset(ds, STRENGTH, ridge=ridge, progress=tick)
    finally:
        if bar is not None:
            bar.close()
    write_mesh_model(root, StoredMeshModel(neutral.numpy(), basis.numpy(), ridge,
                                           f"tracker-consistent (strength {STRENGTH:g})"))
    return {"method": "tracker-consistent",
            "controls": len(dataset_sweeps(ds, blendshape_names())[0]),
            "seconds": time.perf_counter() - t0}
