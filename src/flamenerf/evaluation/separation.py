"""Whether each control acts alone, against ground truth (`eval`'s `separation` section).

The built-in scene's leakage split commands one control at a time from a neutral face at
frame 0's camera, and with `synth --entangled` its pairs split two controls that the capture
never showed together; the scene's own renderer gives what each should look like. Per
control (and pair), over the sweep's values, inside the face masks:

reproduced      the share of the control's true effect that the render reproduces:
                1 − Σ MSE(render, truth) / Σ MSE(truth at neutral, truth)
                (1: exact; 0: no better than not moving; < 0: a wrong change). The render's
                own error at neutral counts against it, as a viewer would see it.
change          the same share measured on the changes from neutral (render − render at
                neutral against truth − truth at neutral), which leaves that error out.
outside         the share of the render's change from neutral (its squared colour change,
                as the MSE counts it) that falls outside the control's own part of the
                face (data/face_parts.py: the pixels whose nearest face-mesh vertex the
                part reaches at all, and a pixel around them), at the sweep's largest
                value; the truth's own share
                beside it (`truth_outside`); `outside_abs` the same of the absolute change,
                which faint changes far below a grey level, spread over the whole face,
                can dominate.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from flamenerf.data.face_parts import control_weights
from flamenerf.data.scene import FrameSet
from flamenerf.geometry import project_points

PART_MARGIN_PX = 1
"""A control's own part is grown by this many pixels: at 128 px the truth's own smile moved
7 % of its squared change across the part's pixel outline, under 1 % with a pixel more."""

SHARE_TARGET = 0.6
"""The share a control should reach alone, counted for `reproduced` (`reaching_target`)
and for `change` (`change_reaching_target`)."""


def _sse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = np.asarray(a, np.float64)[mask] - np.asarray(b, np.float64)[mask]
    return float((d ** 2).sum())


def reproduced_share(renders: list[np.ndarray], truths: list[np.ndarray],
                     reference: np.ndarray, masks: list[np.ndarray]) -> float:
    """1 − Σ_i SSE(renders_i, truths_i) / Σ_i SSE(reference, truths_i) over masks_i.
    renders, truths (H, W, 3) each; reference (H, W, 3) the truth the control moves from;
    masks (H, W) bool. NaN when the truth does not change."""
    moved = sum(_sse(reference, t, m) for t, m in zip(truths, masks))
    if moved <= 0:
        return float("nan")
    return 1.0 - sum(_sse(r, t, m) for r, t, m in zip(renders, truths, masks)) / moved


def outside_share(before: np.ndarray, after: np.ndarray, own: np.ndarray, power: int = 2
                  ) -> float:
    """The share of the change from `before` to `after` (H, W, 3) that lies outside `own`
    (H, W) bool: of its squared colour change (power 2, as the MSE counts it) or its
    absolute change (power 1). NaN when nothing changed."""
    d = (np.abs(np.asarray(after, np.float64) - np.asarray(before, np.float64))
         ** power).sum(-1)
    total = float(d.sum())
    return float(d[~own].sum()) / total if total > 0 else float("nan")


def part_pixels(weights: np.ndarray, vertices: np.ndarray, intr, c2w: np.ndarray,
                mask: np.ndarray) -> np.ndarray:
    """The pixels of `mask` (H, W) bool whose nearest projected face-mesh vertex has a
    weight > 0: a part of the face in the image. weights (V,), vertices (V, 3) world,
    c2w (4, 4). -> (H, W) bool."""
    px, _ = project_points(np.asarray(vertices, np.float64), intr, np.asarray(c2w, np.float64))
    ys, xs = np.nonzero(mask)
    out = np.zeros(mask.shape, bool)
    if len(ys):
        _, nearest = cKDTree(px).query(np.stack([xs + 0.5, ys + 0.5], 1))
        out[ys, xs] = np.asarray(weights)[nearest] > 0
    return out


def separation(leak: FrameSet, leak_preds: list[np.ndarray], pairs: FrameSet | None = None,
               pair_preds: list[np.ndarray] | None = None) -> dict[str, Any] | None:
    """The measures of the module doc for the leakage sweep `leak` (frame 0 neutral, then
    each control alone; its renders `leak_preds`) and the optional pairs split. -> the
    section's dict, or None where the face mesh has no parts for its controls."""
    ds = leak.ds
    names = list(ds.expression_names)
    verts0 = leak.face_vertices[0].numpy()
    weights = control_weights(ds.expression_kind, names, verts0, ds.face_landmarks)
    if weights is None:
        return None
    gt = leak.images.numpy()
    masks = leak.masks.numpy()
    ref_gt, ref_pred, ref_mask = gt[0], leak_preds[0], masks[0]
    face = masks.any(0)  # the face across the sweep (an open jaw reaches lower)
    own_cache: dict[int, np.ndarray] = {}

    def own_part(k: int) -> np.ndarray:
        if k not in own_cache:
            own_cache[k] = ndimage.binary_dilation(
                part_pixels(weights[:, k], verts0, leak.intr, leak.c2w[0].numpy(), face),
                iterations=PART_MARGIN_PX)
        return own_cache[k]

    def measure(rows: list[int], fs: FrameSet, preds: list[np.ndarray], controls: list[int]
                ) -> dict[str, Any]:
        images, fmasks = fs.images.numpy(), fs.masks.numpy()
        truths = [images[i] for i in rows]
        renders = [preds[i] for i in rows]
        m = [fmasks[i] | ref_mask for i in rows]
        own = np.zeros(ref_mask.shape, bool)
        for k in controls:
            own |= own_part(k)
        top = int(np.argmax([float(np.abs(t - ref_gt).sum()) for t in truths]))
        change_r = [r - ref_pred for r in renders]
        change_t = [t - ref_gt for t in truths]
        zero = np.zeros_like(ref_gt)
        return {
            "values": [float(fs.expressions[i][controls].max()) for i in rows],
            "reproduced": reproduced_share(renders, truths, ref_gt, m),
            "change": reproduced_share(change_r, change_t, zero, m),
            "outside": outside_share(ref_pred, renders[top], own),
            "outside_abs": outside_share(ref_pred, renders[top], own, power=1),
            "truth_outside": outside_share(ref_gt, truths[top], own),
        }

    per: dict[str, dict[str, Any]] = {}
    for k, name in enumerate(names):
        rows = [i for i in range(1, leak.n) if leak.frames[i].extra.get("leakage_control") == name]
        if rows:
            per[name] = measure(rows, leak, leak_preds, [k])
    pair_rows: dict[str, dict[str, Any]] = {}
    if pairs is not None and pair_preds is not None:
        for i, fr in enumerate(pairs.frames):
            pair = fr.extra.get("pair") or []
            if len(pair) == 2 and all(p in names for p in pair):
                pair_rows["+".join(pair)] = measure([i], pairs, pair_preds,
                                                    [names.index(p) for p in pair])

    def mean(rows: dict[str, dict[str, Any]], key: str) -> float:
        v = np.array([r[key] for r in rows.values()], np.float64)
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else float("nan")

    capture = ds.expression_matrix(ds.training_frames())
    never = [n for k, n in enumerate(names) if float(np.abs(capture[:, k]).max()) < 1e-6]
    res: dict[str, Any] = {
        "reference_position": leak.frames[0].position,
        "target": SHARE_TARGET,
        "controls": per,
        "pairs": pair_rows,
        "never_trained": never,
        "mean_reproduced": mean(per, "reproduced"),
        "mean_change": mean(per, "change"),
        "mean_outside": mean(per, "outside"),
        "reaching_target": int(sum(r["reproduced"] >= SHARE_TARGET for r in per.values())),
        "change_reaching_target": int(sum(r["change"] >= SHARE_TARGET for r in per.values())),
    }
    if pair_rows:
        res["mean_pair_reproduced"] = mean(pair_rows, "reproduced")
        res["mean_pair_change"] = mean(pair_rows, "change")
    return res
