"""Training on several processes (torchrun, docs/distributed.md): which process this is, its
device, the process group, how a step's batch splits into shards, and the few collectives the
training loop needs besides DistributedDataParallel's gradient all-reduce.

A step's `batch_rays` rays (and `face_reg_points` regulariser points) are split into
`world × accumulate` shards. Shard s draws its rays from a random stream of its own, seeded
by `shard_seed(seed, s)`; shard 0's stream is the one a single-process run has always used.
So a run on 2 processes draws exactly the rays of a run on 1 process with `accumulate=2`,
which is how the tests check that the distributed step is the single-process one.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from flamenerf.errors import UserError
from flamenerf.runtime import pick_device


@dataclass(frozen=True)
class Ranks:
    """This process's place in the job: `rank` of `world` processes, `local_rank` on its
    machine (torchrun's RANK, WORLD_SIZE, LOCAL_RANK). The default is a single process."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one process that writes checkpoints, logs and images."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    # ------------------------------------------------------------------ collectives
    def broadcast(self, obj: Any) -> Any:
        """Rank 0's `obj`, on every rank (what rank 0 read from disk: config, checkpoint)."""
        if not self.distributed:
            return obj
        box = [obj if self.main else None]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def gather(self, obj: Any) -> list[Any]:
        """Every rank's `obj`, in rank order, on every rank."""
        if not self.distributed:
            return [obj]
        out: list[Any] = [None] * self.world
        dist.all_gather_object(out, obj)
        return out

    def sum(self, values: list[float], device: torch.device) -> list[float]:
        """Element-wise sum over the ranks (one all-reduce of a small float64 tensor)."""
        if not self.distributed:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=device)
        dist.all_reduce(t)
        return t.tolist()

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def on_main(self, fn: Callable[[], Any]) -> Any:
        """fn() on rank 0 (reading or writing the run folder), its result on every rank. When
        it fails there, every rank stops: rank 0 with the error, the others quietly."""
        if not self.distributed:
            return fn()
        result, error = None, None
        if self.main:
            try:
                result = fn()
            except Exception as e:  # noqa: BLE001 - re-raised below, after telling the others
                error = e
        failed, result = self.broadcast((error is not None, result))
        if error is not None:
            raise error
        if failed:
            raise SystemExit(2)
        return result

    def failure(self, error: BaseException) -> BaseException:
        """What to raise for an error every rank meets at once (a diverged loss): the error
        on rank 0, which says it for the job, a quiet exit elsewhere."""
        return error if self.main else SystemExit(2)


def launched_ranks() -> Ranks:
    """The ranks torchrun gives this process through its environment (none: one process)."""
    env = os.environ
    try:
        world = int(env.get("WORLD_SIZE", "1"))
        rank = int(env.get("RANK", "0"))
        local = int(env.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise UserError(f"RANK={env.get('RANK')}, WORLD_SIZE={env.get('WORLD_SIZE')}, "
                        f"LOCAL_RANK={env.get('LOCAL_RANK')}: not integers (launch with "
                        "torchrun)") from None
    if world < 1 or not 0 <= rank < world or local < 0:
        raise UserError(f"RANK={rank}, WORLD_SIZE={world}: not a rank of the job (launch "
                        "with torchrun)")
    return Ranks(rank, world, local)


def process_device(device: str, ranks: Ranks) -> torch.device:
    """`pick_device`, and for one of several processes on a GPU machine the GPU of its
    LOCAL_RANK (one GPU per process, as torchrun's --nproc_per_node assumes)."""
    dev = pick_device(device)
    if not ranks.distributed or dev.type != "cuda":
        return dev
    if dev.index is not None:
        raise UserError(f"--device {device}: under torchrun each process takes the GPU of its "
                        "LOCAL_RANK; give --device cuda (or auto)")
    n = torch.cuda.device_count()
    if ranks.local_rank >= n:
        raise UserError(f"LOCAL_RANK {ranks.local_rank}: this machine has {n} GPU(s); start "
                        f"at most {n} processes on it (--nproc_per_node)")
    return torch.device("cuda", ranks.local_rank)


def backend_for(device: torch.device) -> str:
    """NCCL between GPUs, gloo between CPU processes."""
    return "nccl" if device.type == "cuda" else "gloo"


@contextlib.contextmanager
def process_group(ranks: Ranks, device: torch.device) -> Iterator[None]:
    """Join the job's process group for the block (nothing for a single process)."""
    if not ranks.distributed or dist.is_initialized():
        yield
        return
    missing = [k for k in ("MASTER_ADDR", "MASTER_PORT") if not os.environ.get(k)]
    if missing:
        raise UserError(f"WORLD_SIZE={ranks.world} but {' and '.join(missing)} not set: launch "
                        "with torchrun (docs/distributed.md)")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group(backend_for(device), rank=ranks.rank, world_size=ranks.world,
                            device_id=device if device.type == "cuda" else None)
    try:
        yield
    finally:
        dist.destroy_process_group()


# ----------------------------------------------------------------------------- shards


def split(n: int, parts: int) -> list[int]:
    """n items in `parts` near-equal parts, the larger first: split(10, 3) == [4, 3, 3]."""
    return [n // parts + (i < n % parts) for i in range(parts)]


def shard_seed(seed: int, shard: int) -> int:
    """The seed of shard `shard`'s random stream; shard 0's is `seed` itself. (torch's CPU
    generator keeps only the low 32 bits of a seed, hence the modulus.)"""
    return (seed + shard * 0x9E3779B9) % 2**32


# ----------------------------------------------------------------------------- launching


def torchrun_command(nproc: int, args: list[str]) -> list[str]:
    """`torchrun --standalone --nproc-per-node N -m flamenerf ARGS` with this Python."""
    return [sys.executable, "-m", "torch.distributed.run", "--standalone",
            f"--nproc-per-node={nproc}", "-m", "flamenerf", *args]


def launch(nproc: int, args: list[str]) -> tuple[int, bool]:
    """Run `flamenerf ARGS` on `nproc` local processes through torchrun and wait for it.
    -> (torchrun's exit status, whether Ctrl-C was pressed). Ctrl-C reaches torchrun from the
    terminal, and torchrun passes it on to the workers, which stop at a step boundary and
    save (training/interrupt.py); this process only waits for them."""
    pressed = []
    proc = subprocess.Popen(torchrun_command(nproc, args))
    previous = signal.signal(signal.SIGINT, lambda *_: pressed.append(1))
    try:
        return proc.wait(), bool(pressed)
    finally:
        signal.signal(signal.SIGINT, previous)
