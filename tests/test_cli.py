"""The command line's argument errors: a message naming the problem and a non-zero exit,
never a traceback."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from flamenerf.cli import main


def _run(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, FLAMENERF_NO_REEXEC="1", COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "flamenerf.cli", *args], capture_output=True,
                          text=True, env=env, timeout=120)


def test_missing_dataset_is_one_error_line(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nope"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"flamenerf: error: {tmp_path / 'nope'}: dataset directory does not exist"]
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_bad_preset_name_is_refused_with_the_choices(tmp_path):
    r = _run("train", str(tmp_path), "--preset", "nope")
    assert r.returncode != 0
    assert "nope" in r.stderr and "fast" in r.stderr and "flame-in-nerf" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("args", [["render"], ["preprocess", "only-one.mp4"],
                                  ["bench", "--steps", "many"]])
@pytest.mark.slow
def test_malformed_arguments_exit_non_zero_without_a_traceback(args):
    r = _run(*args)
    assert r.returncode != 0 and "Traceback" not in r.stderr


@pytest.mark.parametrize("args, line", [
    (["render", "R", "--sizee", "32"], "--sizee: not an option of `flamenerf render`; did you "
                                       "mean '--size'?"),
    (["train", "D", "--max-steps=1"], "--max-steps: not an option of `flamenerf train`"),
    (["rendr", "R"], "'rendr' is not a command; did you mean 'render'?")])
def test_an_unknown_option_or_command_is_one_line_with_this_commands_nearest(args, line,
                                                                            capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("flamenerf: error: " + line) and err.count("\n") == 1
    assert main(["render", "no-such-run", "--side_by_side"]) == 2  # tyro's own spelling
    assert "not an option" not in capsys.readouterr().err


def test_fast_on_a_gpu_suggests_fast_gpu(tmp_path, capsys, monkeypatch, toy_dataset):
    """`fast` on a machine with CUDA points to `fast-gpu` (once, before training); with
    --device cpu, another preset or its own batch size, it does not."""
    from types import SimpleNamespace

    from flamenerf.commands import train as train_cmd
    from flamenerf.training import trainer

    monkeypatch.setattr(train_cmd, "_has_cuda", lambda: True)
    monkeypatch.setattr(trainer, "train", lambda *a, **k: SimpleNamespace(
        interrupted=False, step=0, seconds=0.0, run_dir=tmp_path / "run"))
    cases = [([], True), (["--device", "cpu"], False), (["--preset", "demo"], False),
             (["--batch-rays", "8192"], False)]
    for extra, noted in cases:
        assert main(["train", str(toy_dataset), "--out", str(tmp_path / "run"), *extra]) == 0
        assert ("--preset fast-gpu" in capsys.readouterr().out) == noted, extra


@pytest.mark.slow
def test_top_level_help_lists_each_command_on_a_line_or_two():
    """`flamenerf --help` is a short index (tyro's printed every whole docstring, ~220
    lines); a command's own --help keeps its whole text."""
    from flamenerf.cli import COMMANDS

    r = _run("--help")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) < 40
    listed = [line.split()[0] for line in lines if line.startswith("  ") and line[2] != " "]
    assert listed == COMMANDS
    r = _run("demo", "--help")
    assert r.returncode == 0 and "OUT/expressions.mp4" in r.stdout


def test_version(capsys):
    from flamenerf import __version__

    assert main(["--version"]) == 0 and capsys.readouterr().out == f"flamenerf {__version__}\n"


def test_help_text_is_reflowed_where_tyro_would_break_mid_sentence():
    """tyro keeps a function parameter's docstring line breaks and breaks a description
    before a line that starts with a non-letter: each paragraph and `Args:` entry is one
    line, lists keep theirs."""
    import docstring_parser

    from flamenerf.cli import available_commands, reflowed

    doc = """Title.

    A paragraph that goes on
    (and on) here.

    - a list
    - kept

    Args:
        steps: Steps of the fit (default: 2000; 300 on
            CPU).
        lr: Rate.
    """
    out = reflowed(doc)
    assert "A paragraph that goes on (and on) here." in out
    assert "- a list\n- kept" in out
    params = {p.arg_name: p.description for p in docstring_parser.parse(out).params}
    assert params == {"steps": "Steps of the fit (default: 2000; 300 on CPU).", "lr": "Rate."}
    ev = available_commands()["eval"]
    assert all("\n" not in p.description for p in docstring_parser.parse(ev.__doc__).params)
