"""What a user can rely on when the machine or another process gets in the way: an output
is never reported as written unless it was read back whole (a full disk stood in for by a
file-size limit on a subprocess), a run folder has one writer at a time (its lock, with two
processes), a damaged checkpoint never takes a good one's place, and a resume continues the
run it names on the dataset it was trained on (docs/reliability.md)."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from toy import make_toy_dataset, toy_config

from flamenerf.cli import main
from flamenerf.errors import UserError
from flamenerf.io import NotWritten, atomic_write_bytes, read_json, save_png
from flamenerf.lock import LOCK_NAME, folder_lock
from flamenerf.training.checkpoint import checkpoints, load_checkpoint
from flamenerf.training.run import load_run
from flamenerf.training.trainer import Trainer, train

SRC = Path(__file__).resolve().parents[1] / "src"


def limited(limit_bytes: int, *args, timeout: float = 240) -> subprocess.CompletedProcess:
    """`flamenerf ARGS` in a subprocess that may write no file larger than `limit_bytes`
    (RLIMIT_FSIZE: what a full disk does to a writer, without filling one)."""
    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    env = {**os.environ, "PYTHONPATH": str(SRC), "MPLCONFIGDIR": os.environ.get(
        "MPLCONFIGDIR", "/tmp")}
    return subprocess.run([sys.executable, "-m", "flamenerf.cli", *map(str, args),
                           "--threads", "1"], preexec_fn=cap, capture_output=True, text=True,
                          timeout=timeout, env=env)


def error_line(stderr: str, *words: str) -> str:
    """The one `flamenerf: error:` line of `stderr`, with no traceback anywhere."""
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
    lines = [ln for ln in stderr.splitlines() if ln.startswith("flamenerf: error:")]
    assert len(lines) == 1, stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def no_temporaries(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if ".flamenerf-" in p.name]
    assert not left, left


@pytest.fixture
def run_copy(toy_run, tmp_path) -> Path:
    """A copy of the shared toy run that a test may change."""
    return Path(shutil.copytree(toy_run, tmp_path / "run"))


def cfg(steps: int, every: int = 10_000):
    c = toy_config("masked", steps)
    c.train.checkpoint_every = every
    return c


# ----------------------------------------------------------------------------- outputs


@pytest.mark.slow
def test_a_video_cut_short_by_a_full_disk_is_an_error_and_not_left(toy_run, tmp_path):
    out = tmp_path / "efbig.mp4"
    r = limited(1024, "render", toy_run, "--out", out, "--frames", "8")
    assert r.returncode != 0, r.stdout
    error_line(r.stderr, str(out), "not written")
    assert "wrote" not in r.stdout
    assert not out.exists()
    no_temporaries(tmp_path)


@pytest.mark.slow
def test_a_video_written_whole_is_reported(toy_run, tmp_path):
    from flamenerf.data.video import check_video, read_frames

    out = tmp_path / "ok.mp4"
    r = limited(50_000_000, "render", toy_run, "--out", out, "--frames", "8")
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stdout
    assert len(read_frames(out)) == 8 and check_video(out, 8) is None
    assert check_video(out, 9) == "it holds 8 of the 9 frames written"


@pytest.mark.slow
def test_a_checkpoint_save_cut_short_is_one_line(toy_dataset, tmp_path):
    run = tmp_path / "run"
    r = limited(2_000_000, "train", toy_dataset, "--out", run, "--steps", "1")
    assert r.returncode != 0
    error_line(r.stderr, "step-000000001.ckpt", "could not save the checkpoint",
               "no earlier checkpoint")
    assert not list((run / "checkpoints").glob("*")) if (run / "checkpoints").exists() else True


@pytest.mark.slow
def test_eval_cut_short_names_the_file_and_leaves_no_empty_folder(toy_run, tmp_path):
    out = tmp_path / "ev"
    r = limited(1024, "eval", toy_run, "--out", out, "--fit-steps", "2", "--no-control",
                "--images", "1")
    assert r.returncode != 0
    line = error_line(r.stderr, str(out))
    assert "File too large" in line or "not written" in line
    assert not out.exists()


def test_an_output_that_does_not_read_back_gets_no_name(tmp_path):
    target = tmp_path / "x.json"
    target.write_text("old")
    with pytest.raises(NotWritten) as e:
        atomic_write_bytes(target, lambda f: f.write(b"new"), lambda tmp: "it is wrong")
    assert e.value.filename == str(target) and "not written" in e.value.strerror
    assert target.read_text() == "old"
    no_temporaries(tmp_path)
    save_png(tmp_path / "a.png", [[0.0, 1.0]])  # written, read back, named
    assert (tmp_path / "a.png").stat().st_size > 0


# ----------------------------------------------------------------------------- checkpoints


@pytest.mark.slow
def test_pruning_never_keeps_a_damaged_checkpoint_in_place_of_a_good_one(toy_dataset,
                                                                         tmp_path, capsys):
    """A run of 4 steps, checkpoints at 3 and 4; 4 cut to half: the resume falls back to 3,
    and its next save (step 5) used to keep the broken 4 and delete 3, by step number."""
    run = tmp_path / "run"
    train(toy_dataset, run, cfg(4, every=3), device="cpu", quiet=True)
    assert [p.name for p in checkpoints(run)] == ["step-000000003.ckpt", "step-000000004.ckpt"]
    broken = checkpoints(run)[-1]
    with open(broken, "r+b") as f:
        f.truncate(broken.stat().st_size // 2)
    train(toy_dataset, run, cfg(4, every=3), resume=True, device="cpu", quiet=True, steps=5)
    kept = checkpoints(run)
    assert [p.name for p in kept] == ["step-000000003.ckpt", "step-000000005.ckpt"]
    for p in kept:
        load_checkpoint(p)
    assert "removed 1 damaged checkpoint" in capsys.readouterr().err


# ----------------------------------------------------------------------------- one writer


HOLD = ("import sys, time\nfrom flamenerf.lock import folder_lock\n"
        "with folder_lock(sys.argv[1], 'run'):\n    print('held', flush=True)\n"
        "    time.sleep(120)\n")


def hold_lock(folder: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE,
                         text=True, env={**os.environ, "PYTHONPATH": str(SRC)})
    assert p.stdout.readline().strip() == "held"
    return p


def test_a_second_training_into_a_run_folder_is_refused(toy_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    holder = hold_lock(run)
    try:
        for args in ([], ["--resume"]):
            rc = main(["train", str(toy_dataset), "--out", str(run), "--steps", "1", *args])
            err = capsys.readouterr().err
            assert rc == 2
            error_line(err, str(run), f"being written by process {holder.pid}")
        assert sorted(p.name for p in run.iterdir()) == [LOCK_NAME]  # nothing else written
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_left_by_a_killed_process_is_taken_over_with_a_note(toy_dataset, tmp_path,
                                                                   capsys):
    run = tmp_path / "run"
    holder = hold_lock(run)
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert (run / LOCK_NAME).exists()  # a kill -9 leaves the file; the kernel drops the lock
    train(toy_dataset, run, cfg(1), device="cpu", quiet=True)
    err = capsys.readouterr().err
    assert f"took over the lock of process {holder.pid}" in err
    assert not (run / LOCK_NAME).exists()  # released when the training ended
    assert load_run(run).step == 1


def test_an_evaluation_folder_has_one_writer(tmp_path):
    out = tmp_path / "eval"
    holder = hold_lock(out)
    try:
        with pytest.raises(UserError, match="being written by process"):
            with folder_lock(out, "evaluation"):
                pass
    finally:
        holder.kill()
        holder.wait()
    with folder_lock(out, "evaluation"):
        assert (out / LOCK_NAME).exists()
    assert not (out / LOCK_NAME).exists()


# ----------------------------------------------------------------------------- resume


def own_dataset(tmp_path: Path, name: str = "dataset") -> Path:
    return make_toy_dataset(tmp_path / name)


@pytest.mark.slow
def test_resume_refuses_a_dataset_made_again_at_the_same_place(tmp_path, capsys):
    ds, run = own_dataset(tmp_path), tmp_path / "run"
    train(ds, run, cfg(2), device="cpu", quiet=True)
    meta = json.loads((ds / "transforms.json").read_text())
    meta["near"] = meta.get("near", 0.5) * 0.9  # the same place, other content
    (ds / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="not the dataset .* was trained on"):
        train(ds, run, cfg(2), resume=True, device="cpu", quiet=True, steps=3)
    res = train(ds, run, cfg(2), resume=True, device="cpu", quiet=True, steps=3,
                other_dataset=True)
    assert res.step == 3 and "resuming on it as asked" in capsys.readouterr().err


@pytest.mark.slow
def test_resume_takes_a_moved_dataset_and_refuses_another_once_it_is_gone(tmp_path):
    ds, run = own_dataset(tmp_path), tmp_path / "run"
    train(ds, run, cfg(2), device="cpu", quiet=True)
    moved = Path(shutil.move(ds, tmp_path / "moved"))
    other = own_dataset(tmp_path, "other")
    meta = json.loads((other / "transforms.json").read_text())
    meta["far"] = meta.get("far", 1.6) * 1.1
    (other / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="not the dataset"):
        train(other, run, cfg(2), resume=True, device="cpu", quiet=True, steps=3)
    assert read_json(run / "config.json")["dataset"] == str(ds.resolve())  # not rewritten
    assert train(moved, run, cfg(2), resume=True, device="cpu", quiet=True, steps=3).step == 3
    assert read_json(run / "config.json")["dataset"] == str(moved.resolve())


@pytest.mark.slow
def test_resume_of_a_run_without_checkpoint_keeps_its_saved_settings(toy_dataset, tmp_path,
                                                                     capsys):
    run = tmp_path / "run"
    train(toy_dataset, run, cfg(6), device="cpu", quiet=True)
    shutil.rmtree(run / "checkpoints")  # stopped before its first checkpoint
    from flamenerf.config import preset

    t = Trainer(preset("fast"), toy_dataset, run, resume=True, device="cpu")
    assert t.cfg.train.steps == 6 and t.cfg.model.field.hash_log2_size == 10
    assert t.step == 0
    assert "starting it again from step 0 with its saved settings" in capsys.readouterr().out


def test_train_refuses_a_folder_that_holds_other_things(toy_dataset, tmp_path, capsys):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "todo.txt").write_text("mine")
    rc = main(["train", str(toy_dataset), "--out", str(out), "--steps", "1"])
    assert rc == 2
    error_line(capsys.readouterr().err, str(out), "not a run", "todo.txt")
    assert sorted(p.name for p in out.iterdir()) == ["todo.txt"]


# ----------------------------------------------------------------------------- bad files


def deep(n: int = 200_000) -> str:
    return "[" * n + "]" * n


def test_deeply_nested_json_is_one_line(run_copy, tmp_path, capsys):
    expr = tmp_path / "e.json"
    expr.write_text(deep())
    rc = main(["render", str(run_copy), "--expressions", str(expr), "--out",
               str(tmp_path / "v.mp4")])
    assert rc == 2
    error_line(capsys.readouterr().err, "e.json", "nested too deeply")
    (run_copy / "config.json").write_text(deep())
    with pytest.raises(UserError, match="config.json: not valid JSON here"):
        load_run(run_copy)
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.dataset_checks import DatasetError

    ds = own_dataset(tmp_path)
    (ds / "transforms.json").write_text(deep())
    with pytest.raises(DatasetError, match="transforms.json: not valid JSON here"):
        load_dataset(ds)


def test_an_unknown_preset_in_config_json_is_refused(run_copy):
    where = run_copy / "config.json"
    meta = json.loads(where.read_text())
    meta["preset"] = meta["config"]["preset"] = "turbo"
    where.write_text(json.dumps(meta))
    with pytest.raises(UserError, match="preset 'turbo' is not one of"):
        load_run(run_copy)
    meta["preset"] = "fast"  # the config's own label alone
    where.write_text(json.dumps(meta))
    with pytest.raises(UserError, match="preset \"turbo\" is not one of"):
        load_run(run_copy)


def test_a_folder_given_as_the_expression_file_is_named_as_a_folder(toy_run, tmp_path,
                                                                     capsys):
    (tmp_path / "moves.json").mkdir()
    rc = main(["render", str(toy_run), "--expressions", str(tmp_path / "moves.json"),
               "--out", str(tmp_path / "v.mp4")])
    assert rc == 2
    error_line(capsys.readouterr().err, "moves.json: is a folder")


def test_a_video_cut_short_with_its_index_in_front_is_said(tmp_path, capsys):
    import imageio_ffmpeg

    from flamenerf.data.video import probe_video

    whole = tmp_path / "whole.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-y", "-f", "lavfi", "-i",
                    "testsrc=size=64x64:rate=30,noise=alls=60:allf=t", "-frames:v", "78",
                    "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(whole)], check=True)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 5])
    assert probe_video(whole).num_frames == 78
    assert "cut short" not in capsys.readouterr().err
    info = probe_video(cut)
    assert 0 < info.num_frames < 78
    err = capsys.readouterr().err
    assert "cut.mp4: the file is cut short" in err and f"first {info.num_frames} frames" in err
    assert "of the 2.6 s its header gives" in err


def test_a_lock_holder_is_described_by_what_it_runs(tmp_path):
    out = tmp_path / "r"
    holder = hold_lock(out)
    try:
        info = json.loads((out / LOCK_NAME).read_text())
        assert info["pid"] == holder.pid and info["started"] <= time.time()
    finally:
        holder.kill()
        holder.wait()
