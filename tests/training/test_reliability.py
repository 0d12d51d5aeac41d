"""Checkpoints that cannot run code, exact resume after Ctrl-C, saves that survive a second
Ctrl-C or a full disk, and fall-backs past damaged files (docs/reliability.md)."""

import errno
import os
import signal
import subprocess
import sys

import pytest
import torch
from test_training import small

from flamenerf.config import preset
from flamenerf.errors import Interrupted, UserError
from flamenerf.training import checkpoint as ckpt
from flamenerf.training.checkpoint import checkpoints, latest_checkpoint
from flamenerf.training.run import load_run
from flamenerf.training.trainer import Trainer


def trainer(scene, run, steps, resume=False, every=1000):
    cfg = small(preset("fast"), steps)
    cfg.train.checkpoint_every = every
    # a resumed run keeps its saved config, except the number of steps
    return Trainer(cfg, scene, run, resume=resume, quiet=True, steps=steps if resume else None)


def ctrl_c_at(t, monkeypatch, step, where="opt"):
    """Press Ctrl-C inside step `step` + 1, just before the optimiser update: the moment at
    which an interrupt used to leave a half-done step behind."""
    real = t.opt.step

    def opt_step(*a, **k):
        if t.step == step:
            signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(t.opt, "step", opt_step)


def same_params(a, b):
    sa, sb = a.model.state_dict(), b.model.state_dict()
    return all(torch.equal(sa[k], sb[k]) for k in sa)


# ----------------------------------------------------------------------------- no pickle


@pytest.mark.slow
def test_checkpoint_loads_without_pickle(tiny_scene, tmp_path):
    trainer(tiny_scene, tmp_path / "run", 1).fit()
    st = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)
    assert st["format"] == ckpt.FORMAT and st["step"] == 1


def bits(t):
    return t.reshape(-1).view(torch.uint8)


@pytest.mark.slow
def test_adam_moments_of_untouched_table_rows_are_not_stored(tiny_scene, tmp_path):
    trainer(tiny_scene, tmp_path / "run", 1).fit()
    raw = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)
    sparse = [s for s in raw["optimizer"]["state"].values() if "sparse_rows" in s]
    assert sparse and all(s["exp_avg"].shape[0] < s["num_rows"] for s in sparse)


def test_sparse_moments_round_trip_bit_exactly():
    m, v = torch.zeros(4096, 2), torch.zeros(4096, 2)
    m[5] = torch.tensor([1.5, 2.0])
    v[7, 1] = float("nan")
    m[9, 0] = -0.0  # equal to 0.0, but not the same bits
    st = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": m, "exp_avg_sq": v}},
          "param_groups": [{"params": [0]}]}
    packed = ckpt.pack_moments(st)
    assert packed["state"][0]["exp_avg"].shape[0] == 3
    back = ckpt.unpack_moments(packed)["state"][0]
    for k in ("exp_avg", "exp_avg_sq"):
        assert torch.equal(bits(back[k]), bits(st["state"][0][k])), k
    assert torch.equal(back["step"], torch.tensor(3.0))


class Payload:
    """What a tampered checkpoint could carry: code run at unpickling (here: make a file)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


@pytest.mark.slow
def test_checkpoint_that_needs_pickle_is_refused_and_runs_nothing(tiny_scene, tmp_path):
    run = tmp_path / "run"
    trainer(tiny_scene, run, 1).fit()
    ck = latest_checkpoint(run)
    st = torch.load(ck, weights_only=True)
    st["extra"] = Payload(tmp_path / "pwned")
    torch.save(st, ck)
    for load in (lambda: load_run(run), lambda: trainer(tiny_scene, run, 2, resume=True)):
        with pytest.raises(UserError, match="posix.mkdir, which no flamenerf checkpoint") as e:
            load()
        # a payload that calls os.mkdir is no old run to convert: `convert` is not offered
        assert "\n" not in str(e.value) and "flamenerf convert" not in str(e.value)
    assert not (tmp_path / "pwned").exists()


@pytest.mark.slow
def test_old_checkpoint_converts_on_request_and_resumes_exactly(tiny_scene, tmp_path):
    """A flamenerf 0.1 checkpoint (NumPy/Python RNG states pickled) is refused with the
    command that converts it; after `convert --trust` the run resumes as if never stopped."""
    import random

    import numpy as np

    from flamenerf.cli import main

    a = trainer(tiny_scene, tmp_path / "a", 4)
    a.fit()
    b = trainer(tiny_scene, tmp_path / "b", 4)
    b.fit(steps=2)
    ck = latest_checkpoint(tmp_path / "b")
    st = torch.load(ck, weights_only=True)
    ckpt.set_rng_states(st, torch.Generator())
    st["numpy_rng"], st["python_rng"] = np.random.get_state(), random.getstate()
    del st["format"]
    torch.save(st, ck)  # what flamenerf 0.1 wrote
    with pytest.raises(UserError, match="convert"):
        load_run(tmp_path / "b")
    assert main(["convert", str(tmp_path / "b")]) == 2  # --trust is required
    assert main(["convert", str(tmp_path / "b"), "--trust"]) == 0
    torch.load(ck, weights_only=True)
    b2 = trainer(tiny_scene, tmp_path / "b", 4, resume=True)
    b2.fit()
    assert same_params(a, b2)


# ----------------------------------------------------------------------------- Ctrl-C


@pytest.mark.slow
def test_ctrl_c_inside_a_step_resumes_bit_exactly(tiny_scene, tmp_path, monkeypatch):
    a = trainer(tiny_scene, tmp_path / "a", 6)
    a.fit()
    before = signal.getsignal(signal.SIGINT)
    b = trainer(tiny_scene, tmp_path / "b", 6)
    ctrl_c_at(b, monkeypatch, 2)
    res = b.fit()
    assert res.interrupted and res.step == 3
    assert signal.getsignal(signal.SIGINT) is before  # default handling is back
    assert latest_checkpoint(tmp_path / "b").name == "step-000000003.ckpt"
    b2 = trainer(tiny_scene, tmp_path / "b", 6, resume=True)
    assert b2.step == 3
    b2.fit()
    assert same_params(a, b2)


def fail_saves(monkeypatch, effect):
    """Make torch.save write some bytes, then `effect()` (a Ctrl-C, a full disk)."""
    real = torch.save

    def save(obj, f, *a, **k):
        f.write(b"partial")
        effect()
        f.seek(0)
        f.truncate()
        return real(obj, f, *a, **k)

    monkeypatch.setattr(torch, "save", save)


@pytest.mark.slow
def test_second_ctrl_c_during_the_save_still_saves(tiny_scene, tmp_path, monkeypatch):
    t = trainer(tiny_scene, tmp_path / "run", 6)
    ctrl_c_at(t, monkeypatch, 2)
    fail_saves(monkeypatch, lambda: signal.raise_signal(signal.SIGINT))
    res = t.fit()
    assert res.interrupted and res.step == 3
    monkeypatch.undo()
    assert load_run(tmp_path / "run").step == 3


@pytest.mark.slow
def test_third_ctrl_c_gives_up_the_save_and_keeps_the_last_checkpoint(tiny_scene, tmp_path,
                                                                     monkeypatch):
    t = trainer(tiny_scene, tmp_path / "run", 6, every=2)
    ctrl_c_at(t, monkeypatch, 2)
    t.fit(steps=2)  # the periodic checkpoint of step 2 (no Ctrl-C yet)
    t.cfg.train.steps = 6

    def two_presses():
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)

    fail_saves(monkeypatch, two_presses)
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(Interrupted, match="step-000000002.ckpt") as e:
        t.fit()
    assert "\n" not in str(e.value)
    assert signal.getsignal(signal.SIGINT) is before
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "run" / "checkpoints").iterdir()] == [
        "step-000000002.ckpt"]  # and no partial file beside it
    assert load_run(tmp_path / "run").step == 2


@pytest.mark.slow
def test_full_disk_at_the_final_save_is_one_line_and_keeps_the_last_checkpoint(
        tiny_scene, tmp_path, monkeypatch):
    t = trainer(tiny_scene, tmp_path / "run", 3, every=2)

    def full():
        if t.step == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    fail_saves(monkeypatch, full)
    with pytest.raises(UserError, match="No space left on device") as e:
        t.fit()
    assert "\n" not in str(e.value) and "step-000000002.ckpt" in str(e.value)
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "run" / "checkpoints").iterdir()] == [
        "step-000000002.ckpt"]
    assert load_run(tmp_path / "run").step == 2


@pytest.mark.slow
def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(tiny_scene, tmp_path,
                                                                 monkeypatch):
    t = trainer(tiny_scene, tmp_path / "run", 6, every=2)
    real = t.train_step

    def step():
        if t.step == 3:
            with torch.no_grad():
                t.model.field.grid.tables[0].fill_(float("nan"))
        return real()

    monkeypatch.setattr(t, "train_step", step)
    with pytest.raises(UserError, match="diverged") as e:
        t.fit()
    assert "\n" not in str(e.value) and "step-000000002.ckpt" in str(e.value)
    r = load_run(tmp_path / "run")
    assert r.step == 2
    assert all(torch.isfinite(v).all() for v in r.model.state_dict().values()
               if v.is_floating_point())


@pytest.mark.slow
def test_interrupted_train_exits_130_with_one_line(tiny_scene, tmp_path, monkeypatch, capsys):
    from flamenerf.cli import main

    real = Trainer.train_step

    def step(self):
        if self.step == 1:
            signal.raise_signal(signal.SIGINT)
        return real(self)

    monkeypatch.setattr(Trainer, "train_step", step)
    rc = main(["train", str(tiny_scene), "--out", str(tmp_path / "run"), "--steps", "5",
               "--batch-rays", "64"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 130
    assert err[-1].startswith("flamenerf: interrupted: run saved at step 2")
    assert "--resume" in err[-1]
    assert latest_checkpoint(tmp_path / "run").name == "step-000000002.ckpt"


# ----------------------------------------------------------------------------- leftovers


def test_stale_partial_checkpoints_are_removed_on_the_next_start(tiny_scene, tmp_path):
    run = tmp_path / "run"
    trainer(tiny_scene, run, 1).fit()
    ckdir = run / "checkpoints"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = [ckdir / f".step-000000002.ckpt.flamenerf-{dead}-abcd1234",
             ckdir / ".step-000000002.ckpt.k2j3h4g5",  # an older flamenerf's naming
             run / f".config.json.flamenerf-{dead}-zz_99xyz"]
    alive = ckdir / f".step-000000002.ckpt.flamenerf-{os.getppid()}-abcd1234"
    theirs = ckdir / ".notes"
    for p in [*stale, alive, theirs]:
        p.write_bytes(b"x")
    trainer(tiny_scene, run, 2, resume=True)
    assert not any(p.exists() for p in stale)
    assert alive.exists() and theirs.exists()


@pytest.mark.slow
def test_corrupt_latest_checkpoint_falls_back_to_the_previous(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    trainer(tiny_scene, run, 4, every=2).fit()
    assert [p.name for p in checkpoints(run)] == ["step-000000002.ckpt", "step-000000004.ckpt"]
    newest = checkpoints(run)[-1]
    newest.write_bytes(newest.read_bytes()[:100_000])  # a copy cut short
    assert load_run(run).step == 2
    err = capsys.readouterr().err
    assert "step-000000004.ckpt" in err and "step-000000002.ckpt" in err
    t = trainer(tiny_scene, run, 6, resume=True, every=2)
    assert t.step == 2
    t.fit()
    assert [p.name for p in checkpoints(run)] == ["step-000000004.ckpt", "step-000000006.ckpt"]
    assert load_run(run).step == 6


@pytest.mark.slow
def test_a_checkpoint_damaged_in_place_is_caught_by_its_checksums(tiny_scene, tmp_path,
                                                                   capsys):
    """Bytes changed inside a tensor (a disk or copy error; the file's length unchanged)
    loaded silently and rendered a smeared scene: the zip's CRCs catch it, and the run
    falls back to the checkpoint before."""
    run = tmp_path / "run"
    trainer(tiny_scene, run, 4, every=2).fit()
    newest = checkpoints(run)[-1]
    data = bytearray(newest.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 4096] = b"\xff" * 4096
    newest.write_bytes(bytes(data))
    with pytest.raises(UserError, match="checksum"):
        ckpt.load_checkpoint(newest)
    assert load_run(run).step == 2
    assert "step-000000004.ckpt" in capsys.readouterr().err
    # a byte of the zip's directory: zipfile cannot read it (an unknown compression
    # method); that is torch.load's to judge, never a traceback
    data = bytearray(checkpoints(run)[0].read_bytes())
    entry = data.rfind(b"PK\x01\x02")
    data[entry + 10] = 99
    checkpoints(run)[0].write_bytes(bytes(data))
    try:
        ckpt.load_checkpoint(checkpoints(run)[0])
    except UserError:
        pass


# ----------------------------------------------------------------------------- damaged runs


@pytest.mark.slow
def test_a_damaged_config_json_is_one_line_naming_it(tiny_scene, tmp_path):
    import json
    import shutil

    run = tmp_path / "run"
    trainer(tiny_scene, run, 2).fit()
    meta = json.loads((run / "config.json").read_text())
    bad = tmp_path / "bad"
    for edit, msg in ((lambda m: [], "no 'config' object"),
                      (lambda m: {**m, "dataset": None}, "'dataset' missing"),
                      (lambda m: {**m, "config": {**m["config"], "model": None}},
                       "model must be an object, got null"),
                      (lambda m: {**m, "config": {**m["config"], "train": {
                          **m["config"]["train"], "downscale": 0}}},
                       "train.downscale must be a positive number, got 0")):
        shutil.rmtree(bad, ignore_errors=True)
        shutil.copytree(run, bad)
        (bad / "config.json").write_text(json.dumps(edit(meta)))
        with pytest.raises(UserError, match=f"bad/config.json: .*{msg}"):
            load_run(bad)
        with pytest.raises(UserError, match=f"bad/config.json: .*{msg}"):
            trainer(tiny_scene, bad, 3, resume=True)


def test_a_run_whose_dataset_moved_says_how_to_give_it(toy_run, toy_dataset, tmp_path):
    r = load_run(toy_run)
    r.meta["dataset"] = str(tmp_path / "moved_away")
    with pytest.raises(UserError, match="moved_away: the dataset this run was trained on is "
                                        "not there .* --dataset PATH"):
        r.dataset()
    assert r.dataset(toy_dataset).root == toy_dataset  # given where it is now


@pytest.mark.slow
def test_a_checkpoint_of_another_run_is_refused(tiny_scene, toy_dataset, tmp_path):
    run, other = tmp_path / "run", tmp_path / "other"
    trainer(tiny_scene, run, 2).fit()
    trainer(toy_dataset, other, 2).fit()  # another dataset: other frame and mesh counts
    stray = checkpoints(other)[-1]
    (run / "checkpoints" / "step-000000009.ckpt").write_bytes(stray.read_bytes())
    with pytest.raises(UserError, match="step-000000009.ckpt: not this run's checkpoint"):
        load_run(run)


def test_resume_with_another_dataset_is_refused(tiny_scene, toy_dataset, tmp_path):
    run = tmp_path / "run"
    trainer(tiny_scene, run, 2).fit()
    with pytest.raises(UserError, match="not the dataset .* was trained on .*--other-dataset"):
        trainer(toy_dataset, run, 3, resume=True)
    assert trainer(tiny_scene, run, 3, resume=True).step == 2
