import math

import torch

from flamenerf.model.encodings import HashGrid, cosine_easing_window, positional_encoding


def test_window_matches_paper_formula():
    m = 8
    for alpha in [0.0, 0.3, 1.0, 2.5, 5.99, 8.0, 11.0]:
        w = cosine_easing_window(m, alpha)
        expect = [(1 - math.cos(math.pi * min(max(alpha - l, 0.0), 1.0))) / 2 for l in range(m)]
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
                    ref += w * g.tables[0][:, i]
        assert torch.allclose(out[k], ref, atol=1e-6)


def test_hash_grid_accepts_the_box_faces():
    g = HashGrid(levels=3, features=2, log2_size=10, base_res=4, max_res=64)
    x = torch.tensor([[1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [1.5, -0.2, 1.0]])
    assert torch.isfinite(g(x)).all()
