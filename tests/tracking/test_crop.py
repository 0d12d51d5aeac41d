"""The stable square crop and the intrinsics that go with it."""

from __future__ import annotations

import numpy as np

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import project_points
from flamenerf.tracking.crop import Crop, stable_square_crop


def test_crop_intrinsics_match_the_pixels():
    rng = np.random.default_rng(0)
    src = Intrinsics(1280, 720, 900.0, 900.0, 640.0, 360.0)
    crop = Crop(x0=400, y0=50, size=560, out_size=256)
    out = crop.intrinsics(src.fx, src.cx, src.cy)
    assert (out.w, out.h) == (256, 256)
    pts = rng.normal(0, 0.1, (50, 3)) + np.array([0.0, 0.0, -0.6])  # in front, c2w = I
    uv_src, _ = project_points(pts, src, np.eye(4))
    uv_out, _ = project_points(pts, out, np.eye(4))
    np.testing.assert_allclose(crop.points(uv_src), uv_out, atol=1e-9)


def test_crop_image_is_the_window():
    img = np.zeros((100, 200, 3), np.uint8)
    img[30:40, 120:130] = 255
    crop = Crop(x0=100, y0=20, size=50, out_size=50)
    out = crop.apply(img)
    assert out.shape == (50, 50, 3)
    assert out[10:20, 20:30].min() == 255 and out.sum() == 255 * 300


def test_stable_crop_is_square_inside_and_covers_the_faces():
    boxes = np.array([[600, 120, 880, 400], [560, 130, 840, 410], [620, 100, 900, 380]],
                     float)
    crop, facts = stable_square_crop(boxes, 1280, 720, 256, scale=2.0)
    assert crop.size == 560 and facts["frames_face_inside"] == 3
    assert 0 <= crop.x0 and crop.x0 + crop.size <= 1280
    assert 0 <= crop.y0 and crop.y0 + crop.size <= 720
    # a face near the top edge: the window slides down to stay inside the frame
    crop, _ = stable_square_crop(boxes - [0, 90, 0, 90], 1280, 720, 256)
    assert crop.y0 == 0
    # a big face: limited by the frame
    crop, facts = stable_square_crop(np.array([[100, 100, 450, 500]], float), 512, 512, 256)
    assert crop.size == 512 and facts["limited_by_frame"]
