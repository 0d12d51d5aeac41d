"""The per-subject expression model and the mesh-guided displacement."""

import numpy as np
import pytest
import torch

from flamenerf.data.dataset import load_dataset
from flamenerf.meshes import (expression_mesh, fit_expression_model, mesh_displacement,
                              nearest_vertices, nearest_vertices_brute,
                              surface_points)


@pytest.mark.slow
def test_expression_model_reproduces_the_training_meshes(synth_scene):
    ds = load_dataset(synth_scene)
    train = ds.split("train")
    betas = torch.from_numpy(ds.expression_matrix(train))
    verts = torch.from_numpy(ds.face_vertices[[f.position for f in train]])
    neutral, basis = fit_expression_model(betas, verts)
    fitted = expression_mesh(neutral, basis, betas)
    motion = (verts - verts.mean(0)).norm(dim=-1).mean()
    err = (fitted - verts).norm(dim=-1).mean()
    # the synthetic head's expressions are near-linear in its vertices: the fit explains
    # almost all of the expression motion (not just the mean mesh)
    assert err < 0.2 * motion, (float(err), float(motion))
    # held-out frames too: the model generalises to expressions it was not fitted on
    val = ds.split("val")
    v_val = torch.from_numpy(ds.face_vertices[[f.position for f in val]])
    pred = expression_mesh(neutral, basis, torch.from_numpy(ds.expression_matrix(val)))
    assert (pred - v_val).norm(dim=-1).mean() < 0.35 * (v_val - verts.mean(0)).norm(dim=-1).mean()


def test_displacement_moves_vertices_exactly_and_far_points_not_at_all():
    g = torch.Generator().manual_seed(0)
    mesh = torch.rand(50, 3, generator=g) * 0.2
    target = mesh + torch.tensor([0.0, -0.03, 0.0])
    d = mesh_displacement(mesh, mesh, target, falloff=0.05)
    assert torch.allclose(d, target - mesh, atol=1e-4)
    far = torch.tensor([[2.0, 2.0, 2.0], [-1.0, 0.5, 0.3]])
    assert mesh_displacement(far, mesh, target, falloff=0.05).abs().max() < 1e-12
    # in between, the motion fades monotonically with the distance to the mesh
    probe = mesh[:1] + torch.tensor([[0.0, 0.0, 1.0]]) * torch.tensor([[0.02], [0.05], [0.1]])
    mags = mesh_displacement(probe, mesh, target, falloff=0.05).norm(dim=-1)
    assert mags[0] > mags[1] > mags[2]


def test_displacement_by_k_d_tree_matches_every_vertex_blended():
    # the CPU path finds the k nearest vertices with a k-d tree and drops points beyond the
    # cutoff; the blend over brute-force distances to every vertex is the reference
    g = torch.Generator().manual_seed(2)
    mesh = torch.rand(300, 3, generator=g) * 0.2
    target = mesh + 0.01 * torch.randn(300, 3, generator=g)
    x = torch.rand(4000, 3, generator=g) * 0.5 - 0.15
    falloff = 0.03
    d2, idx = torch.topk(torch.cdist(x, mesh).square(), 4, dim=-1, largest=False)
    w = 1.0 / (d2 + 1e-10)
    w = w / w.sum(-1, keepdim=True)
    ref = (w[..., None] * (target - mesh)[idx]).sum(1) * torch.exp(-d2[:, :1] / falloff**2)
    got = mesh_displacement(x, mesh, target, falloff)
    assert (got - ref).abs().max() < 1e-5  # float32 cdist against a float64 tree
    assert (ref.norm(dim=-1) > 1e-3).sum() > 200  # the comparison covers moving points
    kd2, kidx = nearest_vertices(x, mesh, 4, bound=1.0)
    assert torch.allclose(kd2, d2, atol=1e-6) and bool((kidx == idx).all())
    far2, _ = nearest_vertices(x, mesh, 4, bound=0.01)
    assert bool(torch.isinf(far2).any()) and bool(torch.isfinite(far2).any())
    for k in (1, 4):  # the brute-force path (off the CPU) gives the tree's answer
        bd2, bidx = nearest_vertices_brute(x, mesh[None], k, 0.05, torch.zeros(len(x)).long(),
                                           block_elements=300 * 512)  # 8 blocks of points
        td2, tidx = nearest_vertices(x, mesh, k, bound=0.05)
        fin = torch.isfinite(td2)
        assert bool(fin.any()) and bool((~fin).any()) and torch.equal(fin, torch.isfinite(bd2))
        assert torch.allclose(bd2[fin], td2[fin], atol=1e-6) and torch.equal(bidx, tidx)


@pytest.mark.slow
def test_displacement_of_many_meshes_at_once_is_each_mesh_alone():
    """A training batch guides points of ~100 frames at once (one k-d tree on a CPU,
    batched distances elsewhere): each point must move with its own frame's mesh."""
    g = torch.Generator().manual_seed(4)
    base = torch.rand(200, 3, generator=g) * 0.3
    meshes = base + 0.02 * torch.randn(5, 200, 3, generator=g)  # overlapping in space
    target = base
    x = torch.rand(3000, 3, generator=g) * 0.4 - 0.05
    which = torch.randint(5, (3000,), generator=g)
    got = mesh_displacement(x, meshes, target, 0.03, which=which)
    ref = torch.zeros_like(x)
    for m in range(5):
        sel = which == m
        ref[sel] = mesh_displacement(x[sel], meshes[m], target, 0.03)
    assert (got - ref).abs().max() < 1e-6 and (ref.norm(dim=-1) > 1e-3).sum() > 100
    # the path off the CPU (blocks of distances to each point's own mesh) agrees with the
    # tree, for points and for the samples of rays (a ray's samples share its mesh)
    rays = x.view(300, 10, 3)
    ray_mesh = torch.randint(5, (300,), generator=g)
    for k in (1, 4):
        for pts, w in ((x, which), (rays, ray_mesh)):
            td2, tidx = nearest_vertices(pts, meshes, k, 0.05, w)
            bd2, bidx = nearest_vertices_brute(pts, meshes, k, 0.05, w,
                                               block_elements=200 * 10 * 7)  # 43 blocks
            fin = torch.isfinite(td2)
            assert bool(fin.any()) and torch.equal(fin, torch.isfinite(bd2))
            assert torch.allclose(bd2[fin], td2[fin], atol=1e-6) and torch.equal(bidx, tidx)
            own = w if pts.dim() == 2 else w.repeat_interleave(10)
            assert bool((tidx[fin] // 200 == own[:, None].expand_as(tidx)[fin]).all())


def test_surface_points_lie_in_their_triangles():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = torch.tensor([[0, 1, 2], [0, 1, 3]])
    g = torch.Generator().manual_seed(1)
    tri = torch.randint(2, (500,), generator=g)
    p = surface_points(verts, faces, tri, torch.rand(500, 2, generator=g))
    on0 = tri == 0
    assert torch.all(p[on0, 2].abs() < 1e-7) and torch.all(p[~on0, 1].abs() < 1e-7)
    assert torch.all(p >= -1e-7) and torch.all(p.sum(-1) <= 1 + 1e-6)
    batched = surface_points(verts.expand(500, -1, -1), faces, tri, torch.rand(500, 2, generator=g))
    assert np.isfinite(batched.numpy()).all()
