"""`flamenerf bench` end to end, tiny: three toy-sized runs on the toy dataset."""

from __future__ import annotations

import json

import pytest

from flamenerf.workflows import bench
from flamenerf.workflows.bench import BenchOptions, method_configs, run_bench
from toy import toy_config


def test_cpu_methods_share_the_fast_machinery_and_budget():
    cfgs = method_configs("fast", steps=500, batch_rays=256, downscale=2.0)
    assert {n: c.model.expression_mode for n, c in cfgs.items()} == {
        "flame-in-nerf": "masked", "nerfies": "none", "no-prior": "everywhere"}
    for c in cfgs.values():
        assert c.preset == "fast" and c.model.field.kind == "hash"
        assert (c.train.steps, c.train.batch_rays, c.train.downscale) == (500, 256, 2.0)
        assert c.model.warp.anneal_fraction == 0.5  # c2f opens half-way, whatever the steps
    paper = method_configs("paper", steps=None, batch_rays=None, downscale=1.0)
    assert {n: c.preset for n, c in paper.items()} == {
        "flame-in-nerf": "flame-in-nerf", "nerfies": "nerfies", "no-prior": "no-prior"}


@pytest.mark.slow
def test_bench_end_to_end(toy_dataset, tmp_path, monkeypatch):
    # the `fast` machinery at toy size (a 16x16 scene needs no 2^17-entry hash tables)
    monkeypatch.setattr(bench, "preset", lambda name: toy_config())
    o = BenchOptions(out=tmp_path / "report", work=tmp_path / "work", scene=toy_dataset,
                     train_size=16, steps=2, batch_rays=32, fit_steps=1, fit_batch_rays=32,
                     device="cpu")
    rep = run_bench(o, log=lambda s: None)
    readme = (o.out / "README.md").read_text()
    for s in ("## Machine", "## Results", "| FLAME-in-NeRF |", "| Nerfies |", "| No prior |",
              "## Timings", "prior_ablation.png", "expression_mode"):
        assert s in readme, s
    assert (o.out / "prior_ablation.png").stat().st_size > 0
    saved = json.loads((o.out / "bench.json").read_text())
    lk = {n: r["leakage"]["mean"] for n, r in saved["results"].items()}
    assert lk["flame-in-nerf"] == 0.0 and lk["nerfies"] == 0.0
    assert rep["machinery"] == "fast"
    # a second invocation reuses the finished runs
    rep2 = run_bench(o, log=lambda s: None)
    assert all(m["reused"] for m in rep2["methods"].values())


def test_an_entangled_bench_makes_its_own_scene_and_refuses_another(tmp_path):
    from flamenerf.data.dataset import load_dataset
    from flamenerf.errors import UserError

    o = BenchOptions(work=tmp_path, scene_size=16, frames=4, entangled=True)
    scene, _, reused = bench._prepare_scene(o, log=lambda *_: None)
    assert not reused and load_dataset(scene).splits.get("pairs")
    assert bench._prepare_scene(o, log=lambda *_: None)[2]  # the same scene is reused
    with pytest.raises(UserError, match="holds another scene"):
        bench._prepare_scene(BenchOptions(work=tmp_path, scene_size=16, frames=4),
                             log=lambda *_: None)


def test_a_finished_run_is_reused_though_its_bf16_settled_off(toy_dataset, tmp_path,
                                                             monkeypatch):
    from flamenerf.training import trainer

    monkeypatch.setattr(trainer, "bf16_pays", lambda: False)  # a CPU where it does not pay
    cfg = toy_config(steps=1)
    cfg.train.bf16 = True
    first = bench.timed_train(tmp_path / "run", cfg, toy_dataset, "cpu", log=lambda *_: None)
    assert not first["reused"] and first["step"] == 1
    asked = toy_config(steps=1)  # asked afresh: bf16 on, as the preset has it
    asked.train.bf16 = True
    again = bench.timed_train(tmp_path / "run", asked, toy_dataset, "cpu", log=lambda *_: None)
    assert again["reused"] and again["train_seconds"] == pytest.approx(
        first["train_seconds"], rel=0.5)
