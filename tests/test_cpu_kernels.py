"""The compiled CPU kernels (cpu_kernels.py): they build, and the k-nearest-vertices kernel
gives the k-d tree's answer. The hash grid's kernel is checked in tests/model/test_encodings.py."""

import numpy as np
import pytest
import torch

from flamenerf import cpu_kernels
from flamenerf.meshes import nearest_vertices


def test_cpu_kernels_build_here():
    assert cpu_kernels.kernel_library() is not None, "the C kernels did not build"


def test_cpu_kernels_build_without_native_flags(portable_kernels, tmp_path):
    """A compiler that rejects the CPU-specific flag still gets the portable kernels; the
    CPU-specific build is cached under a name that includes the CPU."""
    assert portable_kernels() is not None
    assert len(list((tmp_path / "kernels").glob("kernels-*.so"))) == 1
    assert cpu_kernels.cpu_identity()


def _tree(pts, meshes, k, bound, which):
    """The k-d tree's answer (the path without the kernel), point by point."""
    from scipy.spatial import cKDTree

    d2 = np.full((len(pts), k), np.inf)
    idx = np.zeros((len(pts), k), np.int64)
    V = meshes.shape[1]
    for m in range(meshes.shape[0]):
        rows = (which == m).nonzero()[:, 0].numpy()
        if len(rows) == 0:
            continue
        d, i = cKDTree(meshes[m].double().numpy()).query(pts[rows].double().numpy(), k=k,
                                                         distance_upper_bound=bound)
        d, i = d.reshape(len(rows), k), i.reshape(len(rows), k)
        ok = np.isfinite(d)
        d2[rows] = np.where(ok, np.square(d), np.inf)
        idx[rows] = np.where(ok, i + m * V, 0)
    return torch.from_numpy(d2).float(), torch.from_numpy(idx)


def _ray_points(meshes, which, samples, gen):
    """Samples along rays that pass near the meshes' vertices: the kernel's seeded case."""
    R = len(which)
    v = meshes[which, torch.randint(0, meshes.shape[1], (R,), generator=gen)]
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen), dim=-1)
    t = torch.linspace(-0.2, 0.2, samples)
    return v[:, None] + t[None, :, None] * d[:, None]  # (R, S, 3)


@pytest.mark.parametrize("native", [True, False])
def test_nearest_vertices_kernel_matches_the_tree(portable_kernels, native):
    """Several meshes, points near and far (fewer than k within the bound: inf and index
    0), k from 1 to 8, per-ray mesh indices, one mesh without indices: the kernel's
    neighbours and distances are the tree's, in the native build (where it has AVX-512,
    `nearest_vertices` takes it) and in the portable one (its plain loop)."""
    from flamenerf.meshes import _nearest_vertices_kernel

    lib = portable_kernels() if not native else cpu_kernels.kernel_library()
    assert lib is not None
    gen = torch.Generator().manual_seed(0)
    meshes = torch.randn(3, 61, 3, generator=gen) * 0.2
    which = torch.randint(0, 3, (40,), generator=gen)
    rays = _ray_points(meshes, which, 24, gen)
    pts = rays.reshape(-1, 3)
    per_point = which.repeat_interleave(24)
    for k, bound in ((1, 0.05), (4, 0.15), (8, 10.0), (4, 0.02)):
        d2, idx = _nearest_vertices_kernel(lib, pts, meshes, k, bound, per_point)
        td2, tidx = _tree(pts, meshes, k, bound, per_point)
        assert torch.equal(idx, tidx)
        assert torch.equal(torch.isinf(d2), torch.isinf(td2))
        fin = torch.isfinite(td2)
        assert torch.allclose(d2[fin], td2[fin], rtol=1e-6, atol=0)
        if bound < 1:
            assert bool(torch.isinf(d2).any()) and bool(torch.isfinite(d2).any())
        # the public function gives the same answer, whichever path it takes here
        pd2, pidx = nearest_vertices(rays, meshes, k, bound, which)
        assert torch.equal(pidx, tidx) and torch.equal(torch.isinf(pd2), torch.isinf(td2))
    d2, idx = _nearest_vertices_kernel(lib, pts, meshes[1], 4, 0.15, None)
    td2, tidx = _tree(pts, meshes[1:2], 4, 0.15, torch.zeros(len(pts), dtype=torch.long))
    assert torch.equal(idx, tidx) and torch.equal(torch.isinf(d2), torch.isinf(td2))


def test_nearest_vertices_takes_the_kernel_where_it_is_vectorised(monkeypatch):
    """The kernel where its build walks eight vertices at a time; the tree elsewhere (the
    plain loop is slower than the tree on a viewer's points)."""
    from flamenerf import meshes as M

    calls = []
    real = M._nearest_vertices_kernel
    monkeypatch.setattr(M, "_nearest_vertices_kernel",
                        lambda *a: calls.append(1) or real(*a))
    lib = cpu_kernels.kernel_library()
    M.nearest_vertices(torch.zeros(5, 3), torch.ones(7, 3), 2, 10.0)
    assert len(calls) == int(lib.knn_vectorised())


def test_nearest_vertices_without_the_kernel_uses_the_tree(monkeypatch):
    gen = torch.Generator().manual_seed(1)
    meshes = torch.randn(2, 30, 3, generator=gen) * 0.2
    which = torch.randint(0, 2, (10,), generator=gen)
    rays = _ray_points(meshes, which, 8, gen)
    with_kernel = nearest_vertices(rays, meshes, 4, 0.1, which)
    monkeypatch.setattr(cpu_kernels, "_tried", True)
    monkeypatch.setattr(cpu_kernels, "_lib", None)
    without = nearest_vertices(rays, meshes, 4, 0.1, which)
    assert torch.equal(with_kernel[1], without[1])
    assert torch.allclose(with_kernel[0], without[0], rtol=1e-6)


def test_nearest_vertices_kernel_rejects_mesh_indices_out_of_range():
    from flamenerf.meshes import _nearest_vertices_kernel

    meshes = torch.zeros(2, 5, 3)
    with pytest.raises(ValueError, match="mesh indices"):
        _nearest_vertices_kernel(cpu_kernels.kernel_library(), torch.zeros(3, 3), meshes, 1,
                                 1.0, torch.tensor([0, 1, 2]))
