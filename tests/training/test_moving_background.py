"""Background that moves by itself: the dataset's per-frame `moving_path` masks, and the
photometric loss and the face-depth prior that weigh such pixels down."""

from __future__ import annotations

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from toy import toy_config

from flamenerf.config import preset
from flamenerf.data.dataset import Intrinsics, load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.dataset_writer import DatasetWriter
from flamenerf.geometry import look_at
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.losses import LossBatch, LossWeights
from flamenerf.training.trainer import Trainer, moving_shares

SIZE = 8


def write_dataset(out, moving: list[np.ndarray | None]):
    """A dataset of one train frame per entry of `moving` (SIZE x SIZE), each with that
    moving-background mask (None: none given)."""
    intr = Intrinsics(SIZE, SIZE, 10.0, 10.0, SIZE / 2, SIZE / 2)
    verts = np.array([[-0.1, -0.1, 0], [0.1, -0.1, 0], [0, 0.1, 0]], np.float32)
    c2w = look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    with DatasetWriter(out, intr, 0.5, 1.5, ["jawOpen"], "synthetic") as w:
        for i, m in enumerate(moving):
            rgb = np.full((SIZE, SIZE, 3), 0.1 * i, np.float32)
            w.add_frame(rgb, np.zeros((SIZE, SIZE), bool), c2w, np.zeros(1), i, "train",
                        verts=verts, moving=m)
        w.set_faces(np.array([[0, 1, 2]], np.int32))
    return out


def test_writer_writes_and_loader_reads_back_the_moving_mask(tmp_path):
    square = np.zeros((SIZE, SIZE), bool)
    square[2:5, 1:4] = True
    ds = load_dataset(write_dataset(tmp_path / "ds", [square, np.zeros((SIZE, SIZE)), None]))
    meta = json.loads((ds.root / "transforms.json").read_text())
    assert [f.get("moving_path") for f in meta["frames"]] == [
        "moving/000000.png", "moving/000001.png", None]
    assert ds.has_moving and ds.frames[0].moving_path == "moving/000000.png"
    assert iio.imread(ds.root / "moving/000000.png").dtype == np.uint8
    assert np.array_equal(ds.load_moving(ds.frames[0]), square)
    # given but empty: recorded as "nothing moves", not as "not known"
    back = ds.load_moving(ds.frames[1])
    assert back is not None and back.shape == (SIZE, SIZE) and not back.any()
    assert ds.load_moving(ds.frames[2]) is None
    assert "moving_path" not in ds.frames[0].extra
    # a dataset written without them has none
    old = load_dataset(write_dataset(tmp_path / "old", [None, None]))
    assert not old.has_moving and not (old.root / "moving").exists()


def test_missing_or_wrong_moving_file_is_a_one_line_error_naming_it(tmp_path):
    root = write_dataset(tmp_path / "ds", [np.ones((SIZE, SIZE), bool)] * 2)
    (root / "moving/000001.png").unlink()
    with pytest.raises(DatasetError, match=r"moving/000001\.png: file is missing") as e:
        load_dataset(root)
    assert "\n" not in str(e.value)
    iio.imwrite(root / "moving/000001.png", np.zeros((SIZE - 3, SIZE), np.uint8))
    ds = load_dataset(root)
    with pytest.raises(DatasetError, match=r"moving/000001\.png: image is 8x5, "
                                           r"transforms\.json says 8x8") as e:
        ds.load_moving(ds.frames[1])
    assert "\n" not in str(e.value)
    (root / "moving/000001.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"moving/000001\.png: not a readable image"):
        ds.load_moving(ds.frames[1])
    tj = root / "transforms.json"
    meta = json.loads(tj.read_text())
    for value, msg in ((5, "field 'moving_path' has the wrong type"),
                       ("../moving/000000.png", "is outside the dataset")):
        meta["frames"][1]["moving_path"] = value
        tj.write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match=rf"frames\[1\]: .*{msg}"):
            load_dataset(root)


def test_moving_masks_reach_training_as_each_pixels_share(tmp_path):
    half = np.zeros((SIZE, SIZE), bool)
    half[:, :SIZE // 2] = True
    ds = load_dataset(write_dataset(tmp_path / "ds", [half, None]))
    shares = moving_shares(ds, ds.frames, ds.intrinsics.scaled(0.5))
    assert shares.shape == (2, SIZE // 2, SIZE // 2) and shares.dtype == torch.float32
    assert torch.equal(shares[0, :, :SIZE // 4], torch.ones(SIZE // 2, SIZE // 4))
    assert not shares[0, :, SIZE // 4:].any() and not shares[1].any()
    # no mask, or masks where nothing moves: no per-ray weights at all
    empty = load_dataset(write_dataset(tmp_path / "empty", [np.zeros((SIZE, SIZE)), None]))
    assert moving_shares(empty, empty.frames, empty.intrinsics) is None
    assert moving_shares(ds, ds.frames[1:], ds.intrinsics) is None


def _out(n: int = 16, seed: int = 0) -> tuple[dict, torch.Tensor]:
    """A forward pass's outputs as `get_loss_dict` reads them (fine and coarse colours,
    rendering weights over 4 samples) and target colours (n, 3)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(n, 4, generator=g)
    out = {"rgb": torch.rand(n, 3, generator=g), "rgb_coarse": torch.rand(n, 3, generator=g),
           "weights": w / w.sum(-1, keepdim=True), "t": torch.linspace(0.5, 1.5, 4).expand(n, 4)}
    return out, torch.rand(n, 3, generator=g)


def _model() -> FlameNeRF:
    cfg = toy_config().model
    cfg.expression_regions.enabled = False  # no face mesh here
    return FlameNeRF(cfg, num_codes=2, expr_dim=1, near=0.5, far=1.5,
                     box_min=[-1, -1, -1], box_max=[1, 1, 1])


def test_pixels_all_moving_add_nothing_to_the_photometric_loss_at_weight_zero():
    model, (out, target) = _model(), _out()
    weights = LossWeights(face_depth=1.0, moving=0.0)
    depth = torch.full((16,), 1.0)
    full = model.get_loss_dict(out, LossBatch(target, mesh_depth=depth), weights)
    assert full.raw["photo"] > 0 and full.raw["face_depth"] > 0
    moving = model.get_loss_dict(out, LossBatch(target, mesh_depth=depth,
                                                moving=torch.ones(16)), weights)
    assert moving.raw["photo"] == 0 and moving.raw["photo_coarse"] == 0
    assert moving.raw["face_depth"] == 0  # moving rays feed no depth prior
    # half of the rays moving at weight 0.1: those count a tenth, the others as before
    share = (torch.arange(16) % 2).float()
    half = model.get_loss_dict(out, LossBatch(target, moving=share), LossWeights(moving=0.1))
    err = ((out["rgb"] - target) ** 2).mean(-1)
    expect = (err * (1 - 0.9 * share)).mean()
    assert torch.allclose(half.raw["photo"], expect)
    # the static rays' gradient is exactly theirs without masks
    rgb = out["rgb"].clone().requires_grad_(True)
    model.get_loss_dict({**out, "rgb": rgb}, LossBatch(target, moving=share),
                        LossWeights(moving=0.1)).raw["photo"].backward()
    g_masked = rgb.grad.clone()
    rgb.grad = None
    model.get_loss_dict({**out, "rgb": rgb}, LossBatch(target)).raw["photo"].backward()
    assert torch.equal(g_masked[share == 0], rgb.grad[share == 0])


def test_without_masks_the_loss_is_as_before():
    model, (out, target) = _model(), _out(seed=1)
    terms = model.get_loss_dict(out, LossBatch(target), LossWeights(moving=0.1))
    assert torch.equal(terms.raw["photo"], torch.mean((out["rgb"] - target) ** 2))
    assert torch.equal(terms.raw["photo_coarse"],
                       torch.mean((out["rgb_coarse"] - target) ** 2))
    # masks where nothing moves weigh every ray 1
    none = model.get_loss_dict(out, LossBatch(target, moving=torch.zeros(16)),
                               LossWeights(moving=0.1))
    assert torch.equal(none.raw["photo"], terms.raw["photo"])


def _with_moving(src, dst, moving: np.ndarray):
    """A copy of dataset `src` at `dst` whose every frame marks `moving` (H, W) bool."""
    shutil.copytree(src, dst)
    (dst / "moving").mkdir()
    tj = dst / "transforms.json"
    meta = json.loads(tj.read_text())
    for i, fr in enumerate(meta["frames"]):
        iio.imwrite(dst / f"moving/{i:06d}.png", moving.astype(np.uint8) * 255)
        fr["moving_path"] = f"moving/{i:06d}.png"
    tj.write_text(json.dumps(meta))
    return dst


def test_a_step_on_all_moving_pixels_at_weight_zero_has_no_photometric_loss(toy_dataset,
                                                                           tmp_path):
    size = load_dataset(toy_dataset).intrinsics
    ds = _with_moving(toy_dataset, tmp_path / "ds", np.ones((size.h, size.w), bool))
    cfg = toy_config(steps=1)
    cfg.train.moving_weight, cfg.train.face_depth_start, cfg.train.face_ray_fraction = 0, 0, 1
    logs = Trainer(cfg, ds, tmp_path / "run", device="cpu", quiet=True).train_step()
    assert logs["loss/photo"] == 0 and logs["loss/face_depth"] == 0
    plain = Trainer(toy_config(steps=1), toy_dataset, tmp_path / "plain", device="cpu",
                    quiet=True)
    assert plain.moving is None  # no masks: no per-ray weights
    assert plain.train_step()["loss/photo"] > 0


def test_moving_weight_is_a_fraction_with_a_default_in_every_preset():
    from flamenerf.config import PRESETS, from_dict

    assert {preset(n).train.moving_weight for n in PRESETS} == {0.1}
    d = preset("fast").to_dict()
    d["train"]["moving_weight"] = 1.5
    with pytest.raises(Exception, match="train.moving_weight must be between 0 and 1"):
        from_dict(d)


@pytest.mark.slow
def test_cli_moving_weight_reaches_the_run(toy_dataset, tmp_path):
    from flamenerf.cli import main
    from flamenerf.training.run import load_run

    out = tmp_path / "run"
    assert main(["train", str(toy_dataset), "--out", str(out), "--steps", "1",
                 "--batch-rays", "64", "--moving-weight", "0.25", "--device", "cpu"]) == 0
    assert load_run(out).config.train.moving_weight == 0.25
    assert main(["train", str(toy_dataset), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--moving-weight", "2"]) == 2
