"""Does the expression input control the face? Metrics a refitted ω cannot fake.

driven held-out    every val frame rendered from its own camera with its own β and the
                   codes a re-animation uses (frame 0's ω_0, φ_0; nothing fitted), scored on
                   the whole image, the face, the background and the *expressive region*:
                   the part of the face mesh that moves with the expression (mouth, eyes,
                   brows), found from how far each vertex travels over the training frames.
control response   at a fixed camera, sweep one control across the range the training frames
                   cover (everything else at the reference frame's β), render, re-track the
                   renders with MediaPipe's FaceLandmarker and regress the re-tracked value on
                   the commanded one: gain (slope) and correlation. A model that ignores β
                   gets gain 0 whatever its held-out PSNR. Where the face mesh is
                   MediaPipe's, the sweep is also read as geometry (*landmark gain*): how
                   far the re-tracked landmarks move along the motion that the clip's own
                   β -> mesh model gives the command, projected into the camera. The
                   landmarker's blendshape scores read a part of the face in the context of
                   the rest (an open mouth doubles the brows' scores, the brows' pixels
                   unchanged), so a control commanded alone can move the face as the clip
                   does and still score low.
driven, re-tracked the driven held-out renders re-tracked against their frames' β, beside
                   the frames' own images re-tracked alike: the controls followed along
                   expressions like the capture's, where the sweep asks for each alone.
drive correlation  for a driving sequence, the correlation over time of driving and
                   re-tracked controls.
A control *responds* when its gain is at least 0.5 and its correlation at least 0.9
(`metrics.RESPONDS`, the bar the evaluation sets); each reading counts those (`responding`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from flamenerf.tracking.landmarker import (FaceLandmarker, NUM_LANDMARKS, NUM_MESH_VERTICES,
                                           blendshape_names, part_outlines)
from flamenerf.data.companions import Companions
from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.scene import FrameSet
from flamenerf.evaluation import metrics as M
from flamenerf.evaluation.metrics import (GEOMETRY_FOLLOWS, image_metrics, responds, scene_masks,
                                         summarize)
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.render_image import StillCamera, render_image
from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask
from flamenerf.data.expression_range import span, varies
from flamenerf.data.face_parts import MEDIAPIPE_VERTEX_COUNTS
from flamenerf.data.head_pose import canonical_vertices
from flamenerf.geometry import project_points
from flamenerf.model.inference import FAST
from flamenerf.synthetic.scene import scene_from_dataset
from flamenerf.tracking.blendshapes import BlendshapeStage


def expressive_faces(ds: Dataset, fraction: float = 0.2) -> np.ndarray:
    """Triangles of the face mesh that move with the expression: those with a vertex whose
    motion over the training frames (RMS distance from its mean position, in the head's
    canonical frame, the rigid sway removed by subtracting each frame's mesh centroid)
    exceeds `fraction` of the largest. -> (F', 3) int."""
    train = ds.training_frames()
    v = canonical_vertices(ds, train).astype(np.float64)
    v = v - v.mean(1, keepdims=True)
    motion = np.sqrt(((v - v.mean(0)) ** 2).sum(-1).mean(0))  # (V,)
    moving = motion > fraction * motion.max()
    return ds.faces[moving[ds.faces].any(1)]


def region_masks(ds: Dataset, fs: FrameSet, faces: np.ndarray) -> np.ndarray:
    """The expressive region of each frame of `fs` at its resolution, from the frame's own
    face mesh (ground truth where the dataset has it). -> (N, H, W) bool."""
    return np.stack([
        prior_mask(ds, ds.face_vertices[fr.position], fr.c2w, fs.intr, 0, faces=faces)
        for fr in fs.frames])


def region_metrics(pred: np.ndarray, gt: np.ndarray, face: np.ndarray,
                   region: np.ndarray, scene: np.ndarray) -> dict[str, float]:
    """pred, gt (H, W, 3); face, region, scene (H, W) bool -> `metrics.image_metrics`
    (MSE, PSNR/SSIM of the whole image, PSNR of the face, the background and the scene) and
    PSNR of the expressive region."""
    return {**image_metrics(pred, gt, face, scene),
            "psnr_expressive": M.psnr(pred, gt, region)}


DRIVEN_KEYS = ("psnr", "ssim", "psnr_face", "psnr_face_interior", "psnr_face_outline",
               "psnr_background", "psnr_scene", "psnr_expressive", "face_depth_error")


def driven(model: FlameNeRF, ds: Dataset, fs: FrameSet, omega0: torch.Tensor,
           phi0: torch.Tensor, chunk: int = 16384) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Frames of `fs` rendered with their own camera, β and prior mask and frame 0's codes
    (what a re-animation has), against their images; and the rendered face's depth
    against the frame's face mesh (`face_depth_error`: median |depth − mesh depth| over the
    pixels the mesh covers, scene units; a face rendered as a fog behind its surface looks
    right from the captured views only). -> (summary with rows, renders)."""
    regions = region_masks(ds, fs, expressive_faces(ds))
    scenes = scene_masks(fs)
    mesh_depths = fs.mesh_depths().numpy()
    rows, preds = [], []
    for i in range(fs.n):
        out = render_image(model, fs.intr, fs.c2w[i], omega0, phi0, fs.expressions[i],
                           fs.masks[i], chunk=chunk, head=fs.head_of(i))
        pred = out["rgb"].numpy()
        preds.append(pred)
        row = {"position": fs.frames[i].position}
        row.update(region_metrics(pred, fs.images[i].numpy(), fs.masks[i].numpy(), regions[i],
                                  scenes[i]))
        hit = np.isfinite(mesh_depths[i])
        row["face_depth_error"] = (float(np.median(np.abs(out["depth"].numpy()[hit]
                                                         - mesh_depths[i][hit])))
                                   if hit.any() else float("nan"))
        rows.append(row)
    res = summarize(rows, DRIVEN_KEYS)
    res["frames"] = rows
    return res, preds


# ------------------------------------------------------------------------- re-tracking


def fit_line(commanded: np.ndarray, measured: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of measured on commanded, and their Pearson correlation (NaN when
    either is constant)."""
    x, y = np.asarray(commanded, np.float64), np.asarray(measured, np.float64)
    if len(x) < 2 or np.ptp(x) == 0:
        return float("nan"), float("nan")
    slope = float(np.polyfit(x, y, 1)[0])
    corr = float(np.corrcoef(x, y)[0, 1]) if np.ptp(y) > 0 else float("nan")
    return slope, corr


@dataclass
class Retracker:
    """Re-tracks rendered images: MediaPipe's blendshape scores by control name. Images are
    upscaled to at least `min_size` pixels first (the detector misses small faces)."""

    min_size: int = 256

    def __post_init__(self):
        self._lm = FaceLandmarker()
        self.names = blendshape_names()

    def detect(self, img: np.ndarray):
        """img (H, W, 3) float in [0, 1] or uint8 -> the landmarker's Detection (landmarks in
        the upscaled image's pixels), or None when no face is found."""
        from PIL import Image

        u8 = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        h, w = u8.shape[:2]
        s = max(1.0, self.min_size / min(h, w))
        if s > 1:
            u8 = np.asarray(Image.fromarray(u8).resize((round(w * s), round(h * s)),
                                                      Image.BICUBIC))
        return self._lm.detect(u8)

    def read(self, img: np.ndarray) -> tuple[dict[str, float], np.ndarray] | None:
        """img (H, W, 3) -> ({control: score}, the re-tracked face mesh's vertices (468, 2) in
        img's pixels, the irises left out) from one detection, or None when no face is
        found."""
        det = self.detect(img)
        if det is None:
            return None
        s = max(1.0, self.min_size / min(img.shape[:2]))  # detect's upscaling
        return (dict(zip(self.names, map(float, det.blendshapes))),
                det.landmarks[:NUM_MESH_VERTICES, :2] / s)

    def __call__(self, img: np.ndarray) -> dict[str, float] | None:
        """img (H, W, 3) float in [0, 1] -> {control: score}, or None when no face is found."""
        got = self.read(img)
        return None if got is None else got[0]

    def close(self) -> None:
        self._lm.close()


def trackable_controls(names: list[str]) -> list[str]:
    """Controls the landmarker reports by the same name (ARKit-named expression models)."""
    known = set(blendshape_names())
    return [n for n in names if n in known]


def sweep_values(values: np.ndarray, steps: int) -> np.ndarray | None:
    """`steps` values across the span a control covers in the training frames (its 5th to
    95th percentile, data/expression_range.span); None when it barely varies."""
    if not varies(values):
        return None
    return np.linspace(*span(values), steps)


RenderFn = Callable[[np.ndarray], np.ndarray]
"""β (E,) -> rendered image (H, W, 3) at the sweep's fixed camera."""


@dataclass
class LandmarkMotion:
    """How a sweep's renders are read as geometry: `expected` β (E,) -> the face mesh of that
    expression projected into the sweep's camera (V, 2) pixels; `read` image -> (the scores
    by control, the re-tracked mesh (V, 2)) from one detection, or None (`Retracker.read`);
    the vertices of both meshes are the same (MediaPipe's)."""

    expected: Callable[[np.ndarray], np.ndarray]
    read: Callable[[np.ndarray], tuple[dict[str, float], np.ndarray] | None]
    mesh_scores: Callable[[np.ndarray], dict[str, float]] | None = None
    """β -> the tracker's scores of that expression's mesh itself (its blendshape stage on
    the projected mesh, irises included): what a render that followed the mesh exactly
    would score; None where the mesh lacks the irises the stage reads."""


def landmark_motion(ds: Dataset, mesh_of: Callable[[np.ndarray], np.ndarray],
                    intr: Intrinsics, c2w: np.ndarray, read: Callable
                    ) -> LandmarkMotion | None:
    """The geometry reading of a sweep at camera c2w, where the dataset's face mesh is the
    landmarker's own (MediaPipe's topology); None elsewhere (FLAME, the built-in head)."""
    if ds.face_vertices.shape[1] not in MEDIAPIPE_VERTEX_COUNTS:
        return None
    scores = None
    if ds.face_vertices.shape[1] == NUM_LANDMARKS:
        stage = BlendshapeStage()

        def scores(b: np.ndarray) -> dict[str, float]:
            pts = project_points(np.asarray(mesh_of(b), np.float64), intr, c2w)[0]
            return dict(zip(stage.names, map(float, stage.scores(pts))))

    return LandmarkMotion(
        expected=lambda b: project_points(mesh_of(b)[:NUM_MESH_VERTICES], intr, c2w)[0],
        read=read, mesh_scores=scores)


def landmark_gain(retracked: list[np.ndarray | None], expected: list[np.ndarray],
                  moved_fraction: float = 0.3, min_motion_px: float = 0.05
                  ) -> tuple[float, float, float]:
    """A sweep read as geometry. retracked: the re-tracked vertices (V, 2) of each step's
    render (None: no face), expected: the projected mesh of each step's β (V, 2). Motions
    are taken from the first step; the vertices that count are those the command moves by
    at least `moved_fraction` of its largest motion at the last step. Each step's expected
    and achieved motion as a fraction of the last step's expected motion (projections on
    it) are regressed: -> (gain, correlation, the largest expected motion in pixels). Gain
    1: the render moves the face as the mesh model says; NaN where the model moves no
    vertex by `min_motion_px` or the first step has no face."""
    e_last = expected[-1] - expected[0]
    size = np.linalg.norm(e_last, axis=1)
    if retracked[0] is None or size.max() < min_motion_px:
        return float("nan"), float("nan"), float(size.max())
    sel = size >= moved_fraction * size.max()
    ref = e_last[sel].ravel()
    norm = float(ref @ ref)
    x, y = [], []
    for got, exp in zip(retracked, expected):
        if got is None:
            continue
        x.append(float((exp - expected[0])[sel].ravel() @ ref) / norm)
        y.append(float((got - retracked[0])[sel].ravel() @ ref) / norm)
    gain, corr = fit_line(np.array(x), np.array(y))
    return gain, corr, float(size.max())


def control_response(render: RenderFn, names: list[str], base: np.ndarray,
                     train_expressions: np.ndarray, track: Callable, steps: int = 5,
                     controls: list[str] | None = None,
                     companions: Companions | None = None,
                     motion: LandmarkMotion | None = None,
                     generic: list[int] | tuple[int, ...] = ()) -> dict[str, Any]:
    """Sweep each trackable control that varies in the training frames, and those that a
    generic shape stands in for (`generic`, indices: from 0 to 1); re-track.

    base (E,) the β the other controls keep; train_expressions (N, E). With `companions`
    (data/companions.py), a control that has some is swept a second time with them moving
    along, as `render --expressions` keyframes move them: `gain_with_companions`,
    `correlation_with_companions` (the re-tracked value of the swept control itself).
    Renders are made in order: each control's sweep alone, then with its companions.
    With `motion`, each sweep is also read as geometry (`landmark_gain`):
    `landmark_gain`, `landmark_correlation`, `landmark_motion_px` (and `..._with_companions`);
    its `read` then re-tracks each render once for the scores and the mesh (`track` unused);
    with its `mesh_scores`, also `mesh_gain`, `mesh_correlation`: the swept meshes' own
    scores, a render that followed the mesh exactly.
    -> {"controls": {name: {commanded, retracked, gain, correlation, detected, ...}},
    "mean_gain", "mean_correlation", "mean_gain_with_companions" (each control's gain with
    its companions where it has some, else alone), "responding" and
    "responding_with_companions" (how many meet `RESPONDS`, likewise), "mean_landmark_gain" and
    "mean_mesh_gain" (likewise, with `motion`), "skipped": {name: why}}.
    """
    out: dict[str, Any] = {"controls": {}, "skipped": {}}
    want = controls if controls is not None else trackable_controls(names)

    def sweep(vals: np.ndarray, name: str, make: Callable[[float], np.ndarray]):
        got, meshes, expected, own = [], [], [], []
        shape = None
        for v in vals:
            beta = make(v)
            img = render(beta)
            if motion is None:
                scores = track(img)
            else:
                reading = motion.read(img)
                scores, mesh = (None, None) if reading is None else reading
                meshes.append(mesh)
                expected.append(motion.expected(beta))
                if motion.mesh_scores is not None:
                    own.append(motion.mesh_scores(beta).get(name, math.nan))
            got.append(float("nan") if scores is None else scores.get(name, float("nan")))
        got_a = np.array(got)
        ok = np.isfinite(got_a)
        fit = fit_line(vals[ok], got_a[ok]) if ok.sum() >= 2 else (math.nan, math.nan)
        geo = None
        if motion is not None:
            geo = landmark_gain(meshes, expected)
            if own:
                geo = (*geo, *fit_line(vals, np.array(own)))
            shape = geometry_of_sweep(name, vals, meshes)
        return got, fit, int(ok.sum()), geo, shape

    for name in names:
        if name not in want:
            continue
        k = names.index(name)
        vals = (np.linspace(0.0, 1.0, steps) if k in generic
                else sweep_values(train_expressions[:, k], steps))
        if vals is None:
            out["skipped"][name] = "varies by less than 0.1 in the training frames"
            continue

        def alone(v, k=k):
            beta = base.copy()
            beta[k] = v
            return beta

        got, (gain, corr), n, geo, shape = sweep(vals, name, alone)
        row = {"commanded": vals.tolist(), "retracked": got, "gain": gain,
               "correlation": corr, "detected": n}
        if geo is not None:
            row.update(zip(_GEO_KEYS + _MESH_KEYS, geo))
        if shape is not None:
            row["geometry"] = shape
        if k in generic:
            row["generic"] = True  # a generic shape, swept 0 -> 1 (data/generic_shapes.py)
        if companions is not None and companions.of(name):
            got_c, (gain_c, corr_c), _, geo_c, shape_c = sweep(
                vals, name, lambda v, k=k: companions.complete(base, {k: float(v)}))
            row.update(companions=companions.of(name), retracked_with_companions=got_c,
                       gain_with_companions=gain_c, correlation_with_companions=corr_c)
            if geo_c is not None:
                row.update(zip((key + "_with_companions" for key in _GEO_KEYS + _MESH_KEYS),
                               geo_c))
            if shape_c is not None:
                row["geometry_with_companions"] = shape_c
        out["controls"][name] = row
    rows = out["controls"].values()
    out["mean_gain"] = finite_mean(c["gain"] for c in rows)
    out["mean_correlation"] = finite_mean(c["correlation"] for c in rows)
    out["responding"] = sum(responds(c["gain"], c["correlation"]) for c in rows)
    if companions is not None:
        out["mean_gain_with_companions"] = finite_mean(
            c.get("gain_with_companions", c["gain"]) for c in rows)
        out["responding_with_companions"] = sum(
            responds(c.get("gain_with_companions", c["gain"]),
                     c.get("correlation_with_companions", c["correlation"])) for c in rows)
    if motion is not None:
        with_geo = [c for c in rows if "geometry" in c]
        if with_geo:
            out["geometry_measured"] = len(with_geo)
            out["geometry_following"] = sum(c["geometry"]["follows"] for c in with_geo)
            out["geometry_following_with_companions"] = sum(
                c.get("geometry_with_companions", c["geometry"])["follows"] for c in with_geo)
        out["mean_landmark_gain"] = finite_mean(
            c.get("landmark_gain_with_companions", c["landmark_gain"]) for c in rows)
        if motion.mesh_scores is not None:
            out["mean_mesh_gain"] = finite_mean(
                c.get("mesh_gain_with_companions", c.get("mesh_gain", math.nan)) for c in rows)
    return out


_GEO_KEYS = ("landmark_gain", "landmark_correlation", "landmark_motion_px")
_MESH_KEYS = ("mesh_gain", "mesh_correlation")
"""The tracker's reading of the swept meshes themselves (`LandmarkMotion.mesh_scores`)."""


def finite_mean(values) -> float:
    """The mean of the finite values (a control the landmarker never saw has NaN), or NaN."""
    vals = [v for v in values if math.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def retrack_series(images: list[np.ndarray], values: np.ndarray, names: list[str],
                   track: Callable, min_range: float = 0.05,
                   controls: list[str] | None = None) -> dict[str, Any]:
    """Re-track a sequence of images made for the expressions values (T, E) (the run's
    control order): per control that the sequence moves by at least `min_range`, the
    correlation over the sequence of commanded and re-tracked, and the gain (slope of
    re-tracked on commanded). -> {"controls": {name: {commanded, retracked, gain,
    correlation, detected}}, "mean_gain", "mean_correlation", "responding" (how many meet
    `RESPONDS`), "frames", "skipped": {name: why}}."""
    want = controls if controls is not None else trackable_controls(names)
    scores = [track(im) for im in images]
    out: dict[str, Any] = {"controls": {}, "skipped": {}, "frames": len(values)}
    for name in want:
        k = names.index(name)
        x = np.asarray(values[:, k], np.float64)
        if np.ptp(x) < min_range:
            out["skipped"][name] = f"the sequence moves it by less than {min_range}"
            continue
        got = np.array([math.nan if sc is None else sc.get(name, math.nan) for sc in scores])
        ok = np.isfinite(got)
        gain, corr = fit_line(x[ok], got[ok]) if ok.sum() >= 3 else (math.nan, math.nan)
        out["controls"][name] = {"commanded": x.tolist(), "retracked": got.tolist(),
                                 "gain": gain, "correlation": corr, "detected": int(ok.sum())}
    rows = out["controls"].values()
    out["mean_gain"] = finite_mean(c["gain"] for c in rows)
    out["mean_correlation"] = finite_mean(c["correlation"] for c in rows)
    out["responding"] = sum(responds(c["gain"], c["correlation"]) for c in rows)
    return out


def drive_response(render: RenderFn, names: list[str], values: np.ndarray, track: Callable,
                   min_range: float = 0.05, controls: list[str] | None = None,
                   rendered: np.ndarray | None = None
                   ) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Render a driving sequence and re-track it (`retrack_series`): per control that the
    sequence moves, the correlation over time of commanded (the driving video's tracked
    value, mapped onto the run) and re-tracked, and the gain.

    values (T, E) the sequence in the run's control order; rendered (T, E) what is rendered
    for it (default: values; `render` clamps them to the training range, and the gain and
    correlation are still against what the driver did). -> (as `retrack_series`, the
    renders).
    """
    preds = [render(np.asarray(beta, np.float32))
             for beta in (values if rendered is None else rendered)]
    return retrack_series(preds, values, names, track, min_range, controls), preds


def driven_response(preds: list[np.ndarray], images: list[np.ndarray], values: np.ndarray,
                    names: list[str], train_values: np.ndarray, track: Callable
                    ) -> dict[str, Any]:
    """The driven held-out renders re-tracked against their frames' β (T, E): whether the
    controls follow expressions like the capture's at its own cameras, where the sweep
    commands one control at a time from the reference frame (which asks the model for faces
    no frame showed where the capture moves its controls together). The controls are the
    sweep's (those that vary in the training frames, train_values (N, E)); the frames' own
    images (T of (H, W, 3)) re-tracked the same way are `truth`: what the landmarker reads
    from the capture at this resolution, the most a render can show.
    -> as `retrack_series`, plus "truth": {"controls": {name: {gain, correlation}},
    "responding", "mean_gain", "mean_correlation"}."""
    want = [n for n in trackable_controls(names) if varies(train_values[:, names.index(n)])]
    out = retrack_series(preds, values, names, track, controls=want)
    gt = retrack_series(images, values, names, track, controls=want)
    out["truth"] = {"controls": {n: {k: c[k] for k in ("gain", "correlation")}
                                 for n, c in gt["controls"].items()},
                    **{k: gt[k] for k in ("responding", "mean_gain", "mean_correlation")}}
    return out


# MediaPipe face-mesh landmarks: inner lip centres; each eye's upper and lower lid centre
# ("left" is the subject's left, MediaPipe's left eye); the eye corners, for the scale
_LIPS = (13, 14)
_MOUTH_CORNERS = (61, 291)
_LIDS = {"eye_open_left": (386, 374), "eye_open_right": (159, 145)}
_EYE_CORNERS = ((263, 362), (33, 133))
_BROWS = {"brow_left": 334, "brow_right": 105}  # the middle of each brow's upper edge
GEOMETRY = ("mouth_open", "mouth_width", *_LIDS, *_BROWS)

SWEEP_GEOMETRY: dict[str, tuple[tuple[str, ...], int]] = {
    "jawOpen": (("mouth_open",), 1),
    "mouthLowerDownLeft": (("mouth_open",), 1), "mouthLowerDownRight": (("mouth_open",), 1),
    "mouthUpperUpLeft": (("mouth_open",), 1), "mouthUpperUpRight": (("mouth_open",), 1),
    "mouthSmileLeft": (("mouth_width",), 1), "mouthSmileRight": (("mouth_width",), 1),
    "mouthStretchLeft": (("mouth_width",), 1), "mouthStretchRight": (("mouth_width",), 1),
    "mouthPucker": (("mouth_width",), -1), "mouthFunnel": (("mouth_width",), -1),
    "eyeBlinkLeft": (("eye_open_left",), -1), "eyeBlinkRight": (("eye_open_right",), -1),
    "eyeSquintLeft": (("eye_open_left",), -1), "eyeSquintRight": (("eye_open_right",), -1),
    "eyeWideLeft": (("eye_open_left",), 1), "eyeWideRight": (("eye_open_right",), 1),
    "browInnerUp": (("brow_left", "brow_right"), 1),
    "browOuterUpLeft": (("brow_left",), 1), "browOuterUpRight": (("brow_right",), 1),
    "browDownLeft": (("brow_left",), -1), "browDownRight": (("brow_right",), -1),
}
"""The plain geometry (`openings`) each control moves, and which way: a blink shuts its own
eye, a smile widens the mouth, a pucker narrows it ('Left': the subject's left)."""


def geometry_of_sweep(name: str, commanded: np.ndarray, landmarks: list[np.ndarray | None]
                      ) -> dict[str, Any] | None:
    """A control's sweep read by plain geometry: the mean of its `SWEEP_GEOMETRY` measures
    in each step's re-tracked landmarks (None: no face), signed so that the commanded way
    is up. -> {"measure", "values", "change" (last minus first), "correlation",
    "follows"}, or None for a control without a measure or fewer than two faces."""
    if name not in SWEEP_GEOMETRY:
        return None
    keys, sign = SWEEP_GEOMETRY[name]
    vals = [np.nan if lm is None else sign * float(np.mean([openings(lm)[k] for k in keys]))
            for lm in landmarks]
    v = np.array(vals)
    ok = np.isfinite(v)
    if ok.sum() < 2:
        return None
    corr = fit_line(np.asarray(commanded)[ok], v[ok])[1]
    change = float(v[ok][-1] - v[ok][0])
    return {"measure": "+".join(keys) if sign > 0 else "-" + "+".join(keys),
            "values": vals, "change": change, "correlation": corr,
            "follows": bool(np.isfinite(corr) and corr >= GEOMETRY_FOLLOWS[0]
                            and change >= GEOMETRY_FOLLOWS[1])}


def openings(landmarks: np.ndarray) -> dict[str, float]:
    """The face's geometry in units of the distance between the eye centres: the inner-lip
    gap (mouth_open), the mouth corners' distance (mouth_width), the lid gaps
    (eye_open_left/right) and each brow's height over its eye's centre (brow_left/right).
    landmarks (478 or 468, 2+) -> {GEOMETRY name: value}. Unlike blendshape scores this
    does not depend on how the tracker splits an expression into controls (an open mouth
    read as jawOpen on one face and mouthLowerDown on another), so it compares a driver with
    another face."""
    p = np.asarray(landmarks, np.float64)[:, :2]
    eyes = [p[list(c)].mean(0) for c in _EYE_CORNERS]
    scale = max(float(np.linalg.norm(eyes[0] - eyes[1])), 1e-9)
    out = {"mouth_open": float(np.linalg.norm(p[_LIPS[0]] - p[_LIPS[1]])) / scale,
           "mouth_width": float(np.linalg.norm(p[_MOUTH_CORNERS[0]] - p[_MOUTH_CORNERS[1]]))
           / scale}
    for name, (a, b) in _LIDS.items():
        out[name] = float(np.linalg.norm(p[a] - p[b])) / scale
    for (name, brow), eye in zip(_BROWS.items(), eyes):
        out[name] = float(np.linalg.norm(p[brow] - eye)) / scale
    return out


def colour_change(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Per pixel, the mean absolute change of colour between two pictures of an edit:
    (H, W, 3), (H, W, 3) -> (H, W) float32."""
    return np.abs(np.asarray(after, np.float32) - np.asarray(before, np.float32)).mean(-1)


def part_change(before: np.ndarray, after: np.ndarray, landmarks: np.ndarray,
                outlines: dict[str, list[list[int]]] | None = None) -> dict[str, float]:
    """Where an edit changed a picture: the mean absolute change of colour inside the
    convex outline of each part (`part_outlines`) at `landmarks` (468+, 2) in the images'
    pixels (e.g. the unedited render re-tracked, `Retracker.read`). An edit of the brows
    that repaints the eyes, or a smile that does, shows here where the tracker's scores of
    the other part can stay put. before, after (H, W, 3) in [0, 1] -> {part: change}."""
    from scipy.spatial import ConvexHull
    from skimage.draw import polygon

    h, w = before.shape[:2]
    diff = colour_change(before, after)
    out = {}
    for part, sides in (outlines or part_outlines()).items():
        mask = np.zeros((h, w), bool)
        for idx in sides:
            p = np.asarray(landmarks, np.float64)[idx, :2]
            corner = p[ConvexHull(p, qhull_options="QJ").vertices]  # QJ: a shut eye is near flat
            mask[polygon(corner[:, 1], corner[:, 0], (h, w))] = True
        out[part] = float(diff[mask].mean()) if mask.any() else float("nan")
    return out


def edge_change(before: np.ndarray, after: np.ndarray, mask_before: np.ndarray,
                mask_after: np.ndarray, width: int = 2) -> float:
    """The mean absolute change of colour an edit made in the last `width` pixels inside
    the prior's silhouette (of either render): β stops at the silhouette, so change there
    is a seam against the unchanged pixels beyond it (a brow edit repainting the hair at
    the temples). before, after (H, W, 3) in [0, 1]; masks (H, W) bool -> change (nan
    where the silhouettes are empty)."""
    from scipy import ndimage

    inside = np.asarray(mask_before, bool) | np.asarray(mask_after, bool)
    band = inside & ~ndimage.binary_erosion(inside, iterations=width)
    if not band.any():
        return float("nan")
    return float(colour_change(before, after)[band].mean())


def geometry_response(driving: list[np.ndarray], renders: list[np.ndarray],
                      detect: Callable, min_range: float = 0.02) -> dict[str, Any]:
    """The face's geometry (`openings`: mouth, eyes, brows) of each driving frame and of its
    render:
    per measure the driving and re-tracked series, their correlation over time and the gain
    (slope of the render's on the driver's); measures the driver moves by less than
    `min_range` are skipped. detect: image -> Detection or None."""
    def measure(images):
        out = []
        for im in images:
            det = detect(im)
            out.append(None if det is None else openings(det.landmarks))
        return out

    drv, got = measure(driving), measure(renders)
    res: dict[str, Any] = {"measures": {}, "skipped": {}}
    for key in GEOMETRY:
        x = np.array([math.nan if d is None else d[key] for d in drv])
        y = np.array([math.nan if g is None else g[key] for g in got])
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 3 or np.ptp(x[ok]) < min_range:
            res["skipped"][key] = f"the driving frames move it by less than {min_range}"
            continue
        gain, corr = fit_line(x[ok], y[ok])
        res["measures"][key] = {"driving": x.tolist(), "retracked": y.tolist(), "gain": gain,
                                "correlation": corr, "detected": int(ok.sum())}
    return res


def model_renderer(model: FlameNeRF, ds: Dataset, intr: Intrinsics, c2w: np.ndarray,
                   omega: torch.Tensor, phi: torch.Tensor, mesh_of: Callable,
                   dilate_px: int) -> RenderFn:
    """β -> the model's render at camera c2w, with the prior's mask from β's mesh, by the
    inference path that `flamenerf render` and the viewer use (what a user sees; within
    0.01 dB of the training forward and 2-3x faster on a CPU), in its own chunks; after the
    first β only the silhouettes' pixels again (`StillCamera`)."""
    still = StillCamera(model, intr, c2w, omega, phi, settings=FAST)

    def render(beta: np.ndarray) -> np.ndarray:
        mask = prior_mask(ds, mesh_of(beta), c2w, intr, dilate_px)
        return still(torch.as_tensor(np.asarray(beta, np.float32)), mask)["rgb"].numpy()

    return render


def reference_renderer(model: FlameNeRF, ds: Dataset, intr: Intrinsics, omega: torch.Tensor,
                       phi: torch.Tensor) -> tuple[RenderFn, Any, Callable]:
    """What the sweeps and the drive render: `model_renderer` at the reference frame's camera
    with codes (ω, φ), each β's prior mask from that β's mesh (data/prior.mesh_function).
    -> (render, the reference frame, β -> mesh)."""
    ref = ds.frames[reference_position(ds)]
    mesh_of = mesh_function(model, ds)
    return (model_renderer(model, ds, intr, ref.c2w, omega, phi, mesh_of,
                           dataset_dilation(ds)), ref, mesh_of)


def ground_truth_renderer(ds: Dataset, intr: Intrinsics) -> RenderFn | None:
    """β (the dataset's control order) -> the built-in scene's own render of it at the
    reference frame's camera and pose: ground truth for any expression, so that a drive's
    figures can be read against what the scene itself does under the same commands. None
    for a dataset that `flamenerf synth` did not make."""
    try:
        scene = scene_from_dataset(ds)
    except DatasetError:
        return None
    ref = ds.frames[reference_position(ds)]
    pose = ref.extra.get("body_pose")

    def render(beta: np.ndarray) -> np.ndarray:
        view = scene.render(ref.c2w, np.clip(np.asarray(beta, np.float32), 0.0, 1.0),
                            None if pose is None else np.asarray(pose), intr=intr,
                            head_pose=ref.head_pose)
        return np.asarray(view.rgb, np.float32)

    return render


def sweep_response(fs: FrameSet, preds: list[np.ndarray], track: Callable) -> dict[str, Any]:
    """Control response on a sweep with ground truth (the built-in scene's leakage split:
    frame 0 neutral, then one control at a time at a fixed camera). Renders and ground-truth
    images are re-tracked alike, so `gain` reads against `gt_gain`: what the landmarker sees
    in the true scene is the most a model can show. -> as `control_response`, plus gt_gain,
    gt_correlation and relative_gain (gain / gt_gain) per control."""
    known = set(blendshape_names())
    ref_pred, ref_gt = track(preds[0]), track(fs.images[0].numpy())
    by_control: dict[str, list[int]] = {}
    for i, fr in enumerate(fs.frames[1:], start=1):
        c = fr.extra.get("leakage_control")
        if c is not None:
            by_control.setdefault(c, []).append(i)
    out: dict[str, Any] = {"controls": {}, "skipped": {},
                           "source": "the dataset's leakage sweep, against its ground truth"}
    for name, idx in by_control.items():
        if name not in known:
            out["skipped"][name] = "not reported by the landmarker"
            continue
        vals = [0.0] + [float(fs.frames[i].extra.get("leakage_value", 0.0)) for i in idx]

        def scores(ref, imgs, name=name):
            got = [ref] + [track(im) for im in imgs]
            return np.array([float("nan") if g is None else g.get(name, float("nan"))
                             for g in got])

        got = scores(ref_pred, [preds[i] for i in idx])
        gt = scores(ref_gt, [fs.images[i].numpy() for i in idx])
        v = np.array(vals)
        ok, okg = np.isfinite(got), np.isfinite(gt)
        gain, corr = fit_line(v[ok], got[ok]) if ok.sum() >= 2 else (math.nan, math.nan)
        ggain, gcorr = fit_line(v[okg], gt[okg]) if okg.sum() >= 2 else (math.nan, math.nan)
        out["controls"][name] = {
            "commanded": vals, "retracked": got.tolist(), "gt_retracked": gt.tolist(),
            "gain": gain, "correlation": corr, "gt_gain": ggain, "gt_correlation": gcorr,
            "relative_gain": gain / ggain if ggain and math.isfinite(ggain) and ggain > 0.05
            else float("nan"),
            "detected": int(ok.sum())}
    rows = out["controls"].values()
    # only controls the landmarker can see in the true scene say anything about the model
    seen = [c for c in rows if math.isfinite(c["gt_gain"]) and c["gt_gain"] > 0.1]
    out["responsive_controls"] = [n for n, c in out["controls"].items() if c in seen]
    for key in ("gain", "correlation", "gt_gain", "relative_gain"):
        vals_k = [c[key] for c in seen if math.isfinite(c[key])]
        out[f"mean_{key}"] = float(np.mean(vals_k)) if vals_k else float("nan")
    return out
