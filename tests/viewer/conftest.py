"""A tiny trained run for the viewer tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_run(tiny_scene, tmp_path_factory):
    """Two training steps of a shrunk `fast` preset: a model whose face pixels depend on
    the expression (only through the face mask: the spatial prior)."""
    from flamenerf.config import preset
    from flamenerf.training.trainer import Trainer

    cfg = preset("fast")
    cfg.train.steps, cfg.train.batch_rays, cfg.train.face_reg_points = 2, 256, 64
    cfg.train.checkpoint_every, cfg.train.image_every, cfg.train.log_every = 1000, 0, 1
    cfg.model.expression_scale = 50.0  # an untrained model barely reacts to β otherwise
    # β as it is: centred, every control's input is ±50·β̄ at any slider position and the
    # untrained density head saturates (the face's response to a slider shrinks ~7x)
    cfg.model.expression_centre = False
    # β's effect here is the initial weights' (as in tests/toy.py): no random background, and
    # no detail levels, whose inputs widen the density head and shrink its initial weights
    # (the toy runs of the rendering tests keep them)
    cfg.train.random_background, cfg.model.field.detail_levels = False, 0
    f, w, s = cfg.model.field, cfg.model.warp, cfg.model.sampler
    w.code_dim, w.width, w.depth, w.skips = 8, 32, 3, (2,)
    f.hash_levels, f.hash_log2_size, f.hash_max_res = 8, 14, 128
    if hasattr(s, "num_proposal"):
        s.num_proposal, s.num_main = 32, 12
    # two steps leave the main field's rays unfinished where the proposal already says
    # they end, and a second pass with more samples (what a trained model gives only the
    # few rays the proposal misses) weighs the thin shell around the mesh where β acts ~4x
    # less than these 12 samples do: a slider's effect would fall under the test's
    # threshold. The second pass itself is tested in tests/model/test_inference.py.
    s.refine_main = 0
    out = tmp_path_factory.mktemp("viewer") / "run"
    Trainer(cfg, tiny_scene, out, quiet=True, device="cpu").fit()
    return out
