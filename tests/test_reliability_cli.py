"""One line, naming the file, for every bad input or unusable output; `--overwrite` replaces
only what flamenerf wrote (docs/reliability.md). In-process through `cli.main`, so that a
traceback fails the test as an exception."""

import errno
import json
import os
import shutil
import subprocess
import sys

import pytest

from flamenerf.cli import main
from flamenerf.data.dataset import load_dataset
from flamenerf.data.dataset_checks import DatasetError


def run_cli(capsys, *args):
    rc = main([str(a) for a in args])
    err = capsys.readouterr().err.strip()
    return rc, err


def one_line(err, *words):
    lines = [ln for ln in err.splitlines() if ln.startswith("flamenerf: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


# ----------------------------------------------------------------------------- train


@pytest.mark.parametrize("args, words", [
    (["--out", "/proc/x"], ["/proc/x", "cannot write"]),
    (["--out", "{tmp}/afile"], ["afile", "is a file"]),
    (["--batch-rays", "0"], ["--batch-rays 0", "at least 1"]),
    (["--batch-rays", "-3"], ["--batch-rays -3"]),
    (["--steps", "-5"], ["--steps -5", "at least 1"]),
    (["--device", "cuda"], ["--device cuda", "CUDA is not available"]),
    (["--device", "banana"], ["--device banana"]),
])
def test_train_bad_option_or_output_is_one_line(args, words, toy_dataset, tmp_path, capsys,
                                                monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    (tmp_path / "afile").write_text("mine")
    args = [a.format(tmp=tmp_path) for a in args]
    if "--out" not in args:
        args += ["--out", str(tmp_path / "run")]
    rc, err = run_cli(capsys, "train", toy_dataset, *args)
    assert rc == 2
    one_line(err, "flamenerf: error:", *words)
    assert (tmp_path / "afile").read_text() == "mine"
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_train_that_fails_to_start_leaves_no_empty_output(toy_dataset, tmp_path, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(toy_dataset, ds)
    image = sorted((ds / "images").iterdir())[0]
    image.write_bytes(image.read_bytes()[:40])  # read when the frames load, after the check
    (tmp_path / "kept").mkdir()
    for out in (tmp_path / "new" / "run", tmp_path / "kept"):
        rc, err = run_cli(capsys, "train", ds, "--out", out)
        assert rc == 2
        one_line(err, image.name, "not a readable image")
    assert not (tmp_path / "new").exists()  # made by the command: removed with its parent
    assert (tmp_path / "kept").is_dir()  # the user's own (empty) folder stays


# ----------------------------------------------------------------------------- datasets


def edited(toy_dataset, tmp_path, edit):
    ds = tmp_path / "ds"
    shutil.copytree(toy_dataset, ds)
    meta = json.loads((ds / "transforms.json").read_text())
    edit(meta)
    (ds / "transforms.json").write_text(json.dumps(meta))
    return ds


def _set(key, value):
    return lambda m: m.__setitem__(key, value)


def _frame0(key, value):
    return lambda m: m["frames"][0].__setitem__(key, value)


@pytest.mark.parametrize("edit, words", [
    (_set("w", 0), ["w=0", "positive"]),
    (_set("h", -2), ["h=-2", "positive"]),
    (_set("fl_x", 0), ["fl_x=0", "positive"]),
    (_frame0("transform_matrix", [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     ["frames[0]", "transform_matrix", "4x4"]),
    (_frame0("transform_matrix", [["1", 0, 0, 0]] * 4), ["frames[0]", "transform_matrix"]),
    (_frame0("expression", ["x"] * 14), ["frames[0]", "expression", "numbers"]),
    (_frame0("expression", [[0.0, 1.0], [0.0]]), ["frames[0]", "expression", "numbers"]),
    (lambda m: m["expression_model"].__setitem__("dim", 5), ["dim 5 but 3 names"]),
    # finite but absurd: 1e30 trained on garbage, 1e308 overflowed into a traceback
    (_set("far", 1e308), ["far=1e+308", "metres"]),
    (_set("fl_x", 1e308), ["fl_x=1e+308", "times the image size"]),
    (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, 1e30),
     ["frames[0]", "transform_matrix", "1e+30 m"]),
    (lambda m: m["frames"][0]["expression"].__setitem__(0, 1e308),
     ["frames[0]", "expression holds 1e+308"]),
    (lambda m: m["frames"][0].__setitem__(
        "head_pose", [[1, 0, 0, 0], [0, 1, 0, -3e4], [0, 0, 1, 0], [0, 0, 0, 1]]),
     ["frames[0]", "head_pose", "3e+04 m"]),
])
def test_bad_numbers_in_transforms_json_are_one_line(edit, words, toy_dataset, tmp_path):
    ds = edited(toy_dataset, tmp_path, edit)
    with pytest.raises(DatasetError) as e:
        load_dataset(ds)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(ds / "transforms.json"))
    for w in words:
        assert w in msg, (w, msg)


def test_zero_width_through_the_cli(toy_dataset, tmp_path, capsys):
    ds = edited(toy_dataset, tmp_path, _set("w", 0))
    rc, err = run_cli(capsys, "train", ds, "--out", tmp_path / "run", "--size", "8")
    assert rc == 2
    one_line(err, "transforms.json", "w=0")


# ----------------------------------------------------------------------------- eval / render


@pytest.mark.parametrize("command", ["eval", "render", "view"])
def test_a_file_given_as_the_run_is_named_as_a_file(command, toy_run, capsys):
    rc, err = run_cli(capsys, command, toy_run / "config.json")
    assert rc == 2
    one_line(err, "config.json: is a file", "run directory")


def test_eval_output_that_is_a_file_fails_before_the_fit(toy_run, tmp_path, capsys,
                                                        monkeypatch):
    import flamenerf.evaluation.protocol as protocol

    monkeypatch.setattr(protocol, "evaluate_run", lambda *a, **k: pytest.fail("evaluated"))
    (tmp_path / "afile").write_text("mine")
    rc, err = run_cli(capsys, "eval", toy_run, "--out", tmp_path / "afile")
    assert rc == 2
    one_line(err, "afile: is a file")


@pytest.mark.parametrize("out, words", [("/proc/x/v.mp4", ["/proc/x", "cannot write"]),
                                        ("{tmp}/afile/v.mp4", ["afile", "is a file"])])
def test_render_checks_the_output_folder_before_rendering(out, words, toy_run, tmp_path,
                                                          capsys, monkeypatch):
    import flamenerf.rendering.reanimate as reanimate

    monkeypatch.setattr(reanimate, "render_sequence", lambda *a, **k: pytest.fail("rendered"))
    (tmp_path / "afile").write_text("mine")
    rc, err = run_cli(capsys, "render", toy_run, "--out", out.format(tmp=tmp_path),
                      "--frames", "2")
    assert rc == 2
    one_line(err, *words)


# ----------------------------------------------------------------------------- synth


SYNTH = ["--size", "16", "--frames", "2", "--reanimate", "0", "--leakage-steps", "0",
         "--workers", "1"]


def test_overwrite_refuses_a_folder_flamenerf_did_not_write(tmp_path, capsys):
    mine = tmp_path / "important"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    rc, err = run_cli(capsys, "synth", mine, *SYNTH, "--overwrite")
    assert rc == 2
    one_line(err, str(mine), "not a dataset made by flamenerf")
    assert (mine / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["important"]  # no leftovers


def test_overwrite_replaces_our_dataset_but_not_files_added_to_it(tmp_path, capsys):
    ds = tmp_path / "sk"
    assert run_cli(capsys, "synth", ds, *SYNTH)[0] == 0
    (ds / "transforms.json").write_text((ds / "transforms.json").read_text() + " ")
    assert run_cli(capsys, "synth", ds, *SYNTH, "--overwrite")[0] == 0
    assert load_dataset(ds).intrinsics.w == 16
    assert not (ds / "transforms.json").read_text().endswith(" ")  # replaced
    (ds / "notes.txt").write_text("mine")
    rc, err = run_cli(capsys, "synth", ds, *SYNTH, "--overwrite")
    assert rc == 2
    one_line(err, "notes.txt", "did not write")
    assert (ds / "notes.txt").exists()


def test_overwrite_refuses_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("mine")
    rc, err = run_cli(capsys, "synth", tmp_path / "afile", *SYNTH, "--overwrite")
    assert rc == 2
    one_line(err, "afile", "not a folder")
    assert (tmp_path / "afile").read_text() == "mine"


def test_run_folder_with_foreign_files_is_not_replaceable(toy_run, tmp_path):
    from flamenerf.errors import UserError
    from flamenerf.outdir import check_replaceable

    check_replaceable(toy_run, "run")  # ours: fine
    run = tmp_path / "run"
    shutil.copytree(toy_run, run)
    (run / "thesis.tex").write_text("mine")
    with pytest.raises(UserError, match="thesis.tex"):
        check_replaceable(run, "run")


def test_synth_with_out_in_an_unwritable_place_is_one_line(capsys):
    rc, err = run_cli(capsys, "synth", "/proc/x", *SYNTH)
    assert rc == 2
    one_line(err, "/proc", "cannot write")


def test_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    import imageio.v3 as iio

    def full(path, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(iio, "imwrite", full)
    rc, err = run_cli(capsys, "synth", tmp_path / "sk", *SYNTH)
    assert rc == 1
    one_line(err, "000000.png", "No space left on device")
    assert list(tmp_path.iterdir()) == []  # the temporary folder is gone too


@pytest.mark.parametrize("error", [MemoryError(), RuntimeError(
    "[enforce fail at alloc_cpu.cpp:118] DefaultCPUAllocator: not enough memory")])
def test_out_of_memory_is_one_line(tmp_path, capsys, monkeypatch, error):
    """An option asking for more than the machine has (a huge --batch-rays once ended in
    the allocator's traceback)."""
    import imageio.v3 as iio

    def short(*a, **k):
        raise error

    monkeypatch.setattr(iio, "imwrite", short)
    rc, err = run_cli(capsys, "synth", tmp_path / "sk", *SYNTH)
    assert rc == 1
    one_line(err, "out of memory")
    assert list(tmp_path.iterdir()) == []


def test_a_gpu_fault_is_one_line_naming_the_way_round(tmp_path, capsys, monkeypatch):
    """A CUDA context lost to a kernel (an H200's first frame, 2026-11-28): one line that
    says how to run without the Triton kernels, not CUDA's traceback."""
    import imageio.v3 as iio

    def fault(*a, **k):
        raise RuntimeError("CUDA error: an illegal memory access was encountered\n"
                           "CUDA kernel errors might be asynchronously reported")

    monkeypatch.setattr(iio, "imwrite", fault)
    rc, err = run_cli(capsys, "synth", tmp_path / "sk", *SYNTH)
    assert rc == 1
    one_line(err, "GPU faulted", "illegal memory access", "FLAMENERF_GPU_KERNELS=0")
    assert list(tmp_path.iterdir()) == []


def test_a_mistyped_kernel_name_is_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("FLAMENERF_GPU_KERNELS", "knn,hashgird")
    rc, err = run_cli(capsys, "synth", tmp_path / "sk", *SYNTH)
    assert rc == 2
    one_line(err, "FLAMENERF_GPU_KERNELS=knn,hashgird", "no kernel hashgird")
    assert list(tmp_path.iterdir()) == []


def test_an_unreadable_metrics_file_is_one_line(tmp_path, capsys):
    (tmp_path / "m.json").write_bytes(b"\xff\xfe\x00binary")
    rc, err = run_cli(capsys, "compare", tmp_path / "m.json")
    assert rc == 2
    one_line(err, "m.json", "not valid JSON")


def test_a_video_ffmpeg_cannot_write_names_the_video(tmp_path, monkeypatch):
    """ffmpeg's own failure is one line naming the video asked for, not its temporary."""
    import imageio_ffmpeg
    import numpy as np

    from flamenerf.data.video import VideoWriter
    from flamenerf.errors import UserError

    def broken(*a, **k):
        raise BrokenPipeError(32, "Broken pipe")
        yield

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", broken)
    with pytest.raises(UserError, match=r"v.mp4: ffmpeg could not write the video \(.*pipe"):
        with VideoWriter(tmp_path / "v.mp4", 30) as v:
            v.write(np.zeros((8, 8, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_stale_synth_folders_are_removed_on_the_next_start(tmp_path, capsys):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = tmp_path / f".sk.flamenerf-{dead}-abcd1234"
    (stale / "images").mkdir(parents=True)
    other = tmp_path / f".other.flamenerf-{dead}-abcd1234"  # another output's: not ours to
    other.mkdir()                                            # judge from this command
    theirs = tmp_path / ".sk.backup12"
    theirs.mkdir()
    assert run_cli(capsys, "synth", tmp_path / "sk", *SYNTH)[0] == 0
    assert not stale.exists()
    assert other.exists() and theirs.exists()


# ----------------------------------------------------------------------------- numbers


@pytest.mark.parametrize("args, words", [
    (["render", "{run}", "--fps", "nan"], ["--fps: must be a finite number"]),
    (["render", "{run}", "--fps", "0"], ["--fps: the frame rate must be a number from 0.1"]),
    (["render", "{run}", "--fps", "1e300"], ["--fps: the frame rate must be a number from"]),
    (["render", "{run}", "--camera", "orbit", "--amplitude", "inf"], ["--amplitude: must be"]),
    (["train", "{data}", "--out", "{tmp}/r", "--downscale", "nan"], ["--downscale: must be"]),
    (["eval", "{run}", "--fit-lr", "-1"], ["--fit-lr -1.0: must be positive"]),
    (["eval", "{run}", "--seed", "-1"], ["--seed -1"]),
    (["eval", "{run}", "--split", "capture"], ["--split capture: holds the training frames"]),
    (["compare", "{run}", "--out", "{tmp}/afile/x.md"], ["afile: is a file"]),
    (["synth", "{tmp}/s", "--seed", "-1"], ["--seed -1"]),
    (["demo", "--out", "{tmp}/d", "--train-size", "0"], ["--train-size 0", "--size"]),
    (["demo", "--out", "{tmp}/d", "--steps", "0"], ["--steps 0"]),
    (["bench", "--out", "{tmp}/afile", "--work", "{tmp}/w"], ["afile", "not a folder"]),
    (["render", "{run}", "--camera", "{tmp}/flat.json"], ["flat.json", "pose 0 is not rigid"]),
    (["render", "{run}", "--camera", "{tmp}"], ["is a folder; give the camera path file"]),
    (["render", "{run}", "--expressions", "jawOpen=1,jawOpen=0"], ["jawOpen is given twice"]),
    (["train", "{tmp}/afile", "--out", "{tmp}/r"], ["afile: is a file"]),
    (["train", "{data}", "--out", "{tmp}/r", "--face-reg-weight", "-1"], ["--face-reg-weight"]),
    (["convert", "{tmp}/nope"], ["nope: run directory does not exist"]),
    (["eval", "{run}", "--split", "nosuch"], ["no split named 'nosuch'", "--split chooses"]),
    # the output is checked before the video is read (tracking it first took minutes)
    (["track", "{tmp}/nope.mp4", "--out", "{tmp}/afile/d.json"], ["afile", "not a folder"]),
    (["track", "{tmp}/nope.mp4", "--out", "{tmp}", "--overwrite"], ["is a directory"]),
    # a video that is not there: the folders made for the output are removed again
    (["track", "{tmp}/nope.mp4", "--out", "{tmp}/new/sub/d.json"], ["nope.mp4"]),
    (["track", "{tmp}/nope.mp4", "--out", "{tmp}"], ["is a directory"]),
    # no upper bound once meant minutes of work and then an allocator's traceback
    (["render", "{run}", "--frames", "1000000000", "--max-frames", "2"], ["--frames 1000000000"]),
    (["synth", "{tmp}/s", "--frames", "100000000"], ["--frames 100000000: must be from 1"]),
    (["synth", "{tmp}/s", "--workers", "100000"], ["--workers 100000"]),
    (["preprocess", "{tmp}/nope.mp4", "{tmp}/p", "--size", "100000000"], ["--size must be"]),
    (["preprocess", "{tmp}/nope.mp4", "{tmp}/p", "--far", "1e9"], ["--far 1000000000.0"]),
    (["render", "{run}", "--threads", "-3"], ["--threads -3: must be >= 0"]),
    (["eval", "{run}", "--threads", "-3"], ["--threads -3: must be >= 0"]),
    (["render", "{run}", "--expressions", "jawOpen=1e308"], ["a value of 1e+308"]),
    (["render", "{run}", "--split", "capture", "--edit", "jawOpen+=1e308"], ["must be finite"]),
    (["train", "{data}", "--out", "{data}"], ["is a dataset (it holds transforms.json)"]),
    (["track", "{tmp}/v.mp4", "--out", "{tmp}/d.json", "--driver-neutral-frame", "3"],
     ["--driver-neutral-frame: only with --relative-to"]),
    (["eval", "{run}", "--drive", "{tmp}/afile"], ["afile: not a readable video"]),
])
def test_bad_numbers_are_one_line_before_any_work(args, words, toy_run, toy_dataset, tmp_path,
                                                  capsys):
    (tmp_path / "afile").write_text("mine")
    (tmp_path / "flat.json").write_text(json.dumps([[[1, 0, 0, 0], [0, 1, 0, 0],
                                                     [0, 0, 0, 0], [0, 0, 0, 1]]]))
    args = [a.format(run=toy_run, data=toy_dataset, tmp=tmp_path) for a in args]
    rc, err = run_cli(capsys, *args)
    assert rc == 2
    one_line(err, "flamenerf: error:", *words)
    # nothing was made: no scene for the demo or the synth, no run, no bench work
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "flat.json"]


@pytest.mark.slow
def test_resume_says_which_settings_it_ignores(toy_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(toy_dataset), "--out", str(run), "--steps", "1"]) == 0
    capsys.readouterr()
    assert main(["train", str(toy_dataset), "--out", str(run), "--steps", "2", "--resume",
                 "--preset", "nerfies", "--batch-rays", "64"]) == 0
    out = capsys.readouterr().out
    assert "ignored: --preset nerfies, --batch-rays 64" in out
    assert json.loads((run / "config.json").read_text())["preset"] == "fast"
    # a run of another preset resumed with the default one (typed or not): named as such
    nerfies = tmp_path / "nerfies"
    assert main(["train", str(toy_dataset), "--out", str(nerfies), "--steps", "1",
                 "--preset", "nerfies"]) == 0
    capsys.readouterr()
    assert main(["train", str(toy_dataset), "--out", str(nerfies), "--steps", "2", "--resume",
                 "--preset", "fast"]) == 0
    assert "a `nerfies` run, with its own settings" in capsys.readouterr().out
