"""Controls alone against ground truth: the shares are 1 for the truth itself, 0 for a face
that does not move, negative for a wrong change; a control's own part of the face holds
the truth's change."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.data.scene import FrameSet
from flamenerf.evaluation.separation import outside_share, reproduced_share, separation
from flamenerf.synthetic.scene import make_scene


@pytest.fixture(scope="module")
def entangled(tmp_path_factory):
    out = make_scene(tmp_path_factory.mktemp("ent") / "scene", size=40, frames=6,
                     reanimate=0, leakage_steps=1, workers=1, entangled=True,
                     never=("eyeBlinkLeft",))
    ds = load_dataset(out)
    return (FrameSet(ds, ds.split("leakage"), ds.intrinsics),
            FrameSet(ds, ds.split("pairs"), ds.intrinsics))


def _images(fs: FrameSet) -> list[np.ndarray]:
    return list(fs.images.numpy())


def test_the_truth_reproduces_every_control_and_pair(entangled):
    leak, pairs = entangled
    res = separation(leak, _images(leak), pairs, _images(pairs))
    assert set(res["controls"]) == set(leak.ds.expression_names)
    assert len(res["pairs"]) == pairs.n
    for r in [*res["controls"].values(), *res["pairs"].values()]:
        assert r["reproduced"] == pytest.approx(1.0) and r["change"] == pytest.approx(1.0)
        assert r["outside"] == pytest.approx(r["truth_outside"])
        # the scene's rig moves each control's own part of the face, little else
        assert r["truth_outside"] < 0.2
    assert res["reaching_target"] == len(res["controls"])
    assert "eyeBlinkLeft" in res["never_trained"]


def test_a_face_that_does_not_move_reproduces_nothing(entangled):
    leak, pairs = entangled
    still = [leak.images[0].numpy()] * leak.n
    res = separation(leak, still, pairs, [leak.images[0].numpy()] * pairs.n)
    for r in res["controls"].values():
        assert r["reproduced"] == pytest.approx(0.0) and r["change"] == pytest.approx(0.0)
        assert np.isnan(r["outside"])  # nothing changed
    assert res["reaching_target"] == 0


def test_a_change_the_wrong_way_scores_below_zero():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.2, 0.8, (8, 8, 3))
    truth = ref.copy()
    truth[2:5, 2:5] += 0.1
    mask = np.ones((8, 8), bool)
    assert reproduced_share([ref - (truth - ref)], [truth], ref, [mask]) == pytest.approx(-3.0)
    assert reproduced_share([0.5 * (ref + truth)], [truth], ref, [mask]) == pytest.approx(0.75)
    own = np.zeros((8, 8), bool)
    own[2:4] = True
    assert outside_share(ref, truth, own, power=1) == pytest.approx(1 / 3)
    truth[4, 2:5] += 0.1  # the last row changes twice as much: 4x the squared change
    assert outside_share(ref, truth, own) == pytest.approx(4 / 6)


def test_the_report_gives_each_control_and_pair_a_row(entangled):
    from flamenerf.evaluation.report import compare_markdown, eval_markdown

    leak, pairs = entangled
    res = {"resolution": [40, 40],
           "separation": separation(leak, _images(leak), pairs, _images(pairs))}
    md = eval_markdown(res)
    assert "**Controls alone**" in md
    assert "| jawOpen+browDownLeft | 1.00 | 1.00 |" in md
    never = next(line for line in md.splitlines() if line.startswith("Never moved"))
    assert "eyeBlinkLeft" in never
    assert "Controls alone ↑" in compare_markdown([res])
