"""Cross-person transfer of a drive: each control's reach matched from the driver's to the
subject's, per-control gains a user sets, and the landmark geometry (mouth, eyes, brows)
that judges a drive apart from the tracker's scores."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.errors import UserError
from flamenerf.evaluation import control as C
from flamenerf.rendering.expressions import parse_gains
from flamenerf.rendering.videos import RenderOptions
from flamenerf.tracking.expressions import GAIN_RANGE, range_gains, transfer_relative


def test_range_gains_match_the_drivers_reach_to_the_subjects():
    t = np.linspace(0, 1, 101)[:, None]
    # jaw: the driver opens to 0.8, the subject to 0.4; smile: 0.2 and 0.6; blink: the
    # subject never blinks (reach 0.02), the driver does
    drive = np.hstack([0.8 * t, 0.2 * t, 1.0 * t])
    subject = np.hstack([0.4 * t, 0.6 * t, 0.02 * t])
    g = range_gains(drive, np.zeros(3), subject, np.zeros(3))
    assert g[0] == pytest.approx(0.5, rel=1e-3) and g[1] == pytest.approx(3.0, rel=1e-3)
    assert g[2] == 1.0  # nothing to match: as transferred, and `render` says so
    far = range_gains(np.hstack([0.1 * t] * 3) + np.array([0, 0, 0.0]), np.zeros(3),
                      np.hstack([0.9 * t] * 3), np.zeros(3))
    assert far.max() <= GAIN_RANGE[1]
    out = transfer_relative(drive, np.zeros(3), np.full(3, 0.1), "arkit", g)
    assert out[-1, 0] == pytest.approx(0.1 + 0.4, abs=1e-3)  # the driver's widest -> the
    assert out[-1, 1] == pytest.approx(0.1 + 0.6, abs=1e-3)  # subject's widest
    plain = transfer_relative(drive, np.zeros(3), np.full(3, 0.1), "arkit")
    assert plain[-1, 0] == pytest.approx(0.9, abs=1e-3)  # relative alone: past the subject's


def test_gains_parse_by_name_and_stem():
    names = ["jawOpen", "mouthSmileLeft", "mouthSmileRight"]
    assert parse_gains(["jawOpen=1.5,mouthSmile=0.5"], names) == {
        "jawOpen": 1.5, "mouthSmileLeft": 0.5, "mouthSmileRight": 0.5}
    assert parse_gains(None, names) == {}
    for bad, words in (("jaw=2", "unknown control 'jaw'"), ("jawOpen=x", "not a number"),
                       ("jawOpen=20", "0 to 10")):
        with pytest.raises(UserError, match=words):
            parse_gains([bad], names)


def test_gain_and_match_range_need_a_drive(tmp_path):
    for kw in ({"gain": ["jawOpen=2"]}, {"match_range": True}):
        with pytest.raises(UserError, match="--drive"):
            RenderOptions(run=tmp_path, **kw).check()


def _face(mouth_w: float, brow: float) -> np.ndarray:
    p = np.zeros((478, 3))
    p[[263, 362], 0], p[[33, 133], 0] = 1.0, -1.0  # eye centres 2 apart
    p[61, 0], p[291, 0] = -mouth_w, mouth_w
    p[334, :2], p[105, :2] = (1.0, -2 * brow), (-1.0, -2 * brow)
    return p


def test_openings_read_the_mouths_width_and_the_brows_height():
    o = C.openings(_face(0.8, 0.3))
    assert o["mouth_width"] == pytest.approx(0.8)  # 1.6 over the eyes' distance 2
    assert o["brow_left"] == pytest.approx(0.3) and o["brow_right"] == pytest.approx(0.3)
    assert set(C.GEOMETRY) == set(o)
