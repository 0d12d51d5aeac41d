import pytest
import torch

from flamenerf.config import override, preset
from flamenerf.model.flame_nerf import FlameNeRF, RayBatch
from flamenerf.model.losses import face_region_loss

E = 5


def tiny(name: str, kind: str = "mlp", **sets) -> FlameNeRF:
    # no face mesh here: the per-control prior (which needs one) only where asked for
    sets = {"expression_regions.enabled": False, **sets}
    cfg = override(preset(name), {f"model.{k}": v for k, v in sets.items()}).model
    cfg.warp.code_dim, cfg.warp.width, cfg.warp.depth, cfg.warp.skips = 4, 16, 2, ()
    cfg.warp.init_scale = 0.1  # a warp that really moves points, so gradients flow
    if kind == "mlp":
        cfg.field.kind, cfg.field.width, cfg.field.depth, cfg.field.skips = "mlp", 32, 3, (2,)
        cfg.sampler.kind, cfg.sampler.num_coarse, cfg.sampler.num_fine = "hierarchical", 8, 8
    else:
        cfg.field.kind, cfg.field.hash_levels, cfg.field.hash_log2_size = "hash", 4, 10
        cfg.field.hash_max_res, cfg.field.head_width = 64, 16
        cfg.sampler.kind, cfg.sampler.num_proposal, cfg.sampler.num_main = "proposal", 16, 8
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=3, expr_dim=E, near=0.5, far=1.5,
                  box_min=[-1, -1, -1], box_max=[1, 1, 1])
    if kind == "mlp":  # some density on every ray, so that every ray has a gradient
        for f in (m.field, m.field_coarse):
            torch.nn.init.constant_(f.sigma.bias, 1.0)
    return m


def rays(model, n=8, face=None):
    g = torch.Generator().manual_seed(1)
    o = torch.zeros(n, 3)
    o[:, 2] = 1.0
    d = torch.randn(n, 3, generator=g) * 0.2
    d[:, 2] = -1
    omega, phi = model.codes(torch.zeros(n, dtype=torch.long))
    expr = torch.rand(n, E, generator=g).requires_grad_(True)
    face = torch.arange(n) % 2 == 0 if face is None else face
    return RayBatch(o, d, omega, phi, expr, face)


@pytest.mark.parametrize("kind,sets", [
    ("mlp", {}), ("hash", {}),
    ("hash", {"field.expr_rank": 2, "field.expr_direct": False}),  # only the local pathway
    ("mlp", {"warp.expression_input": True}),  # β moves points too
])
def test_spatial_prior_cuts_expression_outside_mask(kind, sets):
    m = tiny("flame-in-nerf", kind, **sets)
    r = rays(m)
    out = m(r)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    g = r.expression.grad
    assert torch.all(g[~r.face_ray] == 0), "β leaked to rays outside the silhouette"
    assert torch.all(g[r.face_ray].abs().sum(-1) > 0), "β has no effect inside the silhouette"


def test_no_prior_feeds_expression_everywhere():
    m = tiny("no-prior")
    r = rays(m)
    m(r)["rgb"].sum().backward()
    assert torch.all(r.expression.grad.abs().sum(-1) > 0)


@pytest.mark.parametrize("kind", ["mlp", "hash"])
def test_nerfies_ignores_expression(kind):
    m = tiny("nerfies", kind)
    r = rays(m, face=torch.ones(8, dtype=torch.bool))
    a = m(r)["rgb"]
    r2 = RayBatch(r.origins, r.dirs, r.deform_code, r.appearance_code,
                  torch.rand_like(r.expression), r.face_ray)
    assert torch.equal(a, m(r2)["rgb"])
    assert m.field.expr_dim == 0


@pytest.mark.parametrize("kind", ["mlp", "hash"])
@pytest.mark.parametrize("view_dependent", [True, False])
def test_colour_sees_the_viewing_direction_only_when_asked(kind, view_dependent):
    m = tiny("fast", kind, **{"field.view_dependent": view_dependent})
    x = torch.rand(6, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    app = torch.randn(6, m.cfg.field.appearance_dim)
    with torch.no_grad():
        _, c1 = m.field(x, d, app, torch.zeros(6, E))
        _, c2 = m.field(x, -d, app, torch.zeros(6, E))
    assert torch.equal(c1, c2) != view_dependent


def test_expression_input_warp_holds_still_at_zero_expression():
    """The face-region regulariser sees the warp with β = 0: ω alone must not move the
    face, while β may."""
    m = tiny("flame-in-nerf", **{"warp.expression_input": True})
    assert m.warp_expression
    x, code = torch.rand(16, 3) * 2 - 1, torch.randn(16, 4)
    zero = torch.zeros(16, E)
    assert torch.equal(m.warp_points(x, code), m.warp_points(x, code, zero))
    assert not torch.allclose(m.warp_points(x, code), m.warp_points(x, code, zero + 1.0))


def test_face_region_loss_zero_for_identity_warp():
    m = tiny("flame-in-nerf")
    for head in (m.warp.rot, m.warp.trans):
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.zeros_(head.bias)
    x = torch.rand(64, 3) * 2 - 1
    code = torch.randn(64, 4)
    assert face_region_loss(m.warp_points(x, code), x).item() == 0.0
    m2 = tiny("flame-in-nerf")
    assert face_region_loss(m2.warp_points(x, code), x).item() > 0.0


def test_shapes_of_outputs():
    for kind in ("mlp", "hash"):
        m = tiny("flame-in-nerf", kind)
        out = m(rays(m, n=6))
        assert out["rgb"].shape == (6, 3) and out["depth"].shape == (6,)
        assert out["acc"].shape == (6,)


def regions_model() -> FlameNeRF:
    """A hash model with the per-control prior on a two-triangle 'face': control 0 moves the
    first triangle, control 1 the second, the others move nothing."""
    cfg = override(preset("fast"), {"model.warp.code_dim": 4, "model.field.hash_levels": 4,
                                    "model.field.hash_log2_size": 10,
                                    "model.field.hash_max_res": 64,
                                    "model.field.head_width": 16,
                                    "model.sampler.num_proposal": 16,
                                    "model.sampler.num_main": 8}).model
    assert cfg.expression_regions.enabled and not cfg.field.expr_direct
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=3, expr_dim=E, near=0.5, far=1.5, box_min=[-1, -1, -1],
                  box_max=[1, 1, 1], mesh_vertices=6, mesh_faces=2)
    verts = torch.tensor([[0, 0, 0], [.1, 0, 0], [0, .1, 0], [.3, .3, 0], [.4, .3, 0],
                          [.3, .4, 0.]])
    basis = torch.zeros(E, 6, 3)
    basis[0, :3, 1], basis[1, 3:, 0] = 0.05, 0.02
    m.set_expression_model(verts, basis, torch.tensor([[0, 1, 2], [3, 4, 5]]))
    return m


def test_expression_regions_gate_each_control_near_what_it_moves():
    m = regions_model()
    # at the β = 1 mesh's vertices 0 and 3 (moved by their controls), and far away
    pts = torch.tensor([[[0.0, 0.05, 0.0], [0.32, 0.3, 0.0], [0.9, -0.9, 0.5]]])  # (1, 3, 3)
    gates = m.expression._region_gates(pts, torch.ones(1, E))[0]  # (3, E)
    assert gates[0, 0] > 0.5 and gates[0, 1] == 0, "control 0 acts near its triangle only"
    assert gates[1, 1] > 0.5 and gates[1, 0] == 0, "control 1 acts near its triangle only"
    assert gates[2].max() < 1e-6, "far from the face no control acts"
    assert torch.all(gates[:, 2:] == 0), "controls that move nothing reach nothing"
    assert torch.all(m.expression._region_gates(pts, torch.zeros(1, E)) == 0)


def test_expression_region_gates_of_many_rays_are_each_rays_own():
    """Rays share meshes where their β agree (one per distinct β, one for a whole image):
    every ray still gets the gates of its own expression's mesh."""
    m = regions_model()
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(7, 4, 3, generator=g) * 0.6 - 0.1
    betas = torch.rand(3, E, generator=g)
    expr = betas[torch.tensor([0, 1, 0, 2, 2, 0, 1])]
    expr[4] = 0  # a ray outside the silhouette
    one = [m.expression._region_gates(pts[i:i + 1], expr[i:i + 1]) for i in range(7)]
    assert torch.allclose(m.expression._region_gates(pts, expr), torch.cat(one), atol=1e-6)
    same = betas[:1].expand(7, E)
    assert torch.allclose(m.expression._region_gates(pts, same),
                          torch.cat([m.expression._region_gates(pts[i:i + 1], same[:1]) for i in range(7)]),
                          atol=1e-6)


def test_a_centred_expression_reaches_the_networks_as_its_difference_from_the_mean():
    """`expression_centre`: the networks see 𝕀·(β − β̄), while the meshes behind the
    per-control prior are those of β itself, and a rebuilt run keeps β̄."""
    m, plain = regions_model(), regions_model()
    mean = torch.tensor([0.6, 0.4, 0.2, 0.0, 0.1])
    m.set_expression_mean(mean)
    beta = torch.stack([mean, mean + torch.tensor([0.3, -0.2, 0.0, 0.5, 0.0]), mean])
    face = torch.tensor([True, True, False])
    e = m.expression.masked(beta, face)
    assert torch.equal(e[0], torch.zeros(E)), "the mean face inside is what outside is"
    assert torch.allclose(e[1], beta[1] - mean) and torch.equal(e[2], torch.zeros(E))
    inside = m.expression.inside(face)
    raw, _ = m.expression.raw(e, inside)
    assert torch.allclose(raw[:2], beta[:2]) and torch.equal(raw[2], torch.zeros(E))
    pts = torch.tensor([[0.0, 0.05, 0.0], [0.32, 0.3, 0.0], [0.05, 0.03, 0.0]]).expand(3, 3, 3)
    # the gates of β's own mesh (as without centring), not of β − β̄'s
    gates = plain.expression._region_gates(pts, beta * face[:, None])
    assert torch.allclose(m.expression.region_expression(pts, e, inside), gates * e[:, None], atol=1e-6)
    assert not torch.allclose(m.expression._region_gates(pts[:1], beta[:1] - mean), gates[:1], atol=1e-4)
    assert gates[0].amax() > 0.5, "the mean face's rays keep their gates (input 0)"
    again = FlameNeRF(m.cfg, **m.init_args)
    assert torch.allclose(again.expression.mean, mean)
    assert torch.equal(regions_model().expression.mean, torch.zeros(E))


def test_expression_regions_keep_the_silhouette_prior():
    m = regions_model()
    r = rays(m)
    # aim the rays through the two triangles, so that samples come within the gates' reach
    target = m.expression.mesh_neutral[torch.arange(8) % 6] + 0.02
    r.dirs = target - r.origins
    out = m(r)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    g = r.expression.grad
    assert g is not None and g[r.face_ray, :2].abs().sum() > 0, "β acts on the face"
    assert torch.all(g[~r.face_ray] == 0), "β leaked to rays outside the silhouette"
    assert torch.all(g[:, 2:] == 0), "a control without a region has no effect"


def test_nearest_vertex_matches_brute_force_within_the_bound():
    from flamenerf.meshes import nearest_vertices

    g = torch.Generator().manual_seed(4)
    verts, pts = torch.rand(50, 3, generator=g), torch.rand(300, 3, generator=g) * 1.6 - 0.3
    d2, i = nearest_vertices(pts, verts, 1, 0.2)  # the gates' query: the nearest alone
    d, i = d2[:, 0].sqrt(), i[:, 0]
    bd, bi = torch.cdist(pts.double(), verts.double()).min(-1)
    bd = bd.float()
    near = bd <= 0.2
    assert near.any() and (~near).any()
    assert torch.allclose(d[near], bd[near], atol=1e-5) and torch.equal(i[near], bi[near])
    assert torch.isinf(d[~near]).all() and (i[~near] == 0).all()



@pytest.mark.parametrize("kind", ["mlp", "hash"])
def test_training_forward_hands_out_the_weights_and_depths_it_rendered(kind):
    m = tiny("fast", kind)
    r = rays(m)
    m.train()
    out = m(r, jitter=True)
    w, t = out["weights"], out["t"]
    assert w.shape == t.shape and w.shape[0] == len(r)
    assert torch.allclose((w * t).sum(-1) / w.sum(-1).clamp_min(1e-6), out["depth"], atol=1e-5)
    m.eval()
    assert "weights" not in m(r)


def test_detail_levels_act_in_the_head_region_only():
    """The finer levels reach only points in (or within the band of) the region, and only
    those points train them."""
    region = {"centre": [0.2, 0.0, 0.0], "axes": torch.eye(3).tolist(),
              "radii": [0.1, 0.15, 0.1]}
    m = tiny("fast", "hash", **{"field.detail_levels": 2, "field.detail_max_res": 256})
    cfg = m.cfg
    assert m.field.detail is None, "a model built without a region has no detail levels"
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=3, expr_dim=E, near=0.5, far=1.5, box_min=[-2, -2, -2],
                  box_max=[2, 2, 2], detail_region=region)  # normalised: halved
    assert m.field.detail.res.tolist() == [128, 256]
    for t in m.field.detail.tables:
        torch.nn.init.uniform_(t, -1, 1)
    inside = torch.tensor([[0.1, 0.0, 0.0], [0.1, 0.07, 0.0]])  # normalised
    outside = torch.tensor([[0.1, 0.0, 0.07], [-0.3, 0.0, 0.0]])  # beyond 1.2 radii
    feats = m.field._detail_features(torch.cat([inside, outside]))
    assert torch.all(feats[:2].abs().sum(-1) > 0) and torch.all(feats[2:] == 0)
    m.field.density(outside, torch.zeros(2, E)).sum().backward()
    assert all(t.grad is None or torch.all(t.grad == 0) for t in m.field.detail.tables)
    m.field.density(inside, torch.zeros(2, E)).sum().backward()
    assert any(torch.any(t.grad != 0) for t in m.field.detail.tables)
    # a loaded run rebuilds the region from the model's init arguments
    m2 = FlameNeRF(cfg, **m.init_args)
    assert torch.equal(m2.field.detail_radii, m.field.detail_radii)
    assert torch.allclose(m.field.detail_centre, torch.tensor([0.1, 0.0, 0.0]))


def test_inference_features_in_one_buffer_match_the_concatenation():
    """Without autograd on a CPU the field writes its grid, detail and expression features
    side by side into one buffer; the values are those of the training path's `cat`, for
    points inside and outside the detail region and with and without β."""
    region = {"centre": [0.2, 0.0, 0.0], "axes": torch.eye(3).tolist(),
              "radii": [0.3, 0.3, 0.3]}
    cfg = tiny("fast", "hash", **{"field.detail_levels": 2, "field.detail_max_res": 256,
                                  "field.expr_rank": 2}).cfg
    torch.manual_seed(0)
    m = FlameNeRF(cfg, num_codes=3, expr_dim=E, near=0.5, far=1.5, box_min=[-2, -2, -2],
                  box_max=[2, 2, 2], detail_region=region)
    for grid in (m.field.grid, m.field.detail, m.field.expr_grid):
        for t in grid.tables:
            torch.nn.init.uniform_(t, -1, 1)
    x = torch.rand(37, 5, 3) - 0.5
    expr = torch.randn(37, 1, E)
    expr[:10] = 0  # rays without β: no expression features there
    for e in (expr, torch.zeros(37, 1, E)):
        with torch.no_grad():
            fast = m.field._geo(x, e)
        with torch.enable_grad():
            ref = m.field._geo(x, e).detach()
        assert torch.allclose(fast, ref, atol=1e-5), (fast - ref).abs().max()
    with torch.no_grad():
        h = m.field._features_in_place(x, expr)
    w = m.field.grid.out_dim
    assert torch.all(h[:, :, w:w + m.field.detail.out_dim].abs().sum(-1)[x.norm(dim=-1) > 0.9] == 0)
    assert torch.all(h[:10, :, -m.field.expr_grid_width:] == 0)
    assert torch.any(h[10:, :, -m.field.expr_grid_width:] != 0)


def test_expression_projection_learns_from_zero():
    """With the projection A at zero (Aβ = 0 everywhere) the training path still evaluates
    the expression grid wherever β ≠ 0, so that A gets a gradient; without autograd those
    points are skipped (their features are exactly 0)."""
    m = tiny("fast", "hash", **{"field.expr_rank": 2})
    for t in m.field.expr_grid.tables:
        torch.nn.init.uniform_(t, -1, 1)
    torch.nn.init.zeros_(m.field.expr_proj.weight)
    x, expr = torch.rand(6, 4, 3) - 0.5, torch.randn(6, 1, E)
    m.field.density(x, expr).sum().backward()
    assert m.field.expr_proj.weight.grad.abs().sum() > 0
    with torch.no_grad():
        h = m.field._expression_features(x, expr)
    assert torch.all(h == 0)
