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


@pytest.mark.slow
def test_a_split_renders_each_frame_with_its_own_codes(toy_run, tmp_path):
    from flamenerf.rendering.reanimate import render_sequence

    opts = RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train", device="cpu")
    plan = plan_render(opts, log=lambda _: None)  # --codes auto: own, with --split
    assert plan.codes is not None and plan.settings.warp_grid == 0
    frames = [f.rgb for f in plan.frames()]
    first = plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="train",
                                      device="cpu", codes="first"), log=lambda _: None)
    assert first.codes is None
    named = plan_render(RenderOptions(toy_run, split="train", codes="first", device="cpu"),
                        log=lambda _: None)
    assert named.paths["rgb"].name == "train_split_first.mp4"  # apart from the default's
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

@pytest.mark.slow
def test_own_codes_need_a_split_of_capture_frames(toy_run, toy_dataset, tmp_path):
    import shutil

    def plan(**kw):
        return plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", device="cpu", **kw),
                           log=lambda _: None)

    assert plan().codes is None  # no split: frame 0's
    with pytest.raises(UserError, match="--codes own: .* give --split"):
        RenderOptions(toy_run, codes="own").check()
    # a re-animation split's frames have no codes: auto keeps the bake, own says why
    p = plan(split="reanimate")
    assert p.codes is None and p.settings.warp_grid > 0
    with pytest.raises(UserError, match="--split reanimate: its frames have no codes"):
        plan(split="reanimate", codes="own")
    other = tmp_path / "copy"  # the same frames, but not the run's dataset
    shutil.copytree(toy_dataset, other)
    assert plan(split="train", dataset=other).codes is None  # auto: frame 0's
    assert plan(split="train", dataset=other, codes="own").codes is not None  # as asked
    assert plan(split="train", max_frames=2).codes[0].shape[0] == 2


def test_a_moved_dataset_keeps_own_codes(toy_run, toy_dataset, tmp_path):
    """A run whose dataset is no longer where it trained, rendered with --dataset (the
    README's advice for a moved dataset), still gets each frame's own codes."""
    import json
    import shutil

    run = tmp_path / "run"
    shutil.copytree(toy_run, run)
    meta = json.loads((run / "config.json").read_text())
    meta["dataset"] = str(tmp_path / "gone")
    (run / "config.json").write_text(json.dumps(meta))
    p = plan_render(RenderOptions(run, out=tmp_path / "x.mp4", split="train",
                                  dataset=toy_dataset, device="cpu"), log=lambda _: None)
    assert p.codes is not None


@pytest.mark.slow
def test_a_still_camera_reuses_what_the_codes_do_not_change(toy_run, tmp_path):
    """Own codes along a static camera: a frame whose codes are the last one's keeps the
    pixels outside the face (`StillCamera.same_codes`), and each frame is exactly what
    it renders alone."""
    from flamenerf.model import render_image
    from flamenerf.rendering.reanimate import render_sequence

    plan = plan_render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="capture",
                                     camera="static", device="cpu"), log=lambda _: None)
    w, a = plan.codes
    # frames 4 and 5 are held out past the last training frame, 3: both take its codes
    assert torch.equal(w[3], w[4]) and torch.equal(w[4], w[5]) and not torch.equal(w[3], w[2])
    made = []
    real = render_image.StillCamera

    class Counting(real):
        def __init__(self, *args, **kw):
            made.append(1)
            super().__init__(*args, **kw)

    import flamenerf.rendering.reanimate as R
    R.StillCamera, saved = Counting, R.StillCamera
    try:
        frames = [f.rgb for f in plan.frames()]
    finally:
        R.StillCamera = saved
    assert len(made) == 4  # frames 0-3 each their own codes; 4 and 5 reuse 3's renderer
    for i in range(6):
        alone = next(render_sequence(plan.run.model, plan.ds, plan.intr, plan.poses[i:i + 1],
                                     plan.values[i:i + 1], plan.verts[i:i + 1], w[i], a[i],
                                     plan.dilate_px, settings=plan.settings)).rgb
        np.testing.assert_allclose(frames[i], alone, atol=1e-6)
