"""A re-animation from a still camera renders only the face's pixels again after its first
frame (rendering/reanimate.py): the frames must be those of rendering each one whole."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.mark.slow
def test_still_camera_frames_equal_whole_renders(toy_run, toy_dataset, monkeypatch, tmp_path):
    from flamenerf.data.prior import dataset_dilation, prior_mask
    from flamenerf.model import render_image as ri
    from flamenerf.model.inference import FAST
    from flamenerf.rendering import reanimate
    from flamenerf.training.run import load_run

    run = load_run(toy_run, "cpu")
    ds = run.dataset(None)
    intr = run.train_intrinsics(ds)
    omega, phi = run.frame_codes(0)
    rng = np.random.default_rng(0)
    T = 5
    betas = (rng.uniform(-1, 1, (T, ds.expression_dim)) * 2).astype(np.float32)
    betas[2] = betas[1]  # the same expression twice: nothing to render again
    betas[3] = betas[2]  # ... and again, under another mesh (another frame of a clip):
    c2w = ds.frames[0].c2w  # the rays of either silhouette
    cams = np.repeat(c2w[None], T, 0)
    cams[4] = ds.frames[1].c2w  # the camera moves: the whole frame
    verts = np.repeat(ds.face_vertices[:1], T, 0)
    verts[3] = verts[3] + np.float32([0.03, 0.0, 0.0])
    dil = dataset_dilation(ds)
    rendered = []
    real = ri.render_pixels

    def counted(*a, **k):
        if a[7] is not None:  # the pixels rendered (None: this test's whole images)
            rendered.append(len(a[7]))
        return real(*a, **k)

    monkeypatch.setattr(ri, "render_pixels", counted)
    frames = list(reanimate.render_sequence(run.model, ds, intr, cams, betas, verts, omega,
                                            phi, dil))
    n = intr.h * intr.w
    mask = prior_mask(ds, verts[0], c2w, intr, dil)
    moved = prior_mask(ds, verts[3], c2w, intr, dil)
    # frame 0 whole, frame 1 its silhouette, frame 2 (the same β) nothing, frame 3 (the
    # same β, the mesh moved) both silhouettes, frame 4 whole
    assert (moved != mask).any()
    assert rendered == [n, mask.sum(), (mask | moved).sum(), n] and 0 < mask.sum() < n
    rendered.clear()
    for i, fr in enumerate(frames):
        whole = ri.render_image(run.model, intr, cams[i], omega, phi,
                                torch.from_numpy(betas[i]), fr.mask, settings=FAST)
        for k in ("rgb", "depth", "acc"):
            assert np.allclose(getattr(fr, k), whole[k].numpy(), atol=1e-5), (i, k)
    assert np.abs(frames[1].rgb - frames[0].rgb).max() > 1e-4  # β moved the face
    # the no-prior ablation: β reaches every ray, every frame is rendered whole
    rendered.clear()
    run.model.cfg.expression_mode = "everywhere"
    list(reanimate.render_sequence(run.model, ds, intr, cams, betas, verts, omega, phi, dil))
    assert rendered == [n] * T
    # the Nerfies variant: β reaches nothing, the still camera's frames are the first one's
    from toy import make_toy_run

    nerfies = load_run(make_toy_run(toy_dataset, tmp_path / "nerfies", "none"),
                       "cpu")
    rendered.clear()
    frames = list(reanimate.render_sequence(nerfies.model, ds, intr, cams, betas, verts,
                                            *nerfies.frame_codes(0), dil))
    assert rendered == [n, n]
    assert np.array_equal(frames[1].rgb, frames[0].rgb)
