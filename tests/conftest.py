"""Shared fixtures: tiny datasets made by the tests themselves."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))

pytest_plugins = ["media"]  # videos and the 48x48 scene shared by several test folders


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The built-in synthetic scene at 32x32, 20 capture frames."""
    from flamenerf.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("scene") / "portrait"
    return make_scene(out, seed=0, size=32, frames=20, reanimate=3, leakage_steps=1, workers=1)


@pytest.fixture(scope="session")
def head_run(tmp_path_factory):
    """A toy run on the built-in scene with head motion (head poses: the model follows the
    head); shared by tests/rendering and tests/viewer."""
    from toy import toy_config

    from flamenerf.synthetic.scene import make_scene
    from flamenerf.training.trainer import train

    root = tmp_path_factory.mktemp("headrun")
    ds = make_scene(root / "scene", seed=2, size=32, frames=8, sway=0.0, reanimate=2,
                    leakage_steps=0, workers=1, head_motion=True)
    train(ds, root / "run", toy_config("masked", 3), device="cpu", quiet=True)
    return root / "run"


@pytest.fixture(scope="session")
def toy_dataset(tmp_path_factory):
    """Every split of the built-in scene at 16x16, made in about a second
    (tests/toy.py); shared by tests/evaluation and tests/rendering."""
    from toy import make_toy_dataset

    return make_toy_dataset(tmp_path_factory.mktemp("toy") / "dataset")


@pytest.fixture(scope="session")
def toy_run(toy_dataset, tmp_path_factory):
    from toy import make_toy_run

    return make_toy_run(toy_dataset, tmp_path_factory.mktemp("toy") / "run", "masked")


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory):
    """The built-in scene at 32x32, 40 capture frames: a face whose mesh moves with its
    expressions (the toy dataset's quad does not), made in a few seconds."""
    from flamenerf.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("synth") / "scene"
    return make_scene(out, seed=1, size=32, frames=40, reanimate=4, leakage_steps=1, workers=1)


@pytest.fixture
def portable_kernels(monkeypatch, tmp_path):
    """A function that rebuilds the CPU kernels without the CPU-specific flag (the build a
    CPU without AVX-512 gets), in a fresh cache, and returns the library it loads."""
    from flamenerf import cpu_kernels

    def build():
        monkeypatch.setenv("FLAMENERF_CACHE", str(tmp_path))
        monkeypatch.setattr(cpu_kernels, "_tried", False)
        monkeypatch.setattr(cpu_kernels, "_lib", None)
        monkeypatch.setattr(cpu_kernels, "_NATIVE", ["-mno-such-flag-here"])
        return cpu_kernels.kernel_library()

    return build
