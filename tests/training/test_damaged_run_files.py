"""A run's files edited or damaged so that they still parse (a valid archive, valid JSON)
but hold the wrong things: one line naming the file, never a traceback, and a checkpoint
refused so falls back to the one before (docs/reliability.md)."""

import datetime
import json
import shutil

import pytest
import torch

from flamenerf.cli import main
from flamenerf.config import Config
from flamenerf.errors import UserError
from flamenerf.training import checkpoint as ckpt
from flamenerf.training.checkpoint import checkpoints, load_checkpoint
from flamenerf.training.run import load_run
from flamenerf.training.trainer import Trainer


@pytest.fixture
def run(toy_run, tmp_path):
    """A copy of the toy run with two checkpoints: step-1 (a copy of step-2's) and step-2."""
    out = tmp_path / "run"
    shutil.copytree(toy_run, out)
    newest = checkpoints(out)[-1]
    assert newest.name == "step-000000002.ckpt"
    shutil.copy(newest, newest.with_name("step-000000001.ckpt"))
    return out


def rewrite(path, edit):
    """Save the checkpoint at `path` again with `edit(state)` applied: a valid archive whose
    checksums pass."""
    st = torch.load(path, weights_only=True)
    edit(st)
    torch.save(st, path)


def single_line(e):
    assert "\n" not in str(e.value), str(e.value)
    return str(e.value)


def setter(key, value):
    return lambda st: st.__setitem__(key, value)


def rng_setter(key, part, value):
    return lambda st: st[key].__setitem__(part, value)


DAMAGE = {
    "model_args": setter("model_args", "x"),
    "model": setter("model", [1, 2]),
    "step": setter("step", "ten"),
    "negative step": setter("step", -3),
    "format": setter("format", 1),
    "generator": setter("generator", torch.zeros(10, dtype=torch.uint8)),
    "torch_rng": setter("torch_rng", torch.zeros(5056, dtype=torch.int64)),
    "numpy keys": rng_setter("numpy_rng", "keys", torch.zeros(5, dtype=torch.int64)),
    "python state": rng_setter("python_rng", "state", torch.zeros(7, dtype=torch.int64)),
    "optimizer": setter("optimizer", "x"),
    "shard_generators": setter("shard_generators", [torch.zeros(3, dtype=torch.uint8)]),
    "a NaN weight": lambda st: next(t for t in st["model"].values()
                                    if t.is_floating_point()).view(-1).__setitem__(0, float("nan")),
    "an inf weight": lambda st: [t for t in st["model"].values()
                                 if t.is_floating_point()][-1].view(-1).__setitem__(0, float("inf")),
}


# ----------------------------------------------------------------------------- checkpoints


@pytest.mark.parametrize("what", list(DAMAGE))
def test_a_checkpoint_field_of_the_wrong_kind_falls_back_to_the_one_before(what, run, capsys):
    newest = checkpoints(run)[-1]
    rewrite(newest, DAMAGE[what])
    with pytest.raises(UserError, match="step-000000002.ckpt: not a readable checkpoint") as e:
        load_checkpoint(newest)
    single_line(e)
    assert load_run(run, device="cpu").step == 2  # from step-1, a copy of step-2
    err = capsys.readouterr().err
    assert "step-000000002.ckpt" in err and "using step-000000001.ckpt instead" in err


def test_the_only_checkpoint_damaged_is_one_line_naming_it(toy_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(toy_run, run)
    rewrite(checkpoints(run)[-1], DAMAGE["model_args"])
    with pytest.raises(UserError, match=r"step-000000002\.ckpt: .*'model_args' is not a dict"
                       ) as e:
        load_run(run, device="cpu")
    single_line(e)


def test_a_newer_format_is_named_and_never_skipped(run):
    """A newer version's checkpoint is not passed over for an older one: a resume would
    train from the older step and then overwrite the newer file."""
    rewrite(checkpoints(run)[-1], setter("format", 99))
    with pytest.raises(UserError, match="checkpoint format 99 is newer than this flamenerf "
                                        "reads"):
        load_run(run, device="cpu")


def test_an_unreadable_checkpoint_is_named_in_full(run, monkeypatch):
    """The message was cut at the first '.', inside the file's name."""
    newest = checkpoints(run)[-1]

    def denied(path, *a, **k):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(torch, "load", denied)  # chmod 000 does not stop root
    with pytest.raises(UserError) as e:
        load_checkpoint(newest)
    assert single_line(e) == (f"{newest}: not a readable checkpoint (PermissionError: "
                              "Permission denied)")


def test_rng_states_the_generators_refuse_are_one_line(run):
    path = checkpoints(run)[-1]
    st = load_checkpoint(path)
    st["generator"] = torch.zeros(3, dtype=torch.uint8)
    with pytest.raises(UserError, match=f"{path}: .*random-number state") as e:
        ckpt.set_rng_states(st, torch.Generator(), path)
    single_line(e)


def test_resume_with_a_python_rng_state_out_of_range_is_one_line(run, toy_dataset):
    """Shapes right (load_checkpoint passes it), a value wrong: random.setstate refuses."""
    def edit(st):
        st["python_rng"]["state"][-1] = 999  # the position: at most 624

    for p in checkpoints(run):
        rewrite(p, edit)
    with pytest.raises(UserError, match="step-000000002.ckpt: .*random-number state") as e:
        Trainer(Config(), toy_dataset, run, resume=True, quiet=True, steps=3, device="cpu")
    single_line(e)


def test_a_model_state_that_is_no_dict_is_one_line(toy_run):
    model = load_run(toy_run, device="cpu").model
    with pytest.raises(UserError, match="x.ckpt: checkpoint does not fit") as e:
        ckpt.load_model_state(model, [1, 2], "x.ckpt")
    single_line(e)


def test_convert_of_a_checkpoint_already_converted_but_needing_pickle_is_one_line(
        run, capsys):
    """Safe RNG states (dicts) and something else that needs pickle: no flamenerf
    checkpoint needs it, so `convert --trust` is not offered, and refused in one line."""
    newest = checkpoints(run)[-1]
    rewrite(newest, setter("extra", datetime.date(2020, 1, 1)))
    with pytest.raises(UserError, match="datetime.date, which no flamenerf checkpoint") as e:
        load_checkpoint(newest)
    assert "flamenerf convert" not in str(e.value)
    assert main(["convert", str(run), "--trust"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "step-000000002.ckpt: not loaded" in err and "not a flamenerf checkpoint" in err


# ----------------------------------------------------------------------------- config.json


def edit_config(run, edit):
    where = run / "config.json"
    meta = json.loads(where.read_text())
    edit(meta)
    where.write_text(json.dumps(meta))


def set_key(dotted, value):
    def edit(meta):
        *parents, last = dotted.split(".")
        d = meta
        for p in parents:
            d = d[p]
        d[last] = value
    return edit


@pytest.mark.parametrize("key, value, words", [
    ("config.train.steps", "ten", 'train.steps must be an int, got "ten"'),
    ("config.model.expression_scale", "1", 'model.expression_scale must be a number, got "1"'),
    ("config.model.mesh_guide.neighbours", 0, "model.mesh_guide.neighbours must be at least 1"),
    ("config.model.sampler.num_proposal", -4, "model.sampler.num_proposal must be at least 1"),
    ("config.model.sampler.num_proposal", "x", 'num_proposal must be an int, got "x"'),
    ("config.model.expression_mode", "weird", 'model.expression_mode must be one of "masked"'),
    ("config.model.warp", "x", 'model.warp must be an object, got "x"'),
    ("config.model.field.kind", "banana", 'model.field.kind must be one of "mlp", "hash"'),
    ("config.model.warp.skips", [1, "a"], "model.warp.skips[1] must be an int"),
    ("config.model.mesh_guide.enabled", 1, "mesh_guide.enabled must be true or false or null"),
    ("config.train.lr", float("nan"), "train.lr must be a finite number"),
    ("expression_names", ["a", 3], "'expression_names' missing or not a list of strings"),
    ("dataset", "", "'dataset' missing or not a path"),
])
def test_a_wrong_value_in_config_json_names_the_file_and_the_key(key, value, words, run,
                                                                 toy_dataset):
    edit_config(run, set_key(key, value))
    for load in (lambda: load_run(run, device="cpu"),
                 lambda: Trainer(Config(), toy_dataset, run, resume=True, quiet=True,
                                 device="cpu")):
        with pytest.raises(UserError) as e:
            load()
        msg = single_line(e)
        assert msg.startswith(f"{run / 'config.json'}: ") and words in msg, msg


def test_a_wrong_value_in_config_json_is_one_line_through_the_cli(run, capsys):
    edit_config(run, set_key("config.model.sampler.num_proposal", -4))
    assert main(["eval", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [f"flamenerf: error: {run / 'config.json'}: "
                                "model.sampler.num_proposal must be at least 1, got -4"], err
