"""Background leakage: zero for a model whose output ignores β (nerfies mode) and, with the
spatial prior, outside the face; positive when β reaches every point (no-prior mode)."""

from __future__ import annotations

import pytest
import torch

from flamenerf.data.dataset import load_dataset
from flamenerf.data.scene import FrameSet
from flamenerf.evaluation.protocol import leakage
from toy import toy_config
from flamenerf.training.trainer import build_for_dataset


def _perturbed(ds, mode: str):
    torch.manual_seed(0)
    model = build_for_dataset(toy_config(mode), ds)
    with torch.no_grad():  # a field with real structure, where β matters when it gets in
        for p in model.field.parameters():
            p.add_(torch.randn_like(p) * 0.5)
    return model.eval()


def _leakage(toy_dataset, mode: str):
    ds = load_dataset(toy_dataset)
    fs = FrameSet(ds, ds.split("leakage"), ds.intrinsics)
    model = _perturbed(ds, mode)
    omega0, phi0 = (c[0].detach() for c in model.codes(torch.zeros(1, dtype=torch.long)))
    res, renders = leakage(model, fs, omega0, phi0, dilate_px=1)
    return res, renders


def test_leakage_is_zero_when_the_output_ignores_expressions(toy_dataset):
    res, renders = _leakage(toy_dataset, "none")
    assert res["mean"] == 0.0 and res["max"] == 0.0
    assert res["face_change"] == 0.0
    assert all((r == renders[0]).all() for r in renders)


def test_leakage_is_zero_outside_the_face_with_the_prior(toy_dataset):
    res, _ = _leakage(toy_dataset, "masked")
    assert res["mean"] == 0.0 and res["max"] == 0.0
    assert res["face_change"] > 0.1, "β should change the face"


def test_leakage_is_positive_without_the_prior(toy_dataset):
    res, _ = _leakage(toy_dataset, "everywhere")
    assert res["mean"] > 0.1
    assert res["max"] >= res["mean"]
    assert set(res["per_control"]) == {"jawOpen", "mouthSmileLeft"}
    assert res["gt_mean"] == pytest.approx(0.0)  # the toy's background never changes
    assert 0 < res["background_fraction"] < 1
