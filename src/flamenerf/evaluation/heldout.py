"""The paper's held-out protocol: for each held-out frame freeze the model and optimise only
its deformation code ω, starting from frame 0's, with frame 0's appearance code φ_0."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from tqdm import tqdm

from flamenerf.data.scene import FrameSet
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.losses import LossBatch


def fit_deformation_codes(model: FlameNeRF, frames: FrameSet, steps: int = 200,
                          batch_rays: int = 4096, lr: float = 1e-2, seed: int = 0,
                          quiet: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """All frames of `frames` are fitted together (one batch samples every frame).

    -> ω (N, code_dim) fitted, φ (N, appearance_dim) = φ_0 repeated. Model parameters are
    never changed (they do not even receive gradients).
    """
    dev = next(model.parameters()).device
    zero = torch.zeros(1, dtype=torch.long, device=dev)
    omega0, phi0 = (c.detach() for c in model.codes(zero))
    omega = torch.nn.Parameter(omega0.expand(frames.n, -1).clone())
    phi = phi0.expand(frames.n, -1)
    if model.warp is None or steps <= 0:
        return omega.detach(), phi
    with model.outside_training(), _frozen(model):
        _fit(model, frames, omega, phi, steps, batch_rays, lr, seed, quiet)
    return omega.detach(), phi


def _fit(model, frames, omega, phi, steps, batch_rays, lr, seed, quiet) -> None:
    dev = omega.device
    opt = torch.optim.Adam([omega], lr=lr)
    gen = torch.Generator().manual_seed(seed)
    for _ in tqdm(range(steps), desc="fit ω (held-out)", disable=quiet, leave=False):
        fi, ys, xs = frames.sample_pixels(batch_rays, gen)
        fi_d = fi.to(dev)
        rays, target = frames.ray_batch(fi, ys, xs, omega[fi_d], phi[fi_d], dev)
        out = model(rays, jitter=True, generator=gen if dev.type == "cpu" else None)
        loss = model.get_loss_dict(out, LossBatch(target)).raw["photo"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


@contextlib.contextmanager
def _frozen(model) -> Iterator[None]:
    """No parameter of `model` takes gradients (they keep their flags after)."""
    flags = [p.requires_grad for p in model.parameters()]
    for p in model.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, f in zip(model.parameters(), flags):
            p.requires_grad_(f)
