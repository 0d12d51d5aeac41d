"""The training loop: progress bar, TensorBoard, atomic checkpoints, exact resume, Ctrl-C."""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flamenerf import __version__
from flamenerf.config import Config, from_dict
from flamenerf.data.dataset import Dataset, load_dataset
from flamenerf.data.scene import FrameSet, fit_dataset_expression_model, scene_box
from flamenerf.errors import UserError
from flamenerf.io import atomic_write_text, read_json
from flamenerf.model.flame_nerf import FlameNeRF, RayBatch
from flamenerf.runtime import pick_device
from flamenerf.training.checkpoint import (latest_checkpoint, load_checkpoint, load_model_state,
                                           save_checkpoint)
from flamenerf.training.losses import face_region_loss, psnr_from_mse


def learning_rate(step: int, cfg) -> float:
    """Exponential decay from lr to lr_final over the run, after a linear warm-up."""
    t = min(step / max(cfg.steps, 1), 1.0)
    lr = cfg.lr * (cfg.lr_final / cfg.lr) ** t
    if cfg.lr_warmup > 0 and step < cfg.lr_warmup:
        lr *= (step + 1) / cfg.lr_warmup
    return lr


def param_groups(model: FlameNeRF, cfg) -> list[dict]:
    """The deformation MLP and the appearance codes in groups of their own, so that they
    can learn more slowly than the rest (`lr_scale`, applied by `Trainer.train_step`)."""
    special = [(model.warp, cfg.warp_lr_scale), (model.appearance_codes, cfg.appearance_lr_scale)]
    taken: set[int] = set()
    groups = []
    for module, scale in special:
        if module is None:
            continue
        params = list(module.parameters())
        taken |= set(map(id, params))
        groups.append({"params": params, "lr_scale": scale})
    rest = [p for p in model.parameters() if id(p) not in taken]
    return [{"params": rest, "lr_scale": 1.0}, *groups]


def train_resolution(ds: Dataset, cfg: Config):
    return ds.intrinsics.scaled(1.0 / cfg.train.downscale)


def build_for_dataset(cfg: Config, ds: Dataset) -> FlameNeRF:
    lo, hi = scene_box(ds)
    V, nf = ds.face_vertices.shape[1], len(ds.faces)
    model = FlameNeRF(cfg.model, num_codes=ds.num_codes, expr_dim=ds.expression_dim,
                      near=ds.near, far=ds.far, box_min=lo, box_max=hi,
                      mesh_vertices=V, mesh_faces=nf)
    if model.mesh_guided:
        neutral, basis = fit_dataset_expression_model(ds, cfg.model.mesh_guide.ridge)
        model.set_expression_model(neutral, basis, torch.from_numpy(ds.faces).long())
    return model


@dataclass
class TrainResult:
    run_dir: Path
    step: int
    interrupted: bool
    seconds: float
    last_psnr: float


class Trainer:
    def __init__(self, cfg: Config, dataset: str | Path, run_dir: str | Path,
                 resume: bool = False, device: str = "auto", quiet: bool = False,
                 steps: int | None = None):
        self.run_dir = Path(run_dir)
        self.device = pick_device(device)
        self.quiet = quiet
        ck = latest_checkpoint(self.run_dir)
        if ck is not None and not resume:
            raise UserError(f"{self.run_dir}: already holds a run (pass --resume to continue "
                            "it, or choose another --out)")
        if resume and ck is not None:
            saved = read_json(self.run_dir / "config.json")
            cfg = from_dict(saved["config"])  # a resumed run keeps its own config
        if steps is not None:
            cfg.train.steps = steps
        self.cfg = cfg
        if cfg.train.num_threads > 0:
            torch.set_num_threads(cfg.train.num_threads)
        self.ds = load_dataset(dataset)
        self.intr = train_resolution(self.ds, cfg)
        torch.manual_seed(cfg.train.seed)
        self.model = build_for_dataset(cfg, self.ds).to(self.device)
        self.train_set = FrameSet(self.ds, self.ds.split("train"), self.intr)
        fused = self.device.type in ("cpu", "cuda")
        eps = 1e-15 if cfg.model.field.kind == "hash" else 1e-8
        self.opt = torch.optim.Adam(param_groups(self.model, cfg.train), lr=cfg.train.lr,
                                    eps=eps, fused=fused)
        self.gen = torch.Generator().manual_seed(cfg.train.seed)
        self.step = 0
        if resume and ck is not None:
            self._load(ck)
        self._write_config()

    # --------------------------------------------------------------- persistence
    def _write_config(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        meta = {
            "flamenerf_version": __version__,
            "preset": self.cfg.preset,
            "dataset": str(Path(self.ds.root).resolve()),
            "expression_names": self.ds.expression_names,
            "expression_kind": self.ds.expression_kind,
            "train_size": [self.intr.w, self.intr.h],
            "model_args": self.model.init_args,
            "config": self.cfg.to_dict(),
        }
        import json

        atomic_write_text(self.run_dir / "config.json", json.dumps(meta, indent=1))

    def state(self) -> dict:
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "model_args": self.model.init_args,
            "optimizer": self.opt.state_dict(),
            "generator": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "numpy_rng": np.random.get_state(),
            "python_rng": random.getstate(),
            "config": self.cfg.to_dict(),
            "version": __version__,
        }

    def save(self) -> Path:
        return save_checkpoint(self.run_dir, self.step, self.state(), self.cfg.train.keep_checkpoints)

    def _load(self, path: Path) -> None:
        st = load_checkpoint(path)
        load_model_state(self.model, st["model"], path)
        try:
            self.opt.load_state_dict(st["optimizer"])
        except ValueError as e:  # a checkpoint from before the per-group learning rates
            raise UserError(f"{path}: optimiser state does not match this version's "
                            f"parameter groups ({e}); start a new run") from None
        self.gen.set_state(st["generator"])
        torch.set_rng_state(st["torch_rng"])
        np.random.set_state(st["numpy_rng"])
        random.setstate(st["python_rng"])
        self.step = int(st["step"])

    # --------------------------------------------------------------- one step
    def train_step(self) -> dict[str, float]:
        cfg, model, ts = self.cfg.train, self.model, self.train_set
        model.train()
        model.update_to_step(self.step, cfg.steps)
        for g in self.opt.param_groups:
            g["lr"] = learning_rate(self.step, cfg) * g["lr_scale"]
        fi, ys, xs = ts.sample_pixels(cfg.batch_rays, self.gen)
        o, d = ts.rays(fi, ys, xs)
        code_idx = ts.frame_index[fi].to(self.device)
        omega, phi = model.codes(code_idx)
        rays = RayBatch(o.to(self.device), d.to(self.device), omega, phi,
                        ts.expressions[fi].to(self.device), ts.masks[fi, ys, xs].to(self.device))
        target = ts.images[fi, ys, xs].to(self.device)
        out = model(rays, jitter=True, generator=self.gen if self.device.type == "cpu" else None)
        mse = torch.mean((out["rgb"] - target) ** 2)
        loss = mse
        logs = {"loss/photo": mse.item()}
        if "rgb_coarse" in out:
            mse_c = torch.mean((out["rgb_coarse"] - target) ** 2)
            loss = loss + mse_c
            logs["loss/photo_coarse"] = mse_c.item()
        if "interlevel" in out:
            loss = loss + cfg.interlevel_weight * out["interlevel"]
            logs["loss/interlevel"] = out["interlevel"].item()
        if cfg.face_reg_weight > 0 and model.warp is not None:
            pfi = torch.randint(ts.n, (cfg.face_reg_points,), generator=self.gen)
            if model.mesh_guided:  # the face is carried to the neutral mesh before the warp
                pts = model.neutral_face_points(cfg.face_reg_points, self.gen)
            else:
                pts = model.normalize(ts.face_points(pfi, self.gen).to(self.device))
            omega_p, _ = model.codes(ts.frame_index[pfi].to(self.device))
            reg = face_region_loss(model.warp_points(pts, omega_p), pts)
            loss = loss + cfg.face_reg_weight * reg
            logs["loss/face_reg"] = reg.item()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        logs["loss/total"] = loss.item()
        logs["metrics/psnr"] = psnr_from_mse(mse.item())
        logs["perf/samples"] = float(out["num_samples"])
        if model.warp is not None:
            logs["params/warp_alpha"] = float(model.warp.alpha)
        return logs

    # --------------------------------------------------------------- loop
    def preview(self, writer=None) -> None:
        """Render the first val frame (else train frame 0) with its own codes."""
        from flamenerf.io import save_png
        from flamenerf.model.render_image import render_image

        frames = self.ds.splits.get("val") or self.ds.splits["train"]
        fr = self.ds.frames[frames[0]]
        fs = FrameSet(self.ds, [fr], self.intr)
        self.model.eval()
        omega, phi = self.model.codes(fs.frame_index.to(self.device))
        out = render_image(self.model, self.intr, fs.c2w[0], omega[0], phi[0],
                           fs.expressions[0], fs.masks[0])
        img = torch.cat([fs.images[0], out["rgb"]], 1).numpy()
        save_png(self.run_dir / "images" / f"step-{self.step:09d}.png", img)
        if writer is not None:
            writer.add_image("val/gt_vs_render", img, self.step, dataformats="HWC")

    def fit(self, steps: int | None = None) -> TrainResult:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        cfg = self.cfg.train
        total = steps if steps is not None else cfg.steps
        writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=self.step or None)
        bar = tqdm(total=total, initial=self.step, desc=f"train {self.cfg.preset}",
                   unit="step", disable=self.quiet, dynamic_ncols=True)
        t0 = time.perf_counter()
        interrupted, psnr, rays_done, t_last = False, float("nan"), 0, time.perf_counter()
        try:
            while self.step < total:
                logs = self.train_step()
                rays_done += cfg.batch_rays
                psnr = logs["metrics/psnr"]
                if self.step % cfg.log_every == 0 or self.step == total:
                    now = time.perf_counter()
                    rps = rays_done / max(now - t_last, 1e-9)
                    logs["perf/rays_per_s"] = rps
                    for k, v in logs.items():
                        writer.add_scalar(k, v, self.step)
                    bar.set_postfix(loss=f"{logs['loss/total']:.4f}", psnr=f"{psnr:.2f}",
                                    rays_s=f"{rps:,.0f}")
                    rays_done, t_last = 0, now
                bar.update(1)
                if self.step % cfg.checkpoint_every == 0 and self.step < total:
                    self.save()
                if cfg.image_every and self.step % cfg.image_every == 0:
                    self.preview(writer)
        except KeyboardInterrupt:
            interrupted = True
            bar.write(f"interrupted at step {self.step}: saving a checkpoint to resume from")
        finally:
            bar.close()
        self.save()
        writer.close()
        return TrainResult(self.run_dir, self.step, interrupted, time.perf_counter() - t0, psnr)


def train(dataset: str | Path, out: str | Path, cfg: Config, resume: bool = False,
          device: str = "auto", quiet: bool = False, steps: int | None = None) -> TrainResult:
    trainer = Trainer(cfg, dataset, out, resume=resume, device=device, quiet=quiet,
                      steps=steps)
    return trainer.fit()
