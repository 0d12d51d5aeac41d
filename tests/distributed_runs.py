"""Toy runs on several CPU processes (gloo), for tests/training/test_distributed.py.

The processes are started with torch.multiprocessing's spawn and given the environment
torchrun gives its workers (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT), so
they take the same path as under `torchrun -m flamenerf train`: `launched_ranks`, then
`process_group`, then the Trainer. Lives outside the test module so that the spawned
interpreters can import it (tests/ is on sys.path)."""

from __future__ import annotations

import json
import os
import signal
import socket
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.multiprocessing as mp

from flamenerf.config import Config


@dataclass
class Job:
    """One Trainer on every rank: `Trainer(cfg, dataset, out, resume).fit(steps=stop_at)`;
    `ctrl_c`: (rank, step): that rank alone gets a SIGINT while it computes step + 1."""

    cfg: Config
    dataset: Path
    out: Path
    resume: bool = False
    stop_at: int | None = None
    ctrl_c: tuple[int, int] | None = None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, jobs: list[Job], record: Path) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE=str(world), LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from flamenerf.training import trainer as trainer_module
    from flamenerf.training.distributed import launched_ranks, process_group

    saves, results = [], []  # the checkpoints this rank wrote; where each job ended
    real = trainer_module.save_checkpoint

    def save_checkpoint(run_dir, step, *a, **k):
        saves.append([str(run_dir), step])
        return real(run_dir, step, *a, **k)

    trainer_module.save_checkpoint = save_checkpoint
    ranks = launched_ranks()
    with process_group(ranks, torch.device("cpu")):
        for i, job in enumerate(jobs):
            t = trainer_module.Trainer(job.cfg, job.dataset, job.out, resume=job.resume,
                                       device="cpu", quiet=True, ranks=ranks)
            if job.ctrl_c is not None and job.ctrl_c[0] == rank:
                real_step = t.train_step

                def step(t=t, real_step=real_step, at=job.ctrl_c[1]):
                    if t.step == at:
                        signal.raise_signal(signal.SIGINT)
                    return real_step()

                t.train_step = step
            res = t.fit(steps=job.stop_at)
            torch.save(t.model.state_dict(), record / f"job{i}-rank{rank}.pt")
            results.append([res.step, res.interrupted])
    (record / f"saves-rank{rank}.json").write_text(json.dumps(saves))
    (record / f"results-rank{rank}.json").write_text(json.dumps(results))


def run_distributed(jobs: list[Job], record: Path, world: int = 2) -> None:
    """Run `jobs` one after another on `world` spawned processes; each rank leaves its
    model after job i in record/job{i}-rank{r}.pt, the checkpoints it wrote in
    record/saves-rank{r}.json and each job's [step, interrupted] in results-rank{r}.json."""
    record.mkdir(parents=True, exist_ok=True)
    mp.spawn(_worker, args=(world, _free_port(), jobs, record), nprocs=world, join=True)
