"""The training loop: progress bar, TensorBoard, atomic checkpoints, exact resume, Ctrl-C;
on one process or several (DistributedDataParallel under torchrun, docs/distributed.md)."""

from __future__ import annotations

import contextlib
import json
import math
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from flamenerf import __version__
from flamenerf.config import Config
from flamenerf.data.dataset import Dataset, Frame, Intrinsics, fingerprint, load_dataset
from flamenerf.data.expression_range import training_expressions
from flamenerf.data.face_parts import applies, has_parts
from flamenerf.data.mesh_model import (expression_model_residual, fit_dataset_expression_model,
                                       generic_controls)
from flamenerf.data.scene import (FrameSet, face_pixel_resolution, model_detail_region,
                                  model_head_region, model_warp_region, scene_box)
from flamenerf.errors import Interrupted, UserError, warn
from flamenerf.images import resize_image
from flamenerf.io import TEMP_NAME, atomic_write_text, read_json, save_png
from flamenerf.lock import folder_lock
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.mlp import bf16_pays, bf16_training
from flamenerf.model.render_image import render_image
from flamenerf.outdir import (LOCK_NAME, RUN_LAYOUT, clean_stale_temps,
                              folders_kept_only_on_success, writable_dir)
from flamenerf.runtime import set_threads
from flamenerf.training.run import run_config
from flamenerf.training.checkpoint import (LEGACY_TEMP, latest_checkpoint, load_latest,
                                           load_model_state, rng_states, save_checkpoint,
                                           set_rng_states)
from flamenerf.training.distributed import (Ranks, launched_ranks, process_device,
                                            process_group, shard_seed, split)
from flamenerf.training.interrupt import StopRequest
from flamenerf.model.losses import LossBatch, LossWeights, PER_POINT, psnr_from_mse


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
    if cfg.deform_code_lr_scale != 1.0:  # a group only when asked: older runs' optimiser
        special.append((model.deform_codes, cfg.deform_code_lr_scale))  # states still load
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


def moving_shares(ds: Dataset, frames: list[Frame], intr: Intrinsics) -> torch.Tensor | None:
    """The share of each training pixel that is background moving by itself: the frames'
    `moving_path` masks area-averaged to `intr`'s size -> (N, H, W) float32 (0 for a
    frame without a mask), or None where no frame flags a pixel, so that such a dataset's
    steps carry no per-ray weights at all (the same training as before the masks)."""
    if not any(f.moving_path is not None for f in frames):
        return None
    out = np.zeros((len(frames), intr.h, intr.w), np.float32)
    for i, fr in enumerate(frames):
        m = ds.load_moving(fr)
        if m is not None and m.any():
            out[i] = resize_image(m.astype(np.float32)[..., None], intr.w, intr.h)[..., 0]
    return torch.from_numpy(out) if out.any() else None


def over_random_background(out: dict, colour: torch.Tensor) -> dict:
    """A forward pass's colours (rendered over black) over per-ray colours (R, 3) instead:
    rgb + colour·(1 - acc), and the coarse network's likewise. -> a new dict."""
    out = dict(out)
    for k, a in (("rgb", "acc"), ("rgb_coarse", "acc_coarse")):
        if k in out:
            out[k] = out[k] + colour * (1 - out[a])[:, None]
    return out


def may_skip_parameters(model: FlameNeRF) -> bool:
    """Whether a step's loss can leave parameters out (DDP must then search the graph):
    the deformation codes without a warp, or with a warp confined to the head's region (a
    batch with no sample there); the expression feature fields in a batch where no sample
    gets a non-zero β (no face ray, or none near a control's region); the detail levels in
    a batch with no sample in the head's region."""
    return (model.warp is None or model.warp_in_head
            or getattr(model.field, "expr_grid", None) is not None
            or getattr(model.field, "detail", None) is not None)


def settle_dataset_defaults(cfg: Config, ds: Dataset) -> Config:
    """Fill the config's dataset-dependent defaults in place (the per-control prior's radius,
    whether the deformation is mesh-guided, whether and how closely it stays in the head's
    region, the hash grid's finest resolution), so that a run's config.json holds what it
    trained with. -> cfg."""
    kind, names, nv = ds.expression_kind, ds.expression_names, ds.face_vertices.shape[1]
    use_parts = cfg.model.mesh_guide.face_parts
    regions = cfg.model.expression_regions
    # the wider fade was measured on tracked clips, the narrower on the built-in scene
    regions.radius = regions.resolved_radius(use_parts and applies(kind, names, nv))
    cfg.model.mesh_guide.enabled = cfg.model.mesh_guide.resolved_enabled(
        use_parts and has_parts(kind, names, nv, ds.face_landmarks))
    cfg.model.warp.settle()
    field = cfg.model.field
    if field.kind == "hash" and (field.hash_max_res == 0 or
                                 (field.detail_levels > 0 and field.detail_max_res == 0)):
        px = face_pixel_resolution(ds, train_resolution(ds, cfg))
        if field.hash_max_res == 0:
            field.hash_max_res = min(max(px, 2 * field.hash_base_res), 8192)
        if field.detail_levels > 0 and field.detail_max_res == 0:
            field.detail_max_res = min(max(2 * px, field.hash_max_res + field.detail_levels),
                                       8192)
    return cfg


def build_for_dataset(cfg: Config, ds: Dataset) -> FlameNeRF:
    """The model for `ds` (settling the config's dataset-dependent defaults first)."""
    settle_dataset_defaults(cfg, ds)
    lo, hi = scene_box(ds)
    V, nf = ds.face_vertices.shape[1], len(ds.faces)
    model = FlameNeRF(cfg.model, num_codes=ds.num_codes, expr_dim=ds.expression_dim,
                      near=ds.near, far=ds.far, box_min=lo, box_max=hi,
                      mesh_vertices=V, mesh_faces=nf, head_region=model_head_region(cfg, ds),
                      detail_region=model_detail_region(cfg, ds),
                      warp_region=model_warp_region(cfg, ds),
                      background=cfg.train.render_background)
    if cfg.model.expression_centre and cfg.model.expression_mode != "none" and ds.expression_dim:
        model.set_expression_mean(torch.from_numpy(training_expressions(ds).mean(0)))
    if model.expression.uses_mesh_model:
        mg = cfg.model.mesh_guide
        # generic shapes act through the mesh guide alone, with the fields kept from them
        generic = bool(mg.generic_shapes and model.expression.mesh_guided
                       and model.expression.regions)
        neutral, basis = fit_dataset_expression_model(ds, mg.ridge, mg.face_parts, mg.stored,
                                                      generic)
        model.set_expression_model(neutral, basis, torch.from_numpy(ds.faces).long(),
                                   generic_controls(ds) if generic else ())
        limit = cfg.model.mesh_guide.max_residual
        if model.expression.mesh_guided and limit is not None:
            miss = expression_model_residual(ds, neutral, basis)
            model.set_guide_skip((miss > limit).nonzero()[:, 0])
    return model


@dataclass
class Shard:
    """One part of a step's batch (training/distributed.py): its index among all the
    step's shards (over every process), its random stream, its rays and regulariser points."""

    index: int
    gen: torch.Generator
    rays: int
    points: int


class _ShardLoss(torch.nn.Module):
    """What DistributedDataParallel wraps. DDP all-reduces the gradients of a backward pass
    only when the loss came out of its own forward, and a shard's loss uses more of the
    model than `FlameNeRF.forward` (the codes, the warp regulariser): so the forward here
    runs the whole shard loss, given as a closure."""

    def __init__(self, model: FlameNeRF):
        super().__init__()
        self.model = model

    def forward(self, loss_fn):
        return loss_fn()


def _weighted_sum(terms: list[tuple[torch.Tensor, float]], factor: float) -> torch.Tensor:
    """Σ term · weight · factor; exactly Σ term where every weight · factor is 1 (one
    process, one shard: the single-process step, bit for bit)."""
    out = None
    for t, w in terms:
        t = t if w * factor == 1.0 else t * (w * factor)
        out = t if out is None else out + t
    return out


def _refuse_foreign_folder(run_dir: Path) -> None:
    """A run goes into a new folder, an empty one, or one that holds a run (or what a
    run that stopped early left): not into a folder of other things (a dataset's images,
    someone's notes), whose files would then sit in the run and block --overwrite."""
    if not run_dir.is_dir():
        return
    entries = [p.name for p in run_dir.iterdir()
               if p.name != LOCK_NAME and not TEMP_NAME.match(p.name)]
    if entries and not any(e in RUN_LAYOUT for e in entries):
        shown = ", ".join(sorted(entries)[:3]) + (", ..." if len(entries) > 3 else "")
        raise UserError(f"{run_dir}: holds files that are not a run ({shown}); give train a "
                        "new or empty --out folder")


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
                 steps: int | None = None, ranks: Ranks | None = None,
                 other_dataset: bool = False):
        """`ranks`: this process's place in a distributed job (its process group joined,
        `training.distributed.process_group`); None for a single process. `other_dataset`:
        resume on a dataset whose content differs from the one the run was trained on."""
        self.run_dir = Path(run_dir)
        self.other_dataset = other_dataset
        self.ranks = ranks = ranks or Ranks()
        self.device = process_device(device, ranks)
        self.quiet = quiet or not ranks.main

        def read_run() -> tuple[Config, bool]:
            if (self.run_dir / "transforms.json").exists():
                raise UserError(f"{self.run_dir}: is a dataset (it holds transforms.json); "
                                "give the run its own --out folder")
            _refuse_foreign_folder(self.run_dir)
            ck = latest_checkpoint(self.run_dir)
            if ck is not None and not resume:
                raise UserError(f"{self.run_dir}: already holds a run (pass --resume to "
                                "continue it, or choose another --out)")
            where = self.run_dir / "config.json"
            if resume and (ck is not None or where.is_file()):
                saved = read_json(where)
                cfg_saved = run_config(saved, where)  # a resumed run keeps its own config
                self._check_same_dataset(saved, dataset)
                if ck is None and not self.quiet:
                    print(f"note: --resume: {self.run_dir} holds no checkpoint yet; starting "
                          "it again from step 0 with its saved settings")
                return cfg_saved, ck is not None
            if resume and not self.quiet:
                print(f"note: --resume: {self.run_dir} holds no run yet; starting a new one "
                      "there")
            # decided once, here, and stored: a measurement must not change a run's numbers
            cfg.train.bf16 = cfg.train.bf16 and self.device.type == "cpu" and bf16_pays()
            return cfg, False

        # rank 0 reads (and writes) the run folder and tells the others, so that every rank
        # starts from the same config and checkpoint, even where a node sees it late
        cfg, resuming = ranks.on_main(read_run)
        if steps is not None:
            cfg.train.steps = steps
        for flag, v in (("--steps", cfg.train.steps), ("--batch-rays", cfg.train.batch_rays),
                        ("--accumulate", cfg.train.accumulate)):
            if v < 1:
                raise ranks.failure(UserError(f"{flag} {v}: must be at least 1"))
        shards = ranks.world * cfg.train.accumulate
        if cfg.train.batch_rays < shards:
            raise ranks.failure(UserError(
                f"--batch-rays {cfg.train.batch_rays}: fewer rays than the step's {shards} "
                f"shards ({ranks.world} process(es) x accumulate {cfg.train.accumulate})"))
        self.cfg = cfg
        set_threads(cfg.train.num_threads)
        self.ds = load_dataset(dataset)
        with folders_kept_only_on_success(self.run_dir, remove=ranks.main):
            ranks.on_main(self._prepare_dir)
            self._build(resuming)

    def _build(self, resuming: bool) -> None:
        cfg, ranks = self.cfg, self.ranks
        self.intr = train_resolution(self.ds, cfg)
        torch.manual_seed(cfg.train.seed)
        self.model = build_for_dataset(cfg, self.ds).to(self.device)
        self.train_set = FrameSet(self.ds, self.ds.split("train"), self.intr)
        self.moving = moving_shares(self.ds, self.train_set.frames, self.intr)
        if cfg.train.face_depth_weight > 0:  # before the progress bar starts
            self.train_set.mesh_depths()
        fused = self.device.type in ("cpu", "cuda")
        eps = 1e-15 if cfg.model.field.kind == "hash" else 1e-8
        self.opt = torch.optim.Adam(param_groups(self.model, cfg.train), lr=cfg.train.lr,
                                    eps=eps, fused=fused)
        self.shards = self._make_shards()
        self.gen = self.shards[0].gen  # on rank 0 the stream of a single-process run
        self.step = 0
        self._saved_step: int | None = None  # the step of the newest checkpoint on disk
        if resuming:
            self._load()
        ranks.on_main(self._write_config)
        self.ddp = None
        if ranks.distributed:
            from torch.nn.parallel import DistributedDataParallel

            # buffers (box, expression mesh) are the same on every rank: no broadcasts
            self.ddp = DistributedDataParallel(
                _ShardLoss(self.model), forward_sync_buffers=False,
                find_unused_parameters=may_skip_parameters(self.model))

    def _make_shards(self) -> list[Shard]:
        """This process's shards of every step's batch (training/distributed.py)."""
        t, r = self.cfg.train, self.ranks
        n = r.world * t.accumulate
        rays, points = split(t.batch_rays, n), split(t.face_reg_points, n)
        ids = range(r.rank * t.accumulate, (r.rank + 1) * t.accumulate)
        if r.rank > 0 and self.device.type == "cuda":  # the sample jitter on a GPU
            torch.cuda.manual_seed(shard_seed(t.seed, ids[0]))
        return [Shard(s, torch.Generator().manual_seed(shard_seed(t.seed, s)), rays[s],
                      points[s]) for s in ids]

    # --------------------------------------------------------------- persistence
    def _check_same_dataset(self, saved: dict, dataset: str | Path) -> None:
        """Refuse to resume on another dataset than the run's: by content where the run
        recorded it (a moved or copied dataset is the same one; one made again at the same
        place is not), else by place."""
        before, given = Path(saved["dataset"]), Path(dataset).resolve()
        recorded = saved.get("dataset_fingerprint")
        if isinstance(recorded, str):
            if recorded == fingerprint(load_dataset(given, check_files=False)):
                return
            if self.other_dataset:
                warn(f"{given}: not the dataset {self.run_dir} was trained on (its "
                     "transforms.json or files differ); resuming on it as asked")
                return
            raise UserError(f"{given}: not the dataset {self.run_dir} was trained on (its "
                            f"transforms.json or files differ from those of {before}); "
                            "resume on that one, train a new run, or pass "
                            "--other-dataset to go on with this one")
        if before.exists() and before.resolve() != given and not self.other_dataset:
            raise UserError(f"{self.run_dir}: was trained on {before}, not {given}; "
                            "resume it with that dataset (or train a new run; "
                            "--other-dataset goes on with this one)")
        if not before.exists() and not self.quiet:
            warn(f"{self.run_dir}: records no content of its dataset (trained by an older "
                 f"flamenerf) and {before} is gone: {given} is taken on trust")

    def _prepare_dir(self) -> None:
        writable_dir(self.run_dir, "run")  # before the slow part, not at the first save
        self._clean_temps()

    def _clean_temps(self) -> None:
        """Partial files that a killed run of this folder left (a checkpoint is ~100 MB)."""
        gone = (clean_stale_temps(self.run_dir / "checkpoints", legacy=LEGACY_TEMP)
                + clean_stale_temps(self.run_dir) + clean_stale_temps(self.run_dir / "images"))
        if gone:
            warn(f"{self.run_dir}: removed {len(gone)} partial file(s) left by an interrupted "
                 "run")

    def _write_config(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        meta = {
            "flamenerf_version": __version__,
            "preset": self.cfg.preset,
            "dataset": str(Path(self.ds.root).resolve()),
            "dataset_fingerprint": fingerprint(self.ds),
            "expression_names": self.ds.expression_names,
            "expression_kind": self.ds.expression_kind,
            "train_size": [self.intr.w, self.intr.h],
            "model_args": self.model.init_args,
            "config": self.cfg.to_dict(),
        }
        atomic_write_text(self.run_dir / "config.json", json.dumps(meta, indent=1))

    def state(self) -> dict:
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "model_args": self.model.init_args,
            "optimizer": self.opt.state_dict(),
            **rng_states(self.gen),
            "config": self.cfg.to_dict(),
            "version": __version__,
        }

    def save(self) -> Path | None:
        """Write a checkpoint (rank 0; every rank takes part, handing over its random
        streams). -> its path on rank 0, None elsewhere."""
        streams = [g for rank in self.ranks.gather([sh.gen.get_state() for sh in self.shards])
                   for g in rank]

        def write() -> Path:
            state = self.state()
            if len(streams) > 1:  # "generator" holds shard 0's, as in a single-process run
                state["shard_generators"] = streams
            return save_checkpoint(self.run_dir, self.step, state,
                                   self.cfg.train.keep_checkpoints)

        path = self.ranks.on_main(write)
        self._saved_step = self.step
        return path if self.ranks.main else None

    def _kept(self) -> str:
        ck = latest_checkpoint(self.run_dir)
        return f"the run resumes from {ck}" if ck else "no checkpoint was saved"

    def _load(self) -> None:
        path, st = self.ranks.on_main(lambda: load_latest(self.run_dir))
        try:
            load_model_state(self.model, st["model"], path)
            try:
                self.opt.load_state_dict(st["optimizer"])
            except ValueError as e:  # a checkpoint from before the per-group learning rates
                raise UserError(f"{path}: optimiser state does not match this version's "
                                f"parameter groups ({e}); start a new run") from None
            except (KeyError, TypeError, IndexError, RuntimeError) as e:  # edited, damaged
                raise UserError(f"{path}: not a readable checkpoint (damaged optimiser "
                                f"state: {type(e).__name__})") from None
            set_rng_states(st, self.gen, path)
        except UserError as e:
            raise self.ranks.failure(e) from None
        self.step = st["step"]  # an int: load_checkpoint checked it
        self._saved_step = self.step
        self._restore_streams(st, path)

    def _restore_streams(self, st: dict, path: Path) -> None:
        """Each shard's random stream as saved; when the run had another number of shards
        (processes x accumulate), the shards the checkpoint lacks start new streams."""
        t = self.cfg.train
        total = self.ranks.world * t.accumulate
        saved = st.get("shard_generators") or [st["generator"]]
        if len(saved) == total:
            for sh in self.shards:
                sh.gen.set_state(saved[sh.index])
            return
        for sh in self.shards:
            if sh.index > 0:
                sh.gen.manual_seed(shard_seed(t.seed + self.step, sh.index))
        if self.ranks.main:
            warn(f"{path}: saved by a run of {len(saved)} shard(s), resumed with {total} "
                 f"({self.ranks.world} process(es) x accumulate {t.accumulate}): it goes on, "
                 "with other rays than the run would have drawn")

    # --------------------------------------------------------------- one step
    def train_step(self) -> dict[str, float]:
        """One optimiser step on this process's shards of the batch. -> its logs (the loss
        terms weighted by the shards' share of the step: the whole step's once summed over
        the processes, `_sync`)."""
        cfg, model = self.cfg.train, self.model
        model.train()
        model.update_to_step(self.step, cfg.steps)
        for g in self.opt.param_groups:
            g["lr"] = learning_rate(self.step, cfg) * g["lr_scale"]
        self.opt.zero_grad(set_to_none=True)
        logs: dict[str, float] = {}
        with bf16_training(cfg.bf16):
            self._shard_steps(logs)
        self.opt.step()
        self.step += 1
        logs["metrics/psnr"] = psnr_from_mse(logs["loss/photo"])
        if model.warp is not None:
            logs["params/warp_alpha"] = float(model.warp.alpha)
        return logs

    def _shard_steps(self, logs: dict[str, float]) -> None:
        """Every shard's forward and backward pass, gradients summed; their logs into `logs`."""
        for j, shard in enumerate(self.shards):
            fn = partial(self._shard_loss, shard)
            # DDP all-reduces the summed gradients once, in the last shard's backward pass
            last = j == len(self.shards) - 1
            with contextlib.nullcontext() if self.ddp is None or last else self.ddp.no_sync():
                loss, shard_logs = fn() if self.ddp is None else self.ddp(fn)
                loss.backward()
            for k, v in shard_logs.items():
                logs[k] = logs.get(k, 0.0) + v

    def _shard_loss(self, sh: Shard) -> tuple[torch.Tensor, dict[str, float]]:
        """One shard's loss, scaled so that the gradients summed over the step's shards
        (DDP averages over the processes) are those of the whole batch's mean loss, and its
        logged terms weighted by its share of the batch."""
        cfg, model, ts, gen = self.cfg.train, self.model, self.train_set, sh.gen
        share = sh.rays / cfg.batch_rays
        fi, ys, xs = ts.sample_pixels(sh.rays, gen, cfg.face_ray_fraction)
        omega, phi = model.codes(ts.frame_index[fi].to(self.device))
        rays, target = ts.ray_batch(fi, ys, xs, omega, phi, self.device)
        out = model(rays, jitter=True, generator=gen if self.device.type == "cpu" else None)
        if cfg.random_background:
            out = over_random_background(out, torch.rand(len(target), 3, generator=gen)
                                         .to(self.device))
        batch = LossBatch(target)
        if self.moving is not None:
            batch.moving = self.moving[fi, ys, xs].to(self.device)
        if cfg.face_depth_weight > 0 and self.step >= cfg.face_depth_start * cfg.steps:
            depth = ts.mesh_depths()[fi, ys, xs].to(self.device)
            batch.mesh_depth = torch.where(rays.face_ray, depth,
                                           torch.full_like(depth, float("inf")))
        regularised = cfg.face_reg_weight > 0 and model.warp is not None
        p_share = 0.0
        if regularised and sh.points > 0:
            pfi = torch.randint(ts.n, (sh.points,), generator=gen)
            batch.reg_points = model.face_reg_points(
                sh.points, gen, lambda: ts.face_points(pfi, gen).to(self.device))
            batch.reg_codes, _ = model.codes(ts.frame_index[pfi].to(self.device))
            p_share = sh.points / cfg.face_reg_points
        losses = model.get_loss_dict(out, batch, LossWeights(
            cfg.interlevel_weight, cfg.face_depth_weight, cfg.face_depth_margin,
            cfg.face_reg_weight, cfg.moving_weight))
        # rays' terms by this shard's share of the rays, the regulariser's by its points'
        terms = [(t, p_share if k in PER_POINT else share) for k, t in losses.weighted.items()]
        logs = {f"loss/{k}": v.item() * (p_share if k in PER_POINT else share)
                for k, v in losses.raw.items()}
        if regularised and "loss/face_reg" not in logs:
            logs["loss/face_reg"] = 0.0  # a shard without points: logged as the others
        loss = _weighted_sum(terms, self.ranks.world)
        logs["loss/total"] = loss.item() / self.ranks.world
        logs["perf/samples"] = float(out["num_samples"])
        return loss, logs

    def _sync(self, logs: dict[str, float], stop: bool) -> tuple[dict[str, float], bool]:
        """The step's logs over every process, and whether any was asked to stop: one small
        all-reduce, so that every rank stops, saves or gives up at the same step."""
        if not self.ranks.distributed:
            return logs, stop
        keys = [k for k in logs if k.startswith(("loss/", "perf/"))]
        *vals, stops = self.ranks.sum([logs[k] for k in keys] + [float(stop)], self.device)
        logs = {**logs, **dict(zip(keys, vals))}
        logs["metrics/psnr"] = psnr_from_mse(logs["loss/photo"])
        return logs, stops > 0

    # --------------------------------------------------------------- loop
    def preview(self, writer=None) -> None:
        """Render the first val frame (else train frame 0) with its own codes."""
        frames = self.ds.splits.get("val") or self.ds.splits["train"]
        fr = self.ds.frames[frames[0]]
        fs = FrameSet(self.ds, [fr], self.intr)
        omega, phi = self.model.codes(fs.frame_index.to(self.device))
        with self.model.outside_training():
            out = render_image(self.model, self.intr, fs.c2w[0], omega[0], phi[0],
                               fs.expressions[0], fs.masks[0])
        img = torch.cat([fs.images[0], out["rgb"]], 1).numpy()
        save_png(self.run_dir / "images" / f"step-{self.step:09d}.png", img)
        if writer is not None:
            writer.add_image("val/gt_vs_render", img, self.step, dataformats="HWC")

    def fit(self, steps: int | None = None) -> TrainResult:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        cfg, main = self.cfg.train, self.ranks.main
        total = steps if steps is not None else cfg.steps
        writer = (SummaryWriter(str(self.run_dir / "tb"), purge_step=self.step or None)
                  if main else None)
        bar = tqdm(total=total, initial=self.step, desc=f"train {self.cfg.preset}",
                   unit="step", disable=self.quiet, dynamic_ncols=True)
        t0 = time.perf_counter()
        psnr, rays_done, t_last = float("nan"), 0, time.perf_counter()
        stopping = False
        # Ctrl-C only asks to stop: the step in flight completes, so the checkpoint saved
        # below is an exact resume point (training/interrupt.py). With several processes
        # each one's request is summed into the step's logs (`_sync`): all stop together
        with StopRequest() as stop:
            try:
                while self.step < total and not stopping:
                    logs, asked = self._sync(self.train_step(), stop.requested)
                    if not math.isfinite(logs["loss/total"]):
                        raise self.ranks.failure(UserError(
                            f"{self.run_dir}: training diverged (loss {logs['loss/total']} at "
                            f"step {self.step}; check the dataset's cameras and scale, or lower "
                            f"the learning rate); stopped without saving: {self._kept()}"))
                    rays_done += cfg.batch_rays
                    psnr = logs["metrics/psnr"]
                    if self.step % cfg.log_every == 0 or self.step == total:
                        now = time.perf_counter()
                        rps = rays_done / max(now - t_last, 1e-9)
                        logs["perf/rays_per_s"] = rps
                        for k, v in logs.items() if writer is not None else ():
                            writer.add_scalar(k, v, self.step)
                        bar.set_postfix(loss=f"{logs['loss/total']:.4f}", psnr=f"{psnr:.2f}",
                                        rays_s=f"{rps:,.0f}")
                        rays_done, t_last = 0, now
                    bar.update(1)
                    if self.step % cfg.checkpoint_every == 0 and self.step < total:
                        stop.what = f"saving the checkpoint of step {self.step}"
                        self.save()
                        stop.what = "the current step"
                    if cfg.image_every and self.step % cfg.image_every == 0 and main:
                        self.preview(writer)
                    # one process reads its own presses up to the end of the step; several
                    # go by what `_sync` gathered, the same on every rank
                    stopping = asked or (not self.ranks.distributed and stop.requested)
                if stopping and main:
                    bar.write(f"interrupted at step {self.step}: saving a checkpoint to resume "
                              "from")
                stop.what = f"saving the checkpoint of step {self.step}"
                if self._saved_step != self.step:
                    self.save()
                self.ranks.barrier()  # no rank leaves (ending the job) before rank 0 saved
            except KeyboardInterrupt:
                # not through the flag (a third Ctrl-C, or outside the main thread): the step
                # or save in flight is abandoned, never saved half done
                raise Interrupted(f"gave up {stop.what} (nothing half done is saved); "
                                  f"{self._kept()}") from None
            finally:
                bar.close()
                if writer is not None:
                    writer.close()
        return TrainResult(self.run_dir, self.step, stopping, time.perf_counter() - t0, psnr)


def train(dataset: str | Path, out: str | Path, cfg: Config, resume: bool = False,
          device: str = "auto", quiet: bool = False, steps: int | None = None,
          other_dataset: bool = False) -> TrainResult:
    """Train on this process, or as one rank of the job torchrun started it in
    (`other_dataset`: see Trainer)."""
    ranks = launched_ranks()
    # one writer per run folder: the process that writes it (rank 0) holds its lock
    with process_group(ranks, process_device(device, ranks)), folder_lock(out, "run", ranks.main):
        trainer = Trainer(cfg, dataset, out, resume=resume, device=device, quiet=quiet,
                          steps=steps, ranks=ranks, other_dataset=other_dataset)
        return trainer.fit()
