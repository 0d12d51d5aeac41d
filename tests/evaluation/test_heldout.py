"""The paper's held-out protocol changes nothing but the deformation codes it returns."""

from __future__ import annotations

import pytest
import torch

from flamenerf.data.scene import FrameSet
from flamenerf.evaluation.heldout import fit_deformation_codes
from flamenerf.evaluation.protocol import EvalOptions, evaluate_run
from flamenerf.training.run import load_run


def _snapshot(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _assert_same(model, before):
    after = model.state_dict()
    assert after.keys() == before.keys()
    for k, v in before.items():
        assert torch.equal(after[k], v), f"{k} changed"


@pytest.mark.slow
def test_fit_changes_only_the_deformation_code(toy_run):
    run = load_run(toy_run, "cpu")
    ds = run.dataset()
    fs = FrameSet(ds, ds.split("val"), run.train_intrinsics(ds))
    before = _snapshot(run.model)
    omega0, phi0 = run.frame_codes(0)
    omega, phi = fit_deformation_codes(run.model, fs, steps=4, batch_rays=64, lr=0.1,
                                       quiet=True)
    _assert_same(run.model, before)  # every parameter and buffer bit-identical
    assert all(p.grad is None for p in run.model.parameters())
    assert omega.shape == (fs.n, omega0.shape[0])
    assert not torch.equal(omega, omega0.expand_as(omega)), "ω was not optimised"
    assert torch.equal(phi, phi0.expand(fs.n, -1)), "φ must be frame 0's"
    assert not run.model.training


@pytest.mark.slow
def test_the_whole_evaluation_leaves_the_model_untouched(toy_run, tmp_path):
    run = load_run(toy_run, "cpu")
    before = _snapshot(run.model)
    res = evaluate_run(run, run.dataset(), EvalOptions(fit_steps=3, fit_batch_rays=64),
                       tmp_path / "eval", quiet=True, log=lambda s: None)
    _assert_same(run.model, before)
    assert res["heldout"]["num_frames"] == 2
