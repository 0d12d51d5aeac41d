"""Load a trained run directory (config.json + latest checkpoint) for eval/render/view."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flamenerf.config import PRESETS, Config, from_dict
from flamenerf.data.dataset import Dataset, Frame, Intrinsics, load_dataset
from flamenerf.errors import UserError
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.io import read_json
from flamenerf.runtime import pick_device
from flamenerf.training.checkpoint import load_latest, load_model_state
from flamenerf.data.captured_views import captured_views


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
        if path is None and not p.exists():  # runs are shared; datasets stay behind
            raise UserError(f"{p}: the dataset this run was trained on is not there (moved or "
                            f"not copied with the run?); give its place with --dataset PATH")
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
        self.model.set_captured_views(captured_views(ds) if captured_directions else None)

    def train_intrinsics(self, ds: Dataset) -> Intrinsics:
        return ds.intrinsics.scaled(1.0 / self.config.train.downscale)

    def frame_codes(self, frame_index: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """ω (code_dim,), φ (appearance_dim,) of one capture frame."""
        i = torch.tensor([frame_index], device=self.device)
        w, a = self.model.codes(i)
        return w[0].detach(), a[0].detach()

    def codes_error(self, ds: Dataset, frames: list[Frame]) -> str | None:
        """Why `frames` of `ds` have no codes of their own in this run, or None: frames
        outside the capture (a re-animation split) have none, and a capture longer than
        the run's code table is another capture than the one it was trained on."""
        if not all(f.in_capture for f in frames):
            return "its frames have no codes of their own (use a capture split such as val)"
        if max(f.frame_index for f in frames) >= self.model.deform_codes.num_embeddings:
            return (f"{ds.root}: frame indices exceed this run's code table (a different "
                    "capture than the run was trained on?)")
        return None

    def clip_codes(self, ds: Dataset, frames: list[Frame]) -> tuple[torch.Tensor, torch.Tensor]:
        """Each capture frame's own ω (T, code_dim) and φ (T, appearance_dim): a training
        frame's trained codes; a held-out frame's (never trained, so still at their
        initial values) interpolated in clip order between the nearest training frames'
        on either side (the nearest one's past either end). `frames` must have codes
        (`codes_error`)."""
        trained = sorted({f.frame_index for f in ds.training_frames() if f.in_capture}) or [0]
        at = [f.frame_index for f in frames]
        w, a = self.model.codes(torch.as_tensor(trained, device=self.device))

        def between(c: torch.Tensor) -> torch.Tensor:
            """(N, D) at the trained frames -> (T, D) at `frames` (np.interp holds the
            nearest one's past either end)."""
            c = c.detach().float().cpu().numpy()
            out = np.stack([np.interp(at, trained, c[:, d]) for d in range(c.shape[1])], -1)
            return torch.as_tensor(out, dtype=torch.float32, device=self.device)

        return between(w), between(a)


def run_config(meta: Any, where: Path) -> Config:
    """The configuration a run's config.json (`meta`, as read from `where`) holds, checked
    as far as loading the run needs; a one-line UserError naming the file otherwise."""
    if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
        raise UserError(f"{where}: damaged (no 'config' object)")
    # an empty path is the current folder, which a later message would name instead
    if not isinstance(meta.get("dataset"), str) or not meta["dataset"]:
        raise UserError(f"{where}: damaged ('dataset' missing or not a path)")
    names = meta.get("expression_names")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise UserError(f"{where}: damaged ('expression_names' missing or not a list of "
                        "strings)")
    if "preset" in meta and meta["preset"] not in PRESETS:  # a label reports carry
        raise UserError(f"{where}: damaged (preset {str(meta['preset'])[:40]!r} is not one of "
                        f"this flamenerf's: {', '.join(PRESETS)})")
    return from_dict(meta["config"], where)  # checks each value's type and range


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
    where = run_dir / "config.json"
    meta = read_json(where)
    cfg = run_config(meta, where)
    found = load_latest(run_dir)  # skips an unreadable newest checkpoint, with a warning
    if found is None:
        raise UserError(f"{run_dir}: no checkpoint in {run_dir / 'checkpoints'} (not a trained run?)")
    ck, state = found
    mine, theirs = meta.get("model_args"), state["model_args"]
    mine = mine if isinstance(mine, dict) else {}  # absent or damaged: nothing to compare
    differ = [k for k in ("num_codes", "expr_dim", "mesh_vertices", "mesh_faces")
              if k in mine and mine[k] != theirs.get(k)]
    if differ:
        raise UserError(f"{ck}: not this run's checkpoint ({differ[0]} {theirs.get(differ[0])}, "
                        f"{where.name} says {mine[differ[0]]}; copied from another run?)")
    dev = pick_device(device)
    try:
        model = FlameNeRF(cfg.model, **theirs, background=cfg.train.render_background)
    except (TypeError, ValueError) as e:
        raise UserError(f"{ck}: does not fit the model {where.name} describes ({e}; copied "
                        "from another run?)") from None
    load_model_state(model, state["model"], ck)
    model.to(dev).eval()
    model.update_to_step(int(state["step"]), cfg.train.steps)
    return Run(run_dir, cfg, meta, model, int(state["step"]), dev)
