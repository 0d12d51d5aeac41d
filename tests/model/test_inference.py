"""The inference renderer (model/inference.py) against the training forward."""

import dataclasses

import numpy as np
import pytest
import torch

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import look_at
from flamenerf.model.baked import baked_proposal_logits, baked_warp
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.inference import FAST, REFERENCE, VIEWER, RenderSettings, march
from flamenerf.model.field import HashField
from flamenerf.model.mlp import MLP, fused_cpu_inference
from flamenerf.model.render import render_weights
from flamenerf.model.render_image import render_image
from flamenerf.runtime import map_single_threaded, torch_threads

E = 3
EXACT = RenderSettings(warp_grid=0, proposal_grid=0, min_transmittance=0.0, half=False)


def toy_model(sampler: str = "proposal", mode: str = "masked", guided: bool = False
              ) -> FlameNeRF:
    """tests/toy.py's `fast` machinery with weights that make the scene partly opaque."""
    from toy import toy_config

    cfg = toy_config(mode).model
    cfg.mesh_guide.enabled = guided
    if sampler == "hierarchical":
        cfg.sampler.kind, cfg.field.kind = "hierarchical", "mlp"
        cfg.field.width, cfg.field.depth, cfg.field.skips = 32, 3, (2,)
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=2, expr_dim=E, near=0.5, far=1.6, box_min=[-0.5] * 3,
                  box_max=[0.5] * 3, mesh_vertices=6, mesh_faces=2).eval()
    if m.expression.uses_mesh_model:  # `fast`'s per-control prior: two triangles in front of the camera
        verts = torch.tensor([[-.1, -.1, .1], [.1, -.1, .1], [0, .1, .1], [-.1, 0, .2],
                              [.1, 0, .2], [0, .15, .2]])
        basis = torch.zeros(E, 6, 3)
        basis[0, :3, 1], basis[1, 3:, 0], basis[2, :, 2] = 0.02, 0.01, 0.01
        m.set_expression_model(verts, basis, torch.tensor([[0, 1, 2], [3, 4, 5]]))
    with torch.no_grad():  # random grids and heads, and enough density to stop some rays
        fields = [m.field] + ([m.proposal] if sampler == "proposal" else [m.field_coarse])
        for f in fields:
            for g in (getattr(f, "grid", None), getattr(f, "expr_grid", None)):
                for t in getattr(g, "tables", []):
                    t.uniform_(-1, 1)
            for p in f.parameters():
                if p.dim() == 2:
                    p.mul_(3)
        head = (m.field.density_head.out if sampler == "proposal" else None)
        if head is not None:
            head.bias[0] = 2.0
            m.proposal.head.out.bias.fill_(2.0)
        else:
            m.field.sigma.bias.fill_(3.0)
            m.field_coarse.sigma.bias.fill_(3.0)
    return m


def render(m, settings, size=12, code=0):
    intr = Intrinsics(size, size, 1.2 * size, 1.2 * size, size / 2, size / 2)
    c2w = look_at(np.array([0.1, 0.05, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    w, a = m.codes(torch.tensor([code]))
    mask = np.zeros((size, size), bool)
    mask[3:8, 2:9] = True  # rays with β and rays without
    return render_image(m, intr, c2w, w[0], a[0], torch.tensor([0.7, -0.4, 0.2]), mask,
                        settings=settings)


@pytest.mark.parametrize("sampler", ["proposal", "hierarchical"])
def test_exact_inference_path_equals_reference(sampler):
    """Without termination and bakes the inference path is the training forward's maths;
    only the summation order inside oneDNN's fused matmuls differs: float32 rounding, which
    the hierarchical sampler amplifies (a coarse weight's last bits move the inverse-CDF
    samples of the fine pass), hence 2e-4 on outputs in [0, 1]."""
    m = toy_model(sampler)
    ref, fast = render(m, REFERENCE), render(m, EXACT)
    if sampler == "proposal":  # (the hierarchical sampler's last interval is infinite)
        assert 0.2 < float(ref["acc"].mean()) < 0.999  # opaque and transparent rays
    for k in ("rgb", "acc"):
        assert torch.allclose(fast[k], ref[k], atol=2e-4), (k, (fast[k] - ref[k]).abs().max())


def test_unfinished_rays_render_over_the_trained_background():
    """What a ray leaves unfinished is rendered over `model.background` (0.5 for runs
    trained over random colours) by both paths outside training, and over black in
    training, where the trainer composites its own colours."""
    m = toy_model()
    m.cfg.sampler.refine_main = 0  # rays left unfinished as they are (no second pass)
    black = render(m, REFERENCE)
    m.background = 0.5
    for settings in (REFERENCE, EXACT):
        grey = render(m, settings)
        fill = grey["rgb"] - black["rgb"]
        assert torch.allclose(fill, 0.5 * (1 - black["acc"])[..., None].expand_as(fill),
                              atol=2e-4)
    assert float((1 - black["acc"]).max()) > 0.1  # some rays are left unfinished
    from flamenerf.data.rays import RayBatch

    n = 8
    rays = RayBatch(torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 1.0]),
                    torch.tensor([[0.0, 0.0, -1.0]]).expand(n, 3).contiguous(),
                    *m.codes(torch.zeros(n, dtype=torch.long)), torch.zeros(n, E),
                    torch.zeros(n, dtype=torch.bool), None)
    m.train()
    with torch.no_grad():
        out = m(rays)
    m.eval()
    with torch.no_grad():
        out_eval = m(rays)
    assert torch.allclose(out_eval["rgb"] - out["rgb"], 0.5 * (1 - out["acc"])[:, None],
                          atol=1e-5)


def test_rays_left_unfinished_are_sampled_again():
    """Outside training, a ray whose main samples leave it below 1 − refine_below opacity
    where the proposal says it ends is rendered as with `refine_main` samples, in both
    paths; every other ray as before. The denser samples find more of what the main field
    holds along those rays. Where the proposal sees through the rays too, nothing changes."""
    m = toy_model()
    s = m.cfg.sampler
    n, dense_n = s.num_main, s.refine_main
    assert dense_n > n
    s.refine_main = 0
    once = render(m, REFERENCE)
    s.num_main = dense_n
    dense = render(m, REFERENCE)
    s.num_main, s.refine_main = n, dense_n
    unfinished = once["acc"] < 1 - s.refine_below
    outs = {settings: render(m, settings) for settings in (REFERENCE, EXACT)}
    # the rays rendered again: those the second pass changed
    redo = (outs[REFERENCE]["rgb"] - once["rgb"]).abs().amax(-1) > 1e-4
    assert bool(redo.any()) and bool((unfinished & ~redo).any())  # the proposal's gate
    assert not bool((redo & ~unfinished).any())
    for settings, out in outs.items():
        for k in ("rgb", "depth", "acc"):
            assert torch.allclose(out[k][~redo], once[k][~redo], atol=2e-4), (settings, k)
            assert torch.allclose(out[k][redo], dense[k][redo], atol=2e-4), (settings, k)
    assert float(dense["acc"][redo].mean()) > float(once["acc"][redo].mean())

    with torch.no_grad():  # a proposal that sees through every ray: no second pass
        m.proposal.head.out.bias.fill_(-30.0)
    s.refine_main = 0
    once = render(m, REFERENCE)
    assert bool((once["acc"] < 1 - s.refine_below).any())
    s.refine_main = dense_n
    for settings in (REFERENCE, EXACT):
        out = render(m, settings)
        for k in ("rgb", "depth", "acc"):
            assert torch.allclose(out[k], once[k], atol=2e-4), (settings, k)


def test_second_pass_takes_the_rays_the_proposal_ends():
    """SamplerConfig.unfinished: opacity below 1 − refine_below after the main samples,
    at least that by the proposal."""
    from flamenerf.config import SamplerConfig

    s = SamplerConfig(kind="proposal", refine_below=0.05)
    acc = torch.tensor([0.2, 0.2, 0.96, 0.94, 0.94])
    prop = torch.tensor([1.0, 0.5, 1.0, 0.95, 0.949])
    assert s.unfinished(acc, prop).tolist() == [0, 3]


@pytest.mark.slow
def test_mesh_guided_inference_equals_reference():
    # tracked clips train mesh-guided (fast's default there): the inference path's guide
    # (nearest vertices by k-d tree) is the training forward's
    m = toy_model(guided=True)
    assert m.expression.mesh_guided
    ref, fast = render(m, REFERENCE), render(m, EXACT)
    assert torch.allclose(fast["rgb"], ref["rgb"], atol=2e-4)
    assert (ref["rgb"] - render(toy_model(), REFERENCE)["rgb"]).abs().max() > 1e-3  # it acts


@pytest.mark.slow
def test_centred_expression_inference_equals_reference():
    """With β̄ set (`fast`'s expression_centre) both paths give the networks 𝕀·(β − β̄) and
    the meshes β: the guide and the per-control prior of the inference path take β's
    mesh, not the centred input's."""
    m = toy_model(guided=True)
    # β̄ = the rendered β: the input inside the silhouette is 0 there as outside, and only
    # the rays' mask tells the guide that β's mesh applies
    for mean in ([0.5, -0.3, 0.6], [0.7, -0.4, 0.2]):
        m.set_expression_mean(torch.tensor(mean))
        ref, fast = render(m, REFERENCE), render(m, EXACT)
        assert torch.allclose(fast["rgb"], ref["rgb"], atol=2e-4)
    assert (ref["rgb"] - render(toy_model(guided=True), REFERENCE)["rgb"]).abs().max() > 1e-3


@pytest.mark.parametrize("kernel", ["1", "0"])
def test_bakes_converge_to_the_fields(kernel, monkeypatch):
    """A bake read at the right places converges to its field as the grid gets finer (a
    flipped axis or an off-by-one vertex would not): 4x the vertices per axis cut the error
    3x or more on this random model's warp (O(h²) once the grid resolves its frequencies),
    the proposal's error by 40 % or more.
    Through the CPU kernel and through grid_sample (the GPU path)."""
    import flamenerf.cpu_kernels as ck

    monkeypatch.setattr(ck, "_tried", kernel == "0")
    monkeypatch.setattr(ck, "_lib", None if kernel == "0" else ck._lib)
    m = toy_model()
    code = m.deform_codes.weight[0].detach()
    x = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8
    with torch.no_grad():
        exact_w = m.warp_points(x, code[None])
        errs = [(baked_warp(m, code, n)(x) - exact_w).abs().max() for n in (9, 33)]
        exact_p = m.proposal.raw_density(x, None)
        perr = [(baked_proposal_logits(m.proposal, n, "cpu")(x)[:, 0] - exact_p).abs().mean()
                for n in (9, 33)]
    assert errs[1] < errs[0] / 3, errs
    # the proposal's random fine levels (uniform tables) converge more slowly than the warp
    assert perr[1] < perr[0] * 0.6, perr


@pytest.mark.slow
def test_default_path_renders_the_same_scene():
    """Termination and 128³ bakes: the bakes interpolate this random model's fields, which
    vary much faster than a trained one's (the trained `fast` run: 43 dB against the
    reference, 0.02 dB PSNR against the images; docs/bench/render.md), hence a loose bound."""
    m = toy_model()
    ref, fast = render(m, REFERENCE), render(m, FAST)
    assert float((fast["rgb"] - ref["rgb"]).abs().mean()) < 0.05
    assert float((fast["acc"] - ref["acc"]).abs().mean()) < 0.05


def test_fewer_main_samples_render_the_same_scene():
    """The viewer's setting: a fraction of the model's main samples, the scene the same
    within a loose bound (this random model's fields vary fast)."""
    m = toy_model()
    n = m.cfg.sampler.num_main
    default = render(m, EXACT)
    few = render(m, dataclasses.replace(EXACT, main_fraction=(n - 2) / n))
    assert not torch.equal(few["rgb"], default["rgb"])
    assert float((few["rgb"] - default["rgb"]).abs().mean()) < 0.05
    assert 0 < VIEWER.main_fraction < FAST.main_fraction == 1.0


@pytest.mark.slow
def test_inference_is_deterministic():
    m = toy_model()
    a, b = render(m, FAST), render(m, FAST)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_termination_never_changes_a_ray_with_weight_left():
    """Rays whose transmittance stays above ε are rendered exactly; a terminated ray loses
    only samples that the reference weighs below ε in total."""
    g = torch.Generator().manual_seed(0)
    R, S, eps = 200, 40, 1e-3
    sigma = torch.rand(R, S, generator=g) * torch.rand(R, 1, generator=g) * 8
    deltas = torch.full((R, S), 0.1)
    rgb = torch.rand(R, S, 3, generator=g)
    calls = []

    def evaluate(rows, lo, hi):
        calls.append(len(rows) * (hi - lo))
        return sigma[rows, lo:hi], rgb[rows, lo:hi]

    w, c = march(evaluate, deltas, 8, eps)
    w_ref = render_weights(sigma, deltas)
    t_end = torch.exp(-(sigma * deltas).sum(-1))  # light left after the last sample
    kept = t_end >= eps
    assert 0 < int(kept.sum()) < R and sum(calls) < R * S  # both kinds, and work saved
    assert torch.allclose(w[kept], w_ref[kept], atol=1e-6)
    assert torch.equal(c[kept], rgb[kept])
    evaluated = w > 0
    assert torch.allclose(w[evaluated], w_ref[evaluated], atol=1e-6)
    assert torch.all((w_ref - w).sum(-1) < eps)  # what a terminated ray skipped


def test_fused_mlp_equals_plain():
    torch.manual_seed(0)
    m = MLP(10 + 4, 32, 3, (1,), out_dim=5)
    x, cond = torch.randn(6, 7, 10), torch.randn(6, 1, 4)
    with torch.no_grad():
        plain = m(x, cond)
        with fused_cpu_inference():
            fused = m(x, cond)
    assert torch.allclose(plain, fused, atol=1e-5)


def test_lean_mlp_equals_plain():
    """The GPU's inference layers (fused bias and ReLU, conditioning added in place) give
    the plain path's outputs, for every shape of MLP a model builds; under autocast they
    run in its dtype."""
    torch.manual_seed(0)
    x, cond = torch.randn(6, 7, 10), torch.randn(6, 1, 4)
    cases = [(MLP(10 + 4, 32, 3, (1,), out_dim=5), [x, cond]),  # skip, per-ray conditioning
             (MLP(10, 16, 1, (), out_dim=4), [x]),  # a density head: one input
             (MLP(10 + 4, 16, 0, (), out_dim=2), [x, cond]),  # depth 0: one linear map
             (MLP(10 + 4, 16, 2, ()), [x.reshape(42, 10), cond.expand(6, 7, 4).reshape(42, 4)])]
    with torch.no_grad():
        for m, inputs in cases:
            plain = m(*inputs)
            lean = m.forward_lean(inputs)
            assert lean.shape == plain.shape and lean.dtype == plain.dtype
            assert torch.allclose(lean, plain, atol=1e-5), (lean - plain).abs().max()
        m, inputs = cases[0]
        plain = m(*inputs)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            half = m.forward_lean(inputs)
        assert half.dtype == torch.bfloat16
        err = (half.float() - plain).abs().max() / plain.abs().max()
        assert 0 < err < 0.05, err


def test_features_in_one_buffer_in_the_autocast_dtype():
    """The inference path's features (grid, detail levels, expression fields written side
    by side) equal the training path's `cat`, in the autocast dtype where autocast is on (a
    GPU's half precision; bfloat16 on this CPU stands in for it)."""
    from toy import toy_config

    cfg = toy_config("masked").model.field
    cfg.detail_levels, cfg.detail_max_res, cfg.detail_log2_size = 2, 128, 10
    torch.manual_seed(0)
    field = HashField(cfg, E, (torch.zeros(3), torch.eye(3), torch.full((3,), 0.3)))
    for p in field.parameters():
        torch.nn.init.uniform_(p, -0.5, 0.5)
    assert field.detail is not None and field.expr_grid is not None
    x = torch.rand(50, 3) * 2 - 1
    x[:10] = 0.05 * torch.randn(10, 3)  # inside the detail levels' region
    expr = torch.randn(50, field.expr_dim)
    expr[20:] = 0
    with torch.no_grad():
        ref = torch.cat([field.grid((x + 1) * 0.5), field._detail_features(x),
                         field._expression_features(x, expr)], -1)
        assert ref[:10, field.grid.out_dim:].abs().max() > 0
        plain = field._features_in_place(x, expr)
        assert plain.dtype == torch.float32 and torch.allclose(plain, ref, atol=1e-6)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            half = field._features_in_place(x, expr)
    assert half.dtype == torch.bfloat16
    assert (half.float() - ref).abs().max() < 0.02 * ref.abs().max()


def test_bf16_mlp_stays_close_to_float32(monkeypatch):
    """The bfloat16 layers (CPUs with native bfloat16) give float32 results within
    bfloat16's rounding, per-ray conditioning included; forced on here, so that the path
    runs on any CPU (oneDNN emulates bfloat16 where the CPU lacks it)."""
    import flamenerf.model.mlp as mlp

    monkeypatch.setattr(mlp, "bf16_pays", lambda: True)
    torch.manual_seed(0)
    m = MLP(10 + 4, 32, 3, (1,), out_dim=5)
    x, cond = torch.randn(6, 7, 10), torch.randn(6, 1, 4)
    with torch.no_grad():
        plain = m(x, cond)
        with fused_cpu_inference(bf16=True):
            half = m(x, cond)
        with fused_cpu_inference():
            full = m(x, cond)
    assert half.dtype == torch.float32
    err = (half - plain).abs().max() / plain.abs().max()
    assert 0 < err < 0.03, err  # bfloat16 (8-bit mantissa), not float32 (that path: 1e-5)
    assert torch.allclose(full, plain, atol=1e-5)


def test_bf16_only_where_measured_faster(monkeypatch):
    """bfloat16 layers need native support and a measured gain over float32: the CPU's
    flags alone do not tell (an Intel Xeon with AVX-512 BF16 ran them 2x slower)."""
    import flamenerf.model.mlp as mlp

    cases = [(False, 3.0, False), (True, 0.5, False), (True, mlp.BF16_MIN_GAIN - 0.01, False),
             (True, 2.0, True)]
    for native, gain, expected in cases:
        monkeypatch.setattr(mlp, "_bf16_verdict", None)
        monkeypatch.setattr(mlp, "native_bf16", lambda n=native: n)
        monkeypatch.setattr(mlp, "_measured_gain", lambda g=gain: g)
        assert mlp.bf16_pays() is expected, (native, gain)
        monkeypatch.setattr(mlp, "_measured_gain", lambda: 1 / 0)  # decided once per process
        assert mlp.bf16_pays() is expected
        with fused_cpu_inference(bf16=True):
            assert mlp._fusing.bf16 is (expected and mlp._fusing.on)
    monkeypatch.undo()
    assert mlp._measured_gain() > 0  # the real measurement runs and gives a ratio


def test_bf16_weights_follow_training(monkeypatch):
    """The cached bfloat16 copy of a layer is renewed when an optimiser changes it."""
    import flamenerf.model.mlp as mlp

    monkeypatch.setattr(mlp, "bf16_pays", lambda: True)
    torch.manual_seed(0)
    m = MLP(3, 16, 1, (), out_dim=2)
    x = torch.randn(50, 3)
    with torch.no_grad(), fused_cpu_inference(bf16=True):
        before = m(x)
    opt = torch.optim.SGD(m.parameters(), lr=1.0)
    m(x).square().sum().backward()
    opt.step()
    with torch.no_grad():
        plain = m(x)
        with fused_cpu_inference(bf16=True):
            after = m(x)
    assert (after - before).abs().max() > 0.1
    assert torch.allclose(after, plain, atol=0.05 * float(plain.abs().max()))


def test_warp_bake_follows_the_code_and_the_weights():
    m = toy_model()
    code = m.deform_codes.weight[0].detach()
    baked_warp(m, code, 8)
    grid = m.warp._baked[1]
    baked_warp(m, code, 8)
    assert m.warp._baked[1] is grid  # reused while nothing changes
    baked_warp(m, code + 1, 8)
    assert m.warp._baked[1] is not grid
    x = torch.rand(50, 3) * 2 - 1
    before = baked_warp(m, code, 8)(x)
    with torch.no_grad():  # an optimiser step changes weights in place
        m.warp.trans.bias.add_(0.1)
    after = baked_warp(m, code, 8)(x)
    assert (after - before).abs().max() > 0.05


@pytest.mark.slow
def test_settings_chunk_changes_nothing_but_speed():
    m = toy_model()
    a = render(m, dataclasses.replace(FAST, chunk=7))
    b = render(m, dataclasses.replace(FAST, chunk=1000))
    assert torch.allclose(a["rgb"], b["rgb"], atol=1e-5)


@pytest.mark.slow
def test_proposal_group_changes_nothing_but_speed():
    """One termination check for the whole proposal ray (the GPU's default) and a check
    every few samples render the same image: a ray stops only once its remaining samples
    weigh less than ε."""
    m = toy_model()
    P = m.cfg.sampler.num_proposal
    whole = render(m, dataclasses.replace(FAST, proposal_group=P))
    few = render(m, dataclasses.replace(FAST, proposal_group=4))
    assert float((whole["rgb"] - few["rgb"]).abs().max()) < 1e-3
    assert FAST.proposal_samples_per_check(torch.device("cpu"), P) == FAST.group
    assert FAST.proposal_samples_per_check(torch.device("cuda"), P) == P


def test_gpu_chunk_follows_the_field():
    """On a GPU a hash-grid model renders a 512 px frame in one pass; the paper's MLP
    fields keep passes of 65536 rays (their activations at 262144 rays: tens of GB)."""
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert FAST.rays_per_chunk(cuda, toy_model()) >= 512 * 512
    assert FAST.rays_per_chunk(cuda, toy_model("hierarchical")) == 1 << 16
    assert FAST.rays_per_chunk(cpu, toy_model()) == 2048
    assert dataclasses.replace(FAST, chunk=99).rays_per_chunk(cuda, toy_model()) == 99


@pytest.mark.slow
def test_threads_render_the_same_image_and_restore_the_thread_count():
    """Chunks rendered side by side in Python threads (each with one torch thread) give the
    image one thread gives, and the process keeps its thread count."""
    m = toy_model()
    before = torch.get_num_threads()
    with torch_threads(2):
        one = render(m, dataclasses.replace(FAST, chunk=7, threads=1))
        two = render(m, dataclasses.replace(FAST, chunk=7, threads=2))
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before
    for k in one:
        assert torch.allclose(one[k], two[k], atol=1e-5), k
    assert FAST.render_threads(torch.device("cpu")) == torch.get_num_threads()
    assert REFERENCE.render_threads(torch.device("cpu")) == 1


def test_map_single_threaded_keeps_order_and_gives_each_worker_one_thread():
    import threading

    seen = []

    def work(i):
        seen.append((threading.get_ident(), torch.get_num_threads()))
        return i * i

    with torch_threads(2):
        assert map_single_threaded(work, list(range(20)), 2) == [i * i for i in range(20)]
        assert torch.get_num_threads() == 2
    assert all(n == 1 for _, n in seen)
    assert threading.get_ident() not in {t for t, _ in seen}
    assert map_single_threaded(work, [3], 2) == [9]  # one item: no threads


def test_distinct_rows_matches_unique():
    from flamenerf.model.expression import distinct_rows

    same = torch.tensor([[0.5, -1.0, 2.0]]).repeat(7, 1)
    u, inv = distinct_rows(same)
    assert torch.equal(u, same[:1]) and torch.equal(inv, torch.zeros(7, dtype=torch.long))
    mixed = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    u, inv = distinct_rows(mixed)
    assert torch.equal(u[inv], mixed) and len(u) == 3
    u, inv = distinct_rows(mixed[:0])
    assert len(u) == 0 and len(inv) == 0



def test_half_precision_features_render_the_same_scene(monkeypatch):
    """On CUDA the inference path runs the fields under float16 autocast, where the
    expression features' einsum and the detail levels come back in half precision and
    index_copy does not promote them (CPU autocast does, so it cannot stand in): those
    features are made half here by hand. A model with expression fields and detail levels
    renders, and its image stays close to float32's."""
    from flamenerf.model.encodings import HashGrid
    from toy import toy_config

    cfg = toy_config().model
    cfg.field.detail_levels, cfg.field.detail_max_res, cfg.field.detail_log2_size = 2, 128, 10
    region = {"centre": [0.0, 0.0, 0.1], "axes": np.eye(3).tolist(), "radii": [0.3] * 3}
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=2, expr_dim=E, near=0.5, far=1.6, box_min=[-0.5] * 3,
                  box_max=[0.5] * 3, mesh_vertices=6, mesh_faces=2, detail_region=region).eval()
    same = {k: v for k, v in toy_model().state_dict().items()
            if k in m.state_dict() and v.shape == m.state_dict()[k].shape}
    m.load_state_dict(same, strict=False)  # the toy's mesh model and opaque weights
    with torch.no_grad():
        for t in m.field.detail.tables:
            t.uniform_(-1, 1)
    full = render(m, EXACT)
    einsum, grid = torch.einsum, HashGrid.forward
    monkeypatch.setattr(torch, "einsum", lambda *a: einsum(*a).to(torch.bfloat16))
    monkeypatch.setattr(HashGrid, "forward", lambda self, x: (
        grid(self, x).to(torch.bfloat16) if self is m.field.detail else grid(self, x)))
    half = render(m, EXACT)
    monkeypatch.undo()
    for k in ("rgb", "acc"):
        assert half[k].dtype == torch.float32
        assert 0 < float((half[k] - full[k]).abs().max()) < 0.03, k  # half, and close
