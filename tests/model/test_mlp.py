import torch

from flamenerf.config import preset
from flamenerf.model.field import HashField, NeRFField
from flamenerf.model.mlp import MLP
from flamenerf.model.warp import SE3Field


def test_per_ray_conditioning_equals_concatenated_input():
    torch.manual_seed(0)
    net = MLP(10 + 4, 32, 6, (4,), out_dim=5)
    x, c = torch.randn(7, 9, 10), torch.randn(7, 1, 4)
    full = net(torch.cat([x, c.expand(7, 9, 4)], -1))
    assert torch.allclose(net(x, c), full, atol=1e-5)
    # and the flat, per-point form
    assert torch.allclose(net(x.reshape(-1, 10), c.expand(7, 9, 4).reshape(-1, 4)),
                          full.reshape(-1, 5), atol=1e-5)


def test_fields_and_warp_accept_per_ray_conditioning():
    torch.manual_seed(0)
    cfg = preset("fast").model
    R, S, E = 5, 6, 3
    x = torch.rand(R, S, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(R, 1, 3), dim=-1)
    app, expr, code = torch.randn(R, 1, 8), torch.randn(R, 1, E), torch.randn(R, 1, 16)

    def flat(v):
        return v.expand(R, S, v.shape[-1]).reshape(R * S, -1)

    for field in (HashField(cfg.field, E), NeRFField(preset("flame-in-nerf").model.field, E)):
        sig, rgb = field(x, d, app, expr)
        sig_f, rgb_f = field(x.reshape(-1, 3), flat(d), flat(app), flat(expr))
        assert sig.shape == (R, S) and rgb.shape == (R, S, 3)
        assert torch.allclose(sig.reshape(-1), sig_f, rtol=1e-4, atol=1e-5)
        assert torch.allclose(rgb.reshape(-1, 3), rgb_f, atol=1e-5)
    warp = SE3Field(cfg.warp)
    warp.set_alpha(3.0)
    for p in warp.parameters():  # a warp far from the identity, so that the test can fail
        torch.nn.init.normal_(p, std=0.3)
    y = warp(x, code)
    assert (y - x).abs().max() > 1e-2
    assert torch.allclose(y.reshape(-1, 3), warp(x.reshape(-1, 3), flat(code)), atol=1e-5)


def test_bf16_training_layers_follow_float32():
    """`train.bf16`'s layers (the path runs on any CPU: oneDNN emulates bfloat16 where the
    CPU lacks it) give float32 outputs and float32 weight gradients within bfloat16's
    rounding of the float32 ones, per-ray conditioning and skips included; off, nothing
    changes."""
    import flamenerf.model.mlp as mlp

    torch.manual_seed(0)
    net = MLP(10 + 4, 32, 4, (2,), out_dim=5)
    x, c = torch.randn(6, 7, 10), torch.randn(6, 1, 4)

    def run():
        net.zero_grad()
        y = net(x, c)
        (y ** 2).sum().backward()
        return y.detach(), [p.grad.clone() for p in net.parameters()]

    y32, g32 = run()
    with mlp.bf16_training():
        y16, g16 = run()
    assert y16.dtype == torch.float32 and all(g.dtype == torch.float32 for g in g16)
    err = (y16 - y32).abs().max() / y32.abs().max()
    assert 0 < err < 0.03, err  # bfloat16's rounding, not float32's
    for a, b in zip(g16, g32):
        assert (a - b).norm() < 0.05 * b.norm()
    with mlp.bf16_training(False):
        assert torch.equal(net(x, c), y32)
