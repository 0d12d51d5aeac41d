import subprocess
import sys

import numpy as np
import pytest
import torch

from flamenerf.config import PRESETS, preset
from flamenerf.data.dataset import load_dataset
from flamenerf.data.mesh_model import expression_model_residual
from flamenerf.data.scene import FrameSet
from flamenerf.evaluation.metrics import psnr
from flamenerf.model.render_image import render_image
from flamenerf.training.checkpoint import latest_checkpoint
from flamenerf.training.run import load_run
from flamenerf.training.trainer import Trainer, build_for_dataset, learning_rate


def small(cfg, steps):
    """Shrink a preset so that a few steps take well under a second."""
    cfg.train.steps, cfg.train.batch_rays = steps, 256
    cfg.train.checkpoint_every, cfg.train.image_every, cfg.train.log_every = 1000, 0, 1
    cfg.train.face_reg_points = 64
    f, w, s = cfg.model.field, cfg.model.warp, cfg.model.sampler
    w.code_dim, w.width, w.depth, w.skips = 8, 32, 3, (2,)
    if f.kind == "mlp":
        f.width, f.depth, f.skips = 64, 4, (2,)
        s.num_coarse, s.num_fine = 16, 16
    else:
        f.hash_levels, f.hash_log2_size, f.hash_max_res = 8, 14, 128
        s.num_proposal, s.num_main = 32, 12
    return cfg


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_trains_two_steps(name, tiny_scene, tmp_path):
    t = Trainer(small(preset(name), 2), tiny_scene, tmp_path / name, quiet=True)
    res = t.fit()
    assert res.step == 2 and np.isfinite(res.last_psnr)
    run = load_run(tmp_path / name)
    assert run.step == 2 and run.config.preset == name


@pytest.mark.slow
def test_warp_and_appearance_codes_learn_at_their_own_rates(tiny_scene, tmp_path):
    cfg = small(preset("fast"), 5)
    cfg.train.lr_warmup = 0
    cfg.train.warp_lr_scale, cfg.train.appearance_lr_scale = 0.1, 0.01
    cfg.train.deform_code_lr_scale = 1.0  # with the rest (`fast` slows them: below)
    t = Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True)
    t.train_step()
    lr = learning_rate(0, cfg.train)
    rate = {id(p): g["lr"] for g in t.opt.param_groups for p in g["params"]}
    assert rate[id(t.model.warp.trunk.layers[0].weight)] == pytest.approx(lr * 0.1)
    assert rate[id(t.model.appearance_codes.weight)] == pytest.approx(lr * 0.01)
    assert rate[id(t.model.deform_codes.weight)] == pytest.approx(lr)
    assert rate[id(t.model.field.grid.tables[0])] == pytest.approx(lr)
    # every parameter is optimised, and only once
    ids = [id(p) for g in t.opt.param_groups for p in g["params"]]
    assert sorted(ids) == sorted(id(p) for p in t.model.parameters())
    cfg.train.deform_code_lr_scale = 0.1
    t = Trainer(cfg, tiny_scene, tmp_path / "run2", quiet=True)
    t.train_step()
    rate = {id(p): g["lr"] for g in t.opt.param_groups for p in g["params"]}
    assert rate[id(t.model.deform_codes.weight)] == pytest.approx(lr * 0.1)
    ids = [id(p) for g in t.opt.param_groups for p in g["params"]]
    assert sorted(ids) == sorted(id(p) for p in t.model.parameters())


@pytest.mark.slow
def test_fast_preset_overfits_tiny_scene(tiny_scene, tmp_path):
    cfg = small(preset("fast"), 300)
    cfg.train.batch_rays = 1024
    cfg.train.lr_warmup = 20
    cfg.model.warp.anneal_fraction = 0.5
    cfg.model.sampler.num_main, cfg.model.sampler.num_proposal = 32, 64
    t = Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True)
    t.fit()
    ds = load_dataset(tiny_scene)
    fs = FrameSet(ds, ds.split("train")[:3], ds.intrinsics)
    scores = []
    for i in range(3):
        w, a = t.model.codes(fs.frame_index[i:i + 1])
        out = render_image(t.model, ds.intrinsics, fs.c2w[i], w[0], a[0], fs.expressions[i],
                           fs.masks[i])
        scores.append(psnr(out["rgb"].numpy(), fs.images[i].numpy()))
    # a 32x32 textured portrait: a model that learned nothing scores ~12 dB; this
    # configuration measured 24.9 dB
    assert np.mean(scores) > 22.0, scores


@pytest.mark.slow
def test_resume_reproduces_uninterrupted_run(tiny_scene, tmp_path):
    a = Trainer(small(preset("fast"), 6), tiny_scene, tmp_path / "a", quiet=True)
    a.fit()
    b = Trainer(small(preset("fast"), 6), tiny_scene, tmp_path / "b", quiet=True)
    b.fit(steps=3)  # stop half-way through the same 6-step schedule
    b2 = Trainer(small(preset("fast"), 6), tiny_scene, tmp_path / "b", resume=True, quiet=True,
                 steps=6)
    assert b2.step == 3
    b2.fit()
    sa, sb = a.model.state_dict(), b2.model.state_dict()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


@pytest.mark.slow
def test_bf16_is_settled_once_per_run_and_kept_on_resume(tiny_scene, tmp_path, monkeypatch):
    """`train.bf16` asks for bfloat16 layers; a new run settles it by measuring
    (`bf16_pays`) and stores the answer, so a resume trains as the run began whatever a
    new measurement would say, and the layers then really run in bfloat16."""
    import flamenerf.model.mlp as mlp
    import flamenerf.training.trainer as trainer

    seen = []
    real = mlp.MLP._forward_bf16

    def spy(self, inputs):
        seen.append(True)
        return real(self, inputs)

    monkeypatch.setattr(mlp.MLP, "_forward_bf16", spy)
    for pays in (True, False):
        monkeypatch.setattr(trainer, "bf16_pays", lambda p=pays: p)
        cfg = small(preset("fast"), 4)
        assert cfg.train.bf16
        run = tmp_path / f"pays_{pays}"
        seen.clear()
        Trainer(cfg, tiny_scene, run, quiet=True).fit(steps=2)
        assert load_run(run).config.train.bf16 is pays and bool(seen) is pays
        # trained over random colours, rendered over their mean (TrainConfig.render_background)
        assert load_run(run).model.background == 0.5
        monkeypatch.setattr(trainer, "bf16_pays", lambda p=pays: not p)  # the machine changed
        seen.clear()
        t = Trainer(small(preset("fast"), 4), tiny_scene, run, resume=True, quiet=True)
        t.fit()
        assert t.step == 4 and t.cfg.train.bf16 is pays and bool(seen) is pays


@pytest.mark.slow
def test_ctrl_c_saves_a_resumable_checkpoint(tiny_scene, tmp_path, monkeypatch):
    import signal

    t = Trainer(small(preset("fast"), 50), tiny_scene, tmp_path / "run", quiet=True)
    real = t.train_step

    def step():
        if t.step == 4:
            signal.raise_signal(signal.SIGINT)  # Ctrl-C while step 5 is computed
        return real()

    monkeypatch.setattr(t, "train_step", step)
    res = t.fit()
    assert res.interrupted and res.step == 5  # the step in flight completes
    assert latest_checkpoint(tmp_path / "run").name == "step-000000005.ckpt"
    assert Trainer(small(preset("fast"), 50), tiny_scene, tmp_path / "run", resume=True,
                   quiet=True).step == 5


def test_existing_run_without_resume_is_refused(tiny_scene, tmp_path):
    from flamenerf.errors import UserError

    Trainer(small(preset("fast"), 1), tiny_scene, tmp_path / "run", quiet=True).fit()
    with pytest.raises(UserError, match="--resume"):
        Trainer(small(preset("fast"), 1), tiny_scene, tmp_path / "run", quiet=True)


def test_checkpoint_from_an_older_model_layout_is_a_one_line_error(tiny_scene, tmp_path):
    from flamenerf.errors import UserError

    Trainer(small(preset("fast"), 1), tiny_scene, tmp_path / "run", quiet=True).fit()
    ck = latest_checkpoint(tmp_path / "run")
    st = torch.load(ck, weights_only=False)
    key = next(k for k in st["model"] if ".tables." in k)
    st["model"][key] = st["model"][key].t().contiguous()  # hash tables were (F, T) before
    torch.save(st, ck)
    with pytest.raises(UserError, match="older flamenerf") as e:
        load_run(tmp_path / "run")
    assert "\n" not in str(e.value) and ck.name in str(e.value)
    with pytest.raises(UserError, match="older flamenerf"):
        Trainer(small(preset("fast"), 2), tiny_scene, tmp_path / "run", resume=True, quiet=True)


@pytest.mark.slow
def test_cli_bad_dataset_is_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "flamenerf.cli", "train", str(tmp_path / "nope"),
                        "--out", str(tmp_path / "run")], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "nope" in r.stderr and "Traceback" not in r.stderr


def test_cli_expression_mode_gives_the_ablation_of_any_preset(tiny_scene, tmp_path):
    from flamenerf.cli import main

    out = tmp_path / "nerfies-fast"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "2",
                 "--batch-rays", "64", "--expression-mode", "none"]) == 0
    run = load_run(out)
    assert run.config.preset == "fast" and run.config.model.expression_mode == "none"
    assert run.model.field.expr_dim == 0  # the Nerfies variant has no β input at all


def test_face_depth_prior_starts_at_its_share_of_the_run(tiny_scene, tmp_path):
    cfg = small(preset("fast"), 4)
    assert cfg.train.face_depth_weight > 0  # on in `fast`
    cfg.train.face_depth_start, cfg.train.face_ray_fraction = 0.5, 0.5
    t = Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True)
    seen = ["loss/face_depth" in t.train_step() for _ in range(4)]
    assert seen == [False, False, True, True]


@pytest.mark.slow
def test_cli_face_depth_weight_reaches_the_run(tiny_scene, tmp_path):
    from flamenerf.cli import main

    out = tmp_path / "run"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "1",
                 "--batch-rays", "64", "--face-depth-weight", "0.5"]) == 0
    assert load_run(out).config.train.face_depth_weight == 0.5
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--face-depth-weight", "-1"]) == 2


@pytest.mark.slow
def test_cli_detail_levels_background_and_view_dependence_reach_the_run(tiny_scene, tmp_path):
    from flamenerf.cli import main

    out = tmp_path / "run"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "1",
                 "--batch-rays", "64", "--detail-levels", "0", "--random-background",
                 "False", "--view-dependent", "False", "--bf16", "False", "--seed", "3"]) == 0
    cfg = load_run(out).config
    assert cfg.train.seed == 3 and preset("fast").train.seed == 0
    assert not cfg.train.bf16 and preset("fast").train.bf16
    assert cfg.model.field.detail_levels == 0 and not cfg.train.random_background
    assert not cfg.model.field.view_dependent and preset("fast").model.field.view_dependent
    assert preset("fast").model.field.detail_levels > 0 and preset("fast").train.random_background
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--detail-levels", "-1"]) == 2
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--seed", str(2 ** 64)]) == 2
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_mesh_guided_training_carries_the_expression_model(synth_scene, tmp_path):
    cfg = small(preset("fast"), 2)
    cfg.model.mesh_guide.enabled = True
    Trainer(cfg, synth_scene, tmp_path / "run", quiet=True).fit()
    run = load_run(tmp_path / "run")
    m, ds = run.model, load_dataset(synth_scene)
    assert m.expression.mesh_guided
    # the run holds the β -> mesh model: a frame's β gives (about) its tracked mesh
    fr = ds.split("val")[0]
    mesh = m.expression.face_mesh(torch.from_numpy(fr.expression.astype(np.float32)))
    err = (mesh - torch.from_numpy(ds.face_vertices[fr.position])).norm(dim=-1).mean()
    assert err < 2e-3  # metres
    # points near the mouth move with jawOpen, the rest of the scene does not
    jaw = torch.zeros(ds.expression_dim)
    jaw[ds.expression_names.index("jawOpen")] = 1.0
    chin = m.normalize(m.expression.face_mesh(jaw))  # (V, 3): where the open jaw's vertices are
    far = torch.tensor([[0.9, 0.9, -0.9]])
    x = torch.cat([chin, far])[:, None]  # (V + 1, 1, 3) as rays of one sample
    # the guide takes what the networks see (`masked_expression`: β centred in `fast`) and
    # which rays the prior lets β reach
    inside, outside = torch.ones(len(x), dtype=torch.bool), torch.zeros(len(x), dtype=torch.bool)
    e = m.expression.masked(jaw.expand(len(x), -1), inside)
    moved = (m.expression.guide_points(x, e, inside) - x).norm(dim=-1)[:, 0]
    assert moved[:-1].max() > 0.01 and moved[-1] == 0
    # and with β masked to zero (a ray outside the prior's silhouette) nothing moves
    e = m.expression.masked(jaw.expand(len(x), -1), outside)
    assert torch.equal(m.expression.guide_points(x, e, m.expression.inside(outside)), x)


@pytest.mark.slow
def test_vertices_the_mesh_model_misses_do_not_guide(synth_scene, tmp_path):
    """`mesh_guide.max_residual`: the vertices whose β -> mesh fit misses the training
    meshes by more than it are left out of the guide, and a loaded run keeps them out."""
    ds = load_dataset(synth_scene)
    cfg = small(preset("fast"), 2)
    cfg.model.mesh_guide.enabled = True
    assert cfg.model.mesh_guide.max_residual == 0.0015  # `fast`'s
    cfg.model.mesh_guide.max_residual = None
    m0 = build_for_dataset(cfg, ds)
    assert not m0.expression.guide_skip.any()
    miss = expression_model_residual(ds, m0.expression.mesh_neutral, m0.expression.mesh_basis)
    limit = float(miss.quantile(0.9))
    cfg.model.mesh_guide.max_residual = limit
    Trainer(cfg, synth_scene, tmp_path / "run", quiet=True).fit()
    m = load_run(tmp_path / "run").model
    assert torch.equal(m.expression.guide_skip, miss > limit) and 0 < int(m.expression.guide_skip.sum()) < len(miss)
    jaw = torch.zeros(ds.expression_dim)
    jaw[ds.expression_names.index("jawOpen")] = 1.0
    x = m.normalize(m.expression.face_mesh(jaw))[:, None]  # (V, 1, 3)
    inside = torch.ones(len(x), dtype=torch.bool)
    e = m.expression.masked(jaw.expand(len(x), -1), inside)
    moved = (m.expression.guide_points(x, e, inside) - x).norm(dim=-1)[:, 0]
    assert moved.max() > 0.01
    m.set_guide_skip(torch.arange(len(miss)))  # none guides: nothing moves
    assert torch.equal(m.expression.guide_points(x, e, inside), x)


def test_face_ray_fraction_draws_that_share_from_the_silhouettes(tiny_scene):
    ds = load_dataset(tiny_scene)
    fs = FrameSet(ds, ds.split("train"), ds.intrinsics)
    g = torch.Generator().manual_seed(0)
    uniform = fs.masks[fs.sample_pixels(4000, g)].float().mean()
    fi, ys, xs = fs.sample_pixels(4000, g, face_fraction=0.5)
    assert len(fi) == len(ys) == len(xs) == 4000
    on_face = fs.masks[fi, ys, xs].float()
    assert on_face[2000:].min() == 1  # the face half is all face
    assert abs(on_face.mean() - (0.5 + 0.5 * uniform)) < 0.05


@pytest.mark.slow
def test_face_depth_prior_moves_the_face_onto_its_mesh(synth_scene, tmp_path):
    """The face-depth prior is trained into the model: with it the rendered face lies
    closer to the tracked mesh than without (same seed, same steps)."""
    ds = load_dataset(synth_scene)
    fs = FrameSet(ds, ds.split("train")[:2], ds.intrinsics)
    target = fs.mesh_depths()
    errors = {}
    for w in (0.0, 1.0):
        cfg = small(preset("fast"), 60)
        cfg.train.face_depth_weight, cfg.train.face_ray_fraction = w, 0.5
        cfg.train.face_depth_start = 0.0
        # the prior alone: at 32 px and 60 steps the random background's opaque room is
        # still forming (the prior with it: 2.6-3.6 mm in the 128 px benchmarks)
        cfg.train.random_background = False
        t = Trainer(cfg, synth_scene, tmp_path / f"w{w}", quiet=True)
        logs = t.train_step()
        assert ("loss/face_depth" in logs) == (w > 0)
        t.fit()
        err = []
        for i in range(fs.n):
            om, ph = t.model.codes(fs.frame_index[i:i + 1])
            out = render_image(t.model, ds.intrinsics, fs.c2w[i], om[0], ph[0],
                               fs.expressions[i], fs.masks[i])
            hit = torch.isfinite(target[i]) & fs.masks[i]
            err.append((out["depth"][hit] - target[i][hit]).abs().median().item())
        errors[w] = float(np.mean(err))
    assert errors[1.0] < 0.7 * errors[0.0], errors


@pytest.mark.slow
def test_hash_grid_resolution_settles_to_one_training_pixel_at_the_face(tiny_scene, tmp_path):
    from flamenerf.data.scene import face_pixel_resolution, scene_box

    ds = load_dataset(tiny_scene)
    res = face_pixel_resolution(ds, ds.intrinsics)
    assert abs(res - 2 * face_pixel_resolution(ds, ds.intrinsics.scaled(0.5))) <= 2
    # one cell of the grid, moved across frame 0's view at the face, moves one pixel
    lo, hi = map(np.asarray, scene_box(ds))
    cell = (hi - lo).max() / res
    fr = ds.split("train")[0]
    R, o = fr.c2w[:3, :3], fr.c2w[:3, 3]
    cam = (ds.face_vertices[fr.position] - o) @ R
    p = cam[np.argmin(np.abs(-cam[:, 2] - np.median(-cam[:, 2])))]
    px = [ds.intrinsics.fx * q[0] / -q[2] for q in (p, p + np.array([cell, 0, 0]))]
    assert 0.9 < px[1] - px[0] < 1.1
    # a run settles it for the size it trains at, and keeps what it trained with
    cfg = small(preset("fast"), 1)
    cfg.model.field.hash_max_res, cfg.train.downscale = 0, 2.0
    Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True).fit()
    run = load_run(tmp_path / "run")
    expected = face_pixel_resolution(ds, ds.intrinsics.scaled(0.5))
    assert run.config.model.field.hash_max_res == max(expected, 2 * cfg.model.field.hash_base_res)


def test_detail_levels_settle_to_two_cells_per_training_pixel_at_the_face(tiny_scene, tmp_path):
    from flamenerf.data.head_pose import head_region
    from flamenerf.data.scene import face_pixel_resolution

    ds = load_dataset(tiny_scene)
    cfg = small(preset("fast"), 1)
    cfg.model.field.hash_max_res, cfg.model.field.detail_levels = 16, 2
    Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True).fit()
    run = load_run(tmp_path / "run")
    assert (run.config.model.field.detail_max_res
            == max(2 * face_pixel_resolution(ds, ds.intrinsics), 16 + 2))
    # the loaded model's detail levels act in the dataset's head region
    got = run.model.init_args["detail_region"]
    assert np.allclose(got["centre"], head_region(ds).centre)


def test_random_background_shows_through_transparent_rays_only(tiny_scene, tmp_path):
    from flamenerf.training.trainer import over_random_background

    out = {"rgb": torch.tensor([[0.2, 0.3, 0.4], [0.0, 0.0, 0.0], [0.1, 0.1, 0.1]]),
           "acc": torch.tensor([1.0, 0.0, 0.5])}
    colour = torch.tensor([[0.9, 0.9, 0.9], [0.5, 0.6, 0.7], [0.2, 0.4, 0.6]])
    got = over_random_background(out, colour)
    assert torch.allclose(got["rgb"], torch.tensor([[0.2, 0.3, 0.4], [0.5, 0.6, 0.7],
                                                    [0.2, 0.3, 0.4]]))
    assert torch.equal(out["rgb"][1], torch.zeros(3)), "the forward's output is left as is"
    cfg = small(preset("fast"), 2)
    cfg.train.random_background = True
    res = Trainer(cfg, tiny_scene, tmp_path / "run", quiet=True).fit()
    assert res.step == 2 and np.isfinite(res.last_psnr)
