import torch

from flamenerf.model.render import composite, render_weights, sample_pdf


def test_weights_closed_form():
    sigma = torch.tensor([[0.0, 1.0, 2.0]])
    deltas = torch.tensor([[1.0, 0.5, 0.25]])
    w = render_weights(sigma, deltas)
    a1, a2 = 1 - torch.exp(torch.tensor(-0.5)), 1 - torch.exp(torch.tensor(-0.5))
    expect = torch.tensor([[0.0, a1, (1 - a1) * a2]])
    assert torch.allclose(w, expect, atol=1e-6)


def test_weights_sum_at_most_one_and_opaque_wall():
    sigma = torch.rand(50, 32) * 5
    w = render_weights(sigma, torch.full((50, 32), 0.1))
    assert torch.all(w.sum(-1) <= 1 + 1e-6)
    sigma = torch.zeros(1, 8)
    sigma[0, 5] = 1e6
    t = torch.linspace(1, 2, 8)[None]
    out = composite(render_weights(sigma, torch.full((1, 8), 0.1)), torch.ones(1, 8, 3), t)
    assert torch.allclose(out["depth"], t[:, 5]) and torch.allclose(out["acc"], torch.ones(1))


def test_sample_pdf_concentrates_on_heavy_bin():
    bins = torch.linspace(0, 1, 11)[None]
    w = torch.zeros(1, 10)
    w[0, 3] = 1.0
    s = sample_pdf(bins, w, 64, jitter=False)
    assert ((s >= 0.3) & (s <= 0.4)).float().mean() > 0.9


def test_interlevel_loss_zero_when_proposal_bounds_main():
    from flamenerf.model.render import interlevel_loss

    edges = torch.linspace(0, 1, 9)[None]
    w = torch.tensor([[0.0, 0.1, 0.5, 0.2, 0.0, 0.0, 0.0, 0.0]])  # all inside [0, 0.5]
    assert interlevel_loss(edges, w, edges, w).item() < 1e-9
    coarse = torch.linspace(0, 1, 3)[None]  # two proposal intervals
    assert interlevel_loss(edges, w, coarse, torch.tensor([[0.9, 0.0]])).item() < 1e-9
    assert interlevel_loss(edges, w, coarse, torch.tensor([[0.0, 0.9]])).item() > 0.1
