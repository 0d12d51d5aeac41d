"""`render --split S --codes own`: each frame of the clip rendered with its own deformation
and appearance codes (a held-out frame's between its neighbours'), not frame 0's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamenerf.errors import UserError
from flamenerf.rendering.videos import RenderOptions, plan_render
from flamenerf.training.run import load_run


def test_training_frames_keep_their_codes_and_held_out_ones_lie_between(toy_run,
                                                                         monkeypatch):
    run = load_run(toy_run, "cpu")
    ds = run.dataset()
    capture = ds.split("capture")
    assert [f.frame_index for f in capture] == [0, 1, 2, 3, 4, 5]
    # train on 0, 2, 3: frame 1 lies half way between 0 and 2; 4 and 5 past the end
    monkeypatch.setattr(type(ds), "training_frames",
                        lambda self: [f for f in capture if f.frame_index in (0, 2, 3)])
    w, a = run.clip_codes(ds, capture)
    assert w.shape[0] == a.shape[0] == 6
    own = [run.frame_codes(i) for i in range(6)]
    for i in (0, 2, 3):
        torch.testing.assert_close(w[i], own[i][0])
        torch.testing.assert_close(a[i], own[i][1])
    torch.testing.assert_close(w[1], (own[0][0] + own[2][0]) / 2)
    torch.testing.assert_close(a[1], (own[0][1] + own[2][1]) / 2)
    for i in (4, 5):  # never trained: frame 3's, not their own initial values
        torch.testing.assert_close(w[i], own[3][0])
    assert not torch.equal(own[4][0], own[3][0])  # (which differ, so the test can fail)


def test_a_split_renders_each_frame_with_its_own_codes(toy_run, tmp_path):
    from flamenerf.rendering.reanimate import render_sequence

    opts = RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train", device="cpu")
    plan = plan_render(opts, log=lambda _: None)  # --codes auto: own, with --split
    assert plan.codes is not None and plan.settings.warp_grid == 0
    frames = [f.rgb for f in plan.frames()]
    first = plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train",
                                      device="cpu", codes="first"), log=lambda _: None)
    assert first.codes is None
    train = plan.ds.split("train")

    def alone(i, codes):
        return next(render_sequence(plan.run.model, plan.ds, plan.intr, plan.poses[i:i + 1],
                                    plan.values[i:i + 1], plan.verts[i:i + 1], *codes,
                                    plan.dilate_px, settings=plan.settings)).rgb

    for i in (0, len(train) - 1):
        np.testing.assert_allclose(frames[i], alone(i, plan.run.frame_codes(
            train[i].frame_index)), atol=1e-6)
    # frame 0's codes render the last training frame otherwise
    assert np.abs(alone(len(train) - 1, plan.run.frame_codes(0)) - frames[-1]).max() > 1e-5

def test_own_codes_need_a_split_of_the_runs_dataset(toy_run, toy_dataset, tmp_path):
    import shutil

    other = tmp_path / "copy"  # the same frames, but not the run's: its codes are not theirs
    shutil.copytree(toy_dataset, other)
    assert plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", device="cpu"),
                       log=lambda _: None).codes is None  # no split: frame 0's
    with pytest.raises(UserError, match="--codes own: .* give --split"):
        RenderOptions(toy_run, codes="own").check()
    with pytest.raises(UserError, match="is not the dataset"):
        plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train",
                                  dataset=other, codes="own", device="cpu"),
                    log=lambda _: None)
    assert plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train",
                                     dataset=other, device="cpu"),
                       log=lambda _: None).codes is None  # auto: frame 0's
