"""Checkpoints: one dict per `step-000001000.ckpt`, written atomically, last K kept."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch

from flamenerf.errors import UserError
from flamenerf.io import atomic_write_bytes

_PAT = re.compile(r"step-(\d{9})\.ckpt$")


def save_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
    ckdir = Path(run_dir) / "checkpoints"
    path = ckdir / f"step-{step:09d}.ckpt"
    atomic_write_bytes(path, lambda f: torch.save(state, f))
    old = sorted(p for p in ckdir.iterdir() if _PAT.search(p.name))[:-keep] if keep > 0 else []
    for p in old:
        p.unlink(missing_ok=True)
    return path


def latest_checkpoint(run_dir: Path) -> Path | None:
    ckdir = Path(run_dir) / "checkpoints"
    if not ckdir.is_dir():
        return None
    cks = sorted(p for p in ckdir.iterdir() if _PAT.search(p.name))
    return cks[-1] if cks else None


def load_checkpoint(path: Path) -> dict[str, Any]:
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001
        raise UserError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from None


def load_model_state(model: torch.nn.Module, state: dict[str, Any], path: Path) -> None:
    """model.load_state_dict, with a one-line error for a checkpoint whose tensors do not fit
    this version's model (e.g. hash tables stored (F, T), as before the CPU kernel)."""
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        first = next((ln.strip() for ln in str(e).splitlines()[1:] if ln.strip()), str(e))
        raise UserError(f"{path}: checkpoint does not fit this version's model ({first}); "
                        "it was written by an older flamenerf: train the run again") from None
