"""Training on several processes (docs/distributed.md): 2 CPU processes with gloo against one
process with the same total batch; one writer; resume; Ctrl-C. The tests that start processes
are slow (about 25 s on the loaded 2-core machine, most of it starting interpreters)."""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest
import torch
from distributed_runs import Job, run_distributed
from toy import toy_config

from flamenerf.errors import UserError
from flamenerf.training.checkpoint import checkpoints, load_latest
from flamenerf.training.distributed import (Ranks, launched_ranks, process_device, shard_seed,
                                            split, torchrun_command)
from flamenerf.training.trainer import Trainer, may_skip_parameters

STEPS = 4


def cfg(accumulate=1):
    c = toy_config(steps=STEPS)
    c.train.log_every = 1  # every step's logs are gathered from both ranks
    c.train.accumulate = accumulate
    return c


@pytest.fixture(scope="module")
def runs(toy_dataset, tmp_path_factory):
    """On 2 processes: `a` trained 4 steps; `b` 2 steps, then resumed to 4; `c` with Ctrl-C
    reaching rank 1 alone during step 2."""
    root = tmp_path_factory.mktemp("ddp")
    t0 = time.perf_counter()
    run_distributed([Job(cfg(), toy_dataset, root / "a"),
                     Job(cfg(), toy_dataset, root / "b", stop_at=2),
                     Job(cfg(), toy_dataset, root / "b", resume=True),
                     Job(cfg(), toy_dataset, root / "c", ctrl_c=(1, 1))], root / "record")
    print(f"2-process runs: {time.perf_counter() - t0:.1f} s")
    return root


def model_of(run):
    return load_latest(run)[1]["model"]


def record(runs, what, rank):
    return json.loads((runs / "record" / f"{what}-rank{rank}.json").read_text())


@pytest.mark.slow
def test_two_processes_match_one_with_the_same_batch(runs, toy_dataset, tmp_path):
    # one process drawing the step's 64 rays as 2 shards of 32 (accumulate=2) draws the
    # rays, jitter and regulariser points the 2 processes drew: the union is the same batch
    one = Trainer(cfg(accumulate=2), toy_dataset, tmp_path / "one", device="cpu", quiet=True)
    one.fit()
    two, ref = model_of(runs / "a"), one.model.state_dict()
    assert two.keys() == ref.keys()
    for k in ref:
        # gradients meet in a different order of float additions (DDP's buckets): 1e-6;
        # measured: identical to the bit on this machine
        torch.testing.assert_close(two[k], ref[k], atol=1e-6, rtol=0, msg=k)
    # and training did something: the parameters moved away from the initial ones
    fresh = Trainer(cfg(), toy_dataset, tmp_path / "fresh", device="cpu", quiet=True)
    moved = [k for k, v in fresh.model.state_dict().items() if not torch.equal(v, ref[k])]
    assert "field.grid.tables.0" in moved and "deform_codes.weight" in moved


@pytest.mark.slow
def test_every_rank_holds_the_same_model(runs):
    for job in (0, 2):
        r0 = torch.load(runs / "record" / f"job{job}-rank0.pt", weights_only=True)
        r1 = torch.load(runs / "record" / f"job{job}-rank1.pt", weights_only=True)
        for k in r0:
            assert torch.equal(r0[k], r1[k]), k


@pytest.mark.slow
def test_only_rank_0_writes(runs):
    saves = [record(runs, "saves", r) for r in (0, 1)]
    assert saves[1] == []
    assert [(os.path.basename(d), s) for d, s in saves[0]] == [("a", 4), ("b", 2), ("b", 4),
                                                                ("c", 2)]
    assert [p.name for p in checkpoints(runs / "a")] == ["step-000000004.ckpt"]
    assert len(list((runs / "a" / "tb").iterdir())) == 1  # one TensorBoard writer
    st = load_latest(runs / "a")[1]
    assert len(st["shard_generators"]) == 2  # each rank's random stream, to resume from


@pytest.mark.slow
def test_resumed_two_process_run_is_the_uninterrupted_one(runs):
    a, b = model_of(runs / "a"), model_of(runs / "b")
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.slow
def test_ctrl_c_on_one_rank_stops_every_rank_at_the_same_step(runs):
    # rank 1 alone was interrupted while computing step 2: both ranks finish that step,
    # stop together, and rank 0 saves it (an exact resume point)
    assert [record(runs, "results", r)[3] for r in (0, 1)] == [[2, True], [2, True]]
    assert [p.name for p in checkpoints(runs / "c")] == ["step-000000002.ckpt"]


@pytest.mark.slow
def test_resume_on_another_number_of_processes_goes_on_with_a_warning(runs, toy_dataset,
                                                                      tmp_path, capsys):
    shutil.copytree(runs / "a", tmp_path / "a")
    t = Trainer(cfg(), toy_dataset, tmp_path / "a", resume=True, device="cpu", quiet=True,
                steps=STEPS + 2)
    assert t.step == STEPS
    assert "saved by a run of 2 shard(s), resumed with 1" in capsys.readouterr().err
    assert t.fit().step == STEPS + 2


# ----------------------------------------------------------------------------- pieces


def test_batch_splits_into_shards_with_streams_of_their_own():
    assert split(64, 2) == [32, 32] and split(10, 3) == [4, 3, 3] and sum(split(7, 4)) == 7
    assert shard_seed(5, 0) == 5  # shard 0 draws what a single process always drew
    assert len({shard_seed(0, s) for s in range(64)}) == 64


def test_ranks_come_from_torchruns_environment(monkeypatch):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(k, raising=False)
    assert launched_ranks() == Ranks(0, 1, 0)
    monkeypatch.setenv("RANK", "3")
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "1")
    r = launched_ranks()
    assert (r.rank, r.world, r.local_rank, r.main, r.distributed) == (3, 4, 1, False, True)
    monkeypatch.setenv("RANK", "4")
    with pytest.raises(UserError, match="torchrun"):
        launched_ranks()
    assert process_device("cpu", Ranks(1, 2, 1)).type == "cpu"


def test_fewer_rays_than_shards_is_a_one_line_error(toy_dataset, tmp_path):
    c = cfg(accumulate=4)
    c.train.batch_rays = 3
    with pytest.raises(UserError, match="--batch-rays 3: fewer rays than the step's 4 shards"):
        Trainer(c, toy_dataset, tmp_path / "run", device="cpu", quiet=True)


def test_ddp_searches_for_unused_parameters_exactly_when_a_step_can_skip_some(
        toy_dataset, tmp_path):
    # a parameter left out of the loss hangs the gradient all-reduce unless DDP was built
    # with find_unused_parameters: check on a step that only the parameters
    # `may_skip_parameters` allows for are ever left out
    def expression_field(name):
        return name.startswith(("field.expr_grid.", "field.expr_proj."))

    for warp, rank, detail in ((True, 0, 0), (False, 0, 0), (True, 8, 0), (True, 0, 4)):
        c = cfg()
        c.model.warp.enabled = warp
        c.model.warp.still_head_only = False  # the warp everywhere: it sees every batch
        c.model.field.expr_rank, c.model.field.detail_levels = rank, detail
        t = Trainer(c, toy_dataset, tmp_path / f"w{warp}{rank}{detail}", device="cpu",
                    quiet=True)
        t.opt.step = lambda: None  # keep the gradients to look at them
        t.train_step()
        unused = {n for n, p in t.model.named_parameters() if p.grad is None
                  and not (rank and expression_field(n))
                  and not (detail and n.startswith("field.detail."))}
        assert unused == (set() if warp else {"deform_codes.weight"}), unused
        assert may_skip_parameters(t.model) == (not warp or rank > 0 or detail > 0)
    c = cfg()  # `fast`'s warp, in the head's region only: a batch may miss it
    c.model.field.expr_rank, c.model.field.detail_levels = 0, 0
    assert c.model.warp.still_head_only
    t = Trainer(c, toy_dataset, tmp_path / "still", device="cpu", quiet=True)
    assert t.model.warp_in_head and may_skip_parameters(t.model)


def test_train_nproc_passes_its_other_options_on():
    import inspect

    from flamenerf.commands.train import _flags, train

    values = {n: p.default for n, p in inspect.signature(train).parameters.items()}
    values.update(dataset="scene", resume=True, batch_rays=512, nproc=4,
                  random_background=False)
    assert _flags(values, skip={"nproc"}) == ["scene", "--batch-rays", "512",
                                              "--random-background", "False", "--resume"]


@pytest.mark.slow
def test_torchrun_command_runs_the_package():
    cmd = torchrun_command(2, ["train", "scene"])
    assert cmd[1:4] == ["-m", "torch.distributed.run", "--standalone"]
    assert cmd[-4:] == ["-m", "flamenerf", "train", "scene"]
    out = subprocess.run([sys.executable, "-m", "flamenerf", "train", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "--nproc" in out.stdout


@pytest.mark.slow
def test_train_nproc_launches_torchrun(toy_dataset, tmp_path):
    # the whole path a user takes: `flamenerf train --nproc 2` -> torchrun -> 2 x
    # `python -m flamenerf train` -> gloo (the `fast` preset on the 16 px toy dataset)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-m", "flamenerf", "train", str(toy_dataset), "--out",
         str(tmp_path / "run"), "--steps", "2", "--batch-rays", "64", "--device", "cpu",
         "--nproc", "2"], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("finished at step 2") == 1  # rank 0 speaks for the job
    assert [p.name for p in checkpoints(tmp_path / "run")] == ["step-000000002.ckpt"]
    assert len(load_latest(tmp_path / "run")[1]["shard_generators"]) == 2
