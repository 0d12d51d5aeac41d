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


def test_stratified_sample_pdf_puts_one_sample_in_each_equal_probability_stratum():
    torch.manual_seed(0)
    bins = torch.linspace(0, 1, 9).expand(200, 9)
    w = torch.rand(200, 8)
    n = 16
    s = sample_pdf(bins, w, n, jitter=True, stratified=True)
    assert torch.all(s[:, 1:] >= s[:, :-1])  # already sorted
    # map back through the CDF: sample k must lie in probability stratum [k/n, (k+1)/n)
    p = (w + 1e-5) / (w + 1e-5).sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros(200, 1), p.cumsum(-1)], -1)
    j = (s * 8).floor().long().clamp(max=7)
    u = cdf.gather(-1, j) + (s * 8 - j) * p.gather(-1, j)
    k = torch.arange(n).expand(200, n)
    assert torch.all(u >= k / n - 1e-5) and torch.all(u <= (k + 1) / n + 1e-5)
    # independent draws (NeRF's) leave larger gaps between neighbouring samples
    iid, _ = torch.sort(sample_pdf(bins, w, n, jitter=True), -1)
    gap = lambda v: (v[:, 1:] - v[:, :-1]).max(-1).values.mean()  # noqa: E731
    assert gap(s) < gap(iid)
    # without jitter: the middle of each stratum
    mid = sample_pdf(bins, torch.ones(1, 8), 4, jitter=False, stratified=True)
    assert torch.allclose(mid, torch.tensor([[0.125, 0.375, 0.625, 0.875]]), atol=1e-4)


def test_stratified_samples_without_jitter_come_out_sorted():
    """The inference path takes the main samples unsorted (model/inference.py): proposal
    weights as they come (mostly ~0, a few spikes, rays seen through) over real depths."""
    g = torch.Generator().manual_seed(0)
    R, P = 20000, 48
    bins = torch.linspace(0.5, 1.6, P + 1).expand(R, P + 1)
    w = torch.rand(R, P, generator=g) ** 8 * (torch.rand(R, P, generator=g) < 0.1)
    w[:100] = 0  # empty rays
    w[100:200, 7] = 1.0  # one opaque sample
    w[200:300] *= 1e-9  # nearly empty
    s = sample_pdf(bins, w, 33, jitter=False, stratified=True)
    assert torch.all(s[:, 1:] >= s[:, :-1])
    assert torch.all(s >= 0.5) and torch.all(s <= 1.6)


def test_interlevel_loss_zero_when_proposal_bounds_main():
    from flamenerf.model.render import interlevel_loss

    edges = torch.linspace(0, 1, 9)[None]
    w = torch.tensor([[0.0, 0.1, 0.5, 0.2, 0.0, 0.0, 0.0, 0.0]])  # all inside [0, 0.5]
    assert interlevel_loss(edges, w, edges, w).item() < 1e-9
    coarse = torch.linspace(0, 1, 3)[None]  # two proposal intervals
    assert interlevel_loss(edges, w, coarse, torch.tensor([[0.9, 0.0]])).item() < 1e-9
    assert interlevel_loss(edges, w, coarse, torch.tensor([[0.0, 0.9]])).item() > 0.1
