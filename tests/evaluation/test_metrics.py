"""Image metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flamenerf.evaluation.metrics import mean_abs_change, mse, psnr, ssim, summarize
from flamenerf.evaluation.protocol import leakage_region


def test_psnr_of_a_constant_error_is_closed_form():
    a = np.zeros((8, 8, 3))
    assert mse(a, a + 0.1) == pytest.approx(0.01)
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert psnr(a, a + 0.01) == pytest.approx(40.0)


def test_masked_psnr_uses_only_the_masked_pixels():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.01)
    face = np.zeros((4, 4), bool)
    face[1:3, 1:3] = True
    b[face] = 0.1
    assert psnr(a, b, face) == pytest.approx(20.0)
    assert psnr(a, b, ~face) == pytest.approx(40.0)
    assert math.isnan(psnr(a, b, np.zeros((4, 4), bool)))


def test_ssim_known_values():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(24, 24, 3))
    assert ssim(x, x) == pytest.approx(1.0)
    # constant images: only the luminance term remains, (2ab + C1) / (a² + b² + C1)
    c1 = (0.01 * 1.0) ** 2
    want = (2 * 0.5 * 0.6 + c1) / (0.5**2 + 0.6**2 + c1)
    assert ssim(np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.6)) == pytest.approx(want)
    assert ssim(x, 1 - x) < 0


def test_mean_abs_change_is_on_the_0_255_scale():
    a = np.zeros((4, 4, 3))
    b = a.copy()
    region = np.zeros((4, 4), bool)
    region[0] = True
    b[0] = 0.5
    b[1] = 1.0  # outside the region: not counted
    assert mean_abs_change(a, b, region) == pytest.approx(127.5)
    assert mean_abs_change(a, b) == pytest.approx((4 * 127.5 + 4 * 255) / 16)


def test_leakage_region_is_outside_the_dilated_union():
    m = np.zeros((2, 9, 9), bool)
    m[0, 4, 4] = True
    m[1, 4, 5] = True
    out0 = leakage_region(m, 0)
    assert out0.sum() == 81 - 2
    out1 = leakage_region(m, 1)  # each pixel grows to a cross (scipy's default structure)
    assert out1.sum() == 81 - 8
    assert not out1[4, 3] and not out1[3, 5] and out1[3, 3]


def test_summarize_skips_nan_frames():
    rows = [{"mse": 0.01, "psnr": 20.0, "ssim": 0.5, "psnr_face": float("nan"),
             "psnr_background": 20.0},
            {"mse": 0.03, "psnr": 30.0, "ssim": 0.7, "psnr_face": 25.0,
             "psnr_background": 30.0}]
    s = summarize(rows)
    assert s["num_frames"] == 2
    assert s["mse"] == pytest.approx(0.02)
    assert s["psnr"] == pytest.approx(25.0)
    assert s["psnr_face"] == pytest.approx(25.0)


def test_scene_masks_leave_out_the_person(tiny_scene):
    """The scene region excludes every face pixel and more around it (hair, neck), and keeps
    the image's top corners (the room)."""
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.metrics import image_metrics, scene_masks

    ds = load_dataset(tiny_scene)
    fs = FrameSet(ds, ds.split("train")[:4], ds.intrinsics)
    scene = scene_masks(fs)
    face = fs.masks.numpy()
    assert scene.shape == face.shape
    assert not (scene & face).any()
    assert (~scene & ~face).sum() > 0.5 * face.sum()  # the person is larger than the face
    assert scene[:, 0, 0].all() and scene[:, 0, -1].all()
    gt = fs.images[0].numpy()
    pred = gt.copy()
    pred[~scene[0]] = 1 - pred[~scene[0]]  # errors only on the person: the scene is exact
    m = image_metrics(pred, gt, face[0], scene[0])
    assert m["psnr_scene"] == float("inf") or m["psnr_scene"] > 90
    assert m["psnr_background"] < 40


def test_face_interior_leaves_out_the_outline():
    """An error on the face mask's outline only counts in psnr_face, not in its interior."""
    from scipy import ndimage

    from flamenerf.evaluation.metrics import face_interior, image_metrics

    face = np.zeros((128, 128), bool)
    face[30:90, 40:100] = True
    inner = face_interior(face)
    assert inner.sum() == 56 * 56  # two pixels off each side at 128 px
    rng = np.random.default_rng(0)
    gt = rng.random((128, 128, 3)).astype(np.float32)
    pred = gt.copy()
    outline = face & ~ndimage.binary_erosion(face)
    pred[outline] = 1 - pred[outline]
    m = image_metrics(pred, gt, face)
    assert m["psnr_face"] < 30 and m["psnr_face_interior"] > 100
    assert m["psnr_face_outline"] < m["psnr_face"]  # the outline holds all of the error
    pred[45, 60] = 1 - pred[45, 60]  # and an error inside counts in both
    assert image_metrics(pred, gt, face)["psnr_face_interior"] < 60



def test_beyond_head_is_the_face_mask_past_the_silhouette():
    """Face-mask pixels more than 8 cm behind the face interior's median depth are the room
    seen past the head; pixels on the head (a few cm of relief) are not."""
    from flamenerf.evaluation.metrics import beyond_head

    face = np.zeros((64, 64), bool)
    face[10:50, 10:40] = True
    depth = np.full((64, 64), 1.5)  # the room
    depth[10:50, 10:38] = 0.6  # the head, relief included
    depth[20:30, 20:25] = 0.66
    far = beyond_head(face, depth)
    assert far.sum() == 40 * 2 and far[10:50, 38:40].all()
    assert not beyond_head(np.zeros_like(face), depth).any()


def test_reanimation_rows_split_the_face_at_the_head(tiny_scene):
    """With ground-truth depth (the built-in scene), errors placed only past the head's
    silhouette leave the face on the head exact and hold all of the face's error; the
    depth follows a FrameSet at another resolution."""
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.metrics import beyond_head
    from flamenerf.evaluation.protocol import _compare

    ds = load_dataset(tiny_scene)
    frames = ds.split("reanimate")
    fs = FrameSet(ds, frames, ds.intrinsics)
    depths = fs.true_depths()
    assert depths.shape == (len(frames), 32, 32)
    assert np.array_equal(depths[0], ds.load_depth(frames[0]))
    half = FrameSet(ds, frames, ds.intrinsics.scaled(0.5))  # the nearest pixel's depth
    assert np.array_equal(half.true_depths()[0], depths[0][1::2, 1::2])
    preds = []
    for i in range(fs.n):
        gt = fs.images[i].numpy().copy()
        far = beyond_head(fs.masks[i].numpy(), depths[i])
        gt[far] = 1 - gt[far]
        preds.append(gt)
    rows = _compare(fs, preds, split_head=True)
    assert any(r["face_error_beyond_head"] == pytest.approx(1.0) for r in rows)
    for r in rows:
        assert r["psnr_face_on_head"] > 90 or r["psnr_face_on_head"] == float("inf")
    assert "psnr_face_on_head" not in _compare(fs, preds)[0]
