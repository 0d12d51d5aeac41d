import math

import pytest
import torch

from flamenerf.model.encodings import HashGrid, cosine_easing_window, positional_encoding


def test_window_matches_paper_formula():
    m = 8
    for alpha in [0.0, 0.3, 1.0, 2.5, 5.99, 8.0, 11.0]:
        w = cosine_easing_window(m, alpha)
        expect = [(1 - math.cos(math.pi * min(max(alpha - k, 0.0), 1.0))) / 2 for k in range(m)]
        assert torch.allclose(w, torch.tensor(expect), atol=1e-6), alpha
    assert torch.all(cosine_easing_window(m, 0.0) == 0)
    assert torch.all(cosine_easing_window(m, float(m)) == 1)


def test_positional_encoding_layout():
    x = torch.tensor([[0.25, -0.5, 0.125]])
    enc = positional_encoding(x, 3)
    assert enc.shape == (1, 3 + 2 * 3 * 3)
    assert torch.equal(enc[0, :3], x[0])  # input first
    for k in range(3):  # then per frequency: sin block, cos block
        blk = enc[0, 3 + 6 * k: 3 + 6 * (k + 1)]
        assert torch.allclose(blk[:3], torch.sin(2**k * math.pi * x[0]), atol=1e-6)
        assert torch.allclose(blk[3:], torch.cos(2**k * math.pi * x[0]), atol=1e-6)


def test_window_zeroes_high_bands():
    x = torch.rand(5, 3)
    w = cosine_easing_window(4, 1.0)  # only band 0 on
    enc = positional_encoding(x, 4, w)
    assert torch.all(enc[:, 3 + 6:] == 0)
    assert torch.any(enc[:, 3:9] != 0)


def test_hash_grid_shapes_and_position_gradient():
    g = HashGrid(levels=4, features=2, log2_size=12, base_res=4, max_res=64)
    for t in g.tables:
        torch.nn.init.uniform_(t, -1, 1)
    x = torch.rand(100, 3, requires_grad=True)
    out = g(x)
    assert out.shape == (100, 8)
    out.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    # trilinear interpolation reproduces the table at a grid vertex of the coarsest level
    v = torch.tensor([[0.25, 0.5, 0.75]])
    assert torch.isfinite(g(v)).all()


def test_hash_grid_is_trilinear_on_a_dense_level():
    g = HashGrid(levels=1, features=2, log2_size=10, base_res=4, max_res=4)
    for t in g.tables:
        torch.nn.init.uniform_(t, -1, 1)
    x = torch.tensor([[0.1, 0.55, 0.9], [0.0, 0.0, 0.0], [0.3, 0.3, 0.74]])
    out = g(x)
    r = 4
    for k, p in enumerate(x):
        pos = p * r
        b = torch.floor(pos).long()
        f = pos - b
        ref = torch.zeros(2)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    i = (b[0] + dx) + (b[1] + dy) * (r + 1) + (b[2] + dz) * (r + 1) ** 2
                    w = ((f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1])
                         * (f[2] if dz else 1 - f[2]))
                    ref += w * g.tables[0][i]
        assert torch.allclose(out[k], ref, atol=1e-6)


def test_hash_grid_accepts_the_box_faces():
    g = HashGrid(levels=3, features=2, log2_size=10, base_res=4, max_res=64)
    x = torch.tensor([[1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [1.5, -0.2, 1.0]])
    assert torch.isfinite(g(x)).all()


def _grid_with_features(levels, features, log2_size, base_res, max_res):
    g = HashGrid(levels=levels, features=features, log2_size=log2_size, base_res=base_res,
                 max_res=max_res)
    for t in g.tables:
        torch.nn.init.uniform_(t, -1, 1)
    return g


def test_cpu_kernel_matches_the_pytorch_reference():
    torch.manual_seed(0)
    # dense coarse levels and hashed fine ones (2^10 entries < (r+1)^3 from r = 10 on)
    for features in (1, 2, 3, 4, 16):  # the vectorised path's specialised counts and others
        g = _grid_with_features(5, features, 10, 4, 64)
        assert any(g.dense.tolist()) and not all(g.dense.tolist())
        # points outside the unit cube are clamped: their position gradient is zero;
        # 3001 points: the vectorised path's last block of 16 is partial
        x = torch.rand(3001, 3) * 1.2 - 0.1
        x1, x2 = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        a, b = g(x1), g.forward_torch(x2)
        assert torch.allclose(a, b, atol=1e-6)
        gout = torch.randn_like(a)
        ga = torch.autograd.grad(a, [x1, *g.tables], gout)
        gb = torch.autograd.grad(b, [x2, *g.tables], gout)
        for u, v in zip(ga, gb):
            assert torch.allclose(u, v, rtol=1e-4, atol=1e-4)
        outside = ((x < 0) | (x > 1))
        assert torch.all(ga[0][outside] == 0) and torch.any(ga[0][~outside] != 0)


def test_portable_and_native_kernels_agree(portable_kernels):
    """The native build (on an AVX-512 CPU: 16 points at a time with gathers, forward and
    backward) and the portable one (the generic loops) give the same encoding and
    gradients (up to the rounding of fused multiply-adds, which only the native build has)."""
    torch.manual_seed(0)
    x = torch.rand(1001, 3) * 1.2 - 0.1
    grids = [_grid_with_features(5, f, 10, 4, 64) for f in (1, 2, 3, 4, 16)]
    gouts = [torch.randn(1001, g.out_dim) for g in grids]

    def encode_and_grads():
        out = []
        for g, go in zip(grids, gouts):
            xr = x.clone().requires_grad_(True)
            y = g(xr)
            out.append((y.detach(), *torch.autograd.grad(y, [xr, *g.tables], go)))
        return out

    native = encode_and_grads()
    assert portable_kernels() is not None
    portable = encode_and_grads()
    for (ya, gxa, *gta), (yb, gxb, *gtb) in zip(native, portable):
        assert torch.allclose(ya, yb, atol=1e-6)
        assert torch.allclose(gxa, gxb, rtol=1e-4, atol=1e-4)
        outside = (x < 0) | (x > 1)
        assert torch.all(gxa[outside] == 0) and torch.any(gxa[~outside] != 0)
        for u, v in zip(gta, gtb):
            assert torch.allclose(u, v, rtol=1e-5, atol=1e-5)


def test_encode_into_writes_the_encoding_beside_other_columns(monkeypatch):
    """`encode_into` fills a column block of a wider buffer with the encoding and leaves
    the other columns alone; without the kernel it does the same by a copy."""
    from flamenerf import cpu_kernels

    g = _grid_with_features(4, 2, 10, 4, 64)
    x = torch.rand(1001, 3)
    ref = g(x).detach()
    for kernel in (True, False):
        if not kernel:
            monkeypatch.setattr(cpu_kernels, "_tried", True)
            monkeypatch.setattr(cpu_kernels, "_lib", None)
        buf = torch.full((1001, 3 + g.out_dim + 5), 7.0)
        g.encode_into(x, buf[:, 3:3 + g.out_dim])
        assert torch.allclose(buf[:, 3:3 + g.out_dim], ref, atol=1e-6)
        assert torch.all(buf[:, :3] == 7) and torch.all(buf[:, 3 + g.out_dim:] == 7)


@pytest.mark.parametrize("native", [True, False])
def test_contract_matches_the_batched_product(native, portable_kernels):
    """`HashGrid.contract` (the expression fields' Σ_r z_r G_r(x) inside the CPU's kernel)
    gives the batched product over the encoding, for the vectorised counts and others, in
    the native and the portable build; it declines what the kernel does not take."""
    if not native:
        assert portable_kernels() is not None
    torch.manual_seed(0)
    for rank, fe in ((8, 2), (3, 2), (4, 1), (12, 2)):  # F = 16, 6, 4, 24 (no vector path)
        g = _grid_with_features(4, rank * fe, 10, 4, 64)
        x, z = torch.rand(1100, 3) * 1.2 - 0.1, torch.randn(1100, rank)  # 1100: a part block
        ref = torch.matmul(z[:, None, None, :], g(x).detach().view(-1, 4, rank, fe))
        got = g.contract(x, z, fe)
        assert got is not None and got.shape == (1100, 4 * fe)
        assert torch.allclose(got, ref.reshape(1100, -1), atol=1e-5), (rank, fe)
    assert g.contract(x, torch.randn(1100, 5), 2) is None  # rank · features != F


def test_cpu_kernel_table_gradient_without_position_gradient_is_deterministic():
    g = _grid_with_features(4, 2, 12, 8, 128)
    x = torch.rand(4000, 3)  # no position gradient requested (the proposal field's case)
    grads = [torch.autograd.grad(g(x).square().sum(), list(g.tables)) for _ in range(2)]
    ref = torch.autograd.grad(g.forward_torch(x).square().sum(), list(g.tables))
    for a, b, r in zip(*grads, ref):
        assert torch.equal(a, b)
        assert torch.allclose(a, r, atol=1e-4)


def test_hash_grid_without_the_kernel_uses_pytorch(monkeypatch):
    from flamenerf import cpu_kernels

    g = _grid_with_features(3, 2, 10, 4, 32)
    x = torch.rand(50, 3)
    with_kernel = g(x)
    monkeypatch.setattr(cpu_kernels, "_tried", True)
    monkeypatch.setattr(cpu_kernels, "_lib", None)
    assert torch.allclose(g(x), with_kernel, atol=1e-6)


def test_grouped_levels_match_level_by_level():
    """The GPU's encoding (every dense level in one set of ops, every hashed one in
    another) is the level-by-level reference's, values and gradients (positions and
    every table), for grids with only dense, only hashed, and both kinds of levels."""
    torch.manual_seed(0)
    for levels, log2, base, top, kinds in ((5, 10, 4, 64, [True, False]),
                                           (3, 20, 4, 16, [True]), (4, 6, 8, 64, [False]),
                                           (2, 19, 1024, 2048, [False])):
        g = _grid_with_features(levels, 2, log2, base, top)
        assert [k for *_, k in g.level_groups()] == kinds
        x = torch.rand(2000, 3) * 1.2 - 0.1
        x1, x2 = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        a, b = g.forward_grouped(x1), g.forward_torch(x2)
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6)
        gout = torch.randn_like(a)
        ga = torch.autograd.grad(a, [x1, *g.tables], gout)
        gb = torch.autograd.grad(b, [x2, *g.tables], gout)
        for u, v in zip(ga, gb):
            assert torch.allclose(u, v, rtol=1e-4, atol=1e-5)
