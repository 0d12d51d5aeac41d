"""Shared fixtures: tiny datasets made by the tests themselves."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The built-in synthetic scene at 32x32, 20 capture frames."""
    from flamenerf.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("scene") / "portrait"
    return make_scene(out, seed=0, size=32, frames=20, reanimate=3, leakage_steps=1, workers=1)
