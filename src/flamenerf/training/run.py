"""Load a trained run directory (config.json + latest checkpoint) for eval/render/view."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from flamenerf.config import Config, from_dict
from flamenerf.data.dataset import Dataset, Intrinsics, load_dataset
from flamenerf.errors import UserError
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.io import read_json
from flamenerf.runtime import pick_device
from flamenerf.training.checkpoint import load_latest, load_model_state


@dataclass
class Run:
    run_dir: Path
    config: Config
    meta: dict[str, Any]  # config.json
    model: FlameNeRF  # in eval mode, on `device`
    step: int
    device: torch.device

    @property
    def expression_names(self) -> list[str]:
        return list(self.meta["expression_names"])

    def dataset(self, path: str | Path | None = None, captured_directions: bool = True
                ) -> Dataset:
        """The run's training dataset (or another one with the same expression model),
        attached to the model (`attach`)."""
        p = Path(path) if path is not None else Path(self.meta["dataset"])
        ds = load_dataset(p)
        if ds.expression_names != self.expression_names:
            raise UserError(f"{p}: its expression model ({ds.expression_dim} controls) is not "
                            f"the one this run was trained with ({len(self.expression_names)})")
        self.attach(ds, captured_directions)
        return ds

    def attach(self, ds: Dataset, captured_directions: bool = True) -> None:
        """Render with `ds`'s capture: colour at a new camera as the nearest captured view
        saw it (data/captured_views.py); `captured_directions` False: at the direction
        asked, as the training forward does."""
        from flamenerf.data.captured_views import captured_views

        self.model.set_captured_views(captured_views(ds) if captured_directions else None)

    def train_intrinsics(self, ds: Dataset) -> Intrinsics:
        return ds.intrinsics.scaled(1.0 / self.config.train.downscale)

    def frame_codes(self, frame_index: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """ω (code_dim,), φ (appearance_dim,) of one capture frame."""
        i = torch.tensor([frame_index], device=self.device)
        w, a = self.model.codes(i)
        return w[0].detach(), a[0].detach()


def load_run(run_dir: str | Path, device: str = "auto") -> Run:

    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise UserError(f"{run_dir}: is a file; give the run directory made by `flamenerf "
                        "train` (the folder holding config.json)")
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: run directory does not exist")
    if not (run_dir / "config.json").is_file():
        raise UserError(f"{run_dir}: not a run directory (no config.json; give the folder "
                        "`flamenerf train --out` made)")
    meta = read_json(run_dir / "config.json")
    found = load_latest(run_dir)  # skips an unreadable newest checkpoint, with a warning
    if found is None:
        raise UserError(f"{run_dir}: no checkpoint in {run_dir / 'checkpoints'} (not a trained run?)")
    ck, state = found
    cfg = from_dict(meta["config"])
    dev = pick_device(device)
    model = FlameNeRF(cfg.model, **state["model_args"], background=cfg.train.render_background)
    load_model_state(model, state["model"], ck)
    model.to(dev).eval()
    model.update_to_step(int(state["step"]), cfg.train.steps)
    return Run(run_dir, cfg, meta, model, int(state["step"]), dev)
