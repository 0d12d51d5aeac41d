"""The training frames' range of each control, and clamping to it."""

import numpy as np

from flamenerf.data.expression_range import ExpressionRange, training_range


def test_clamp_and_what_it_changes():
    r = ExpressionRange(["jawOpen", "mouthSmileLeft"], np.array([0.0, 0.0]),
                        np.array([0.6, 0.1]))
    v = np.array([[0.3, 1.0], [0.7, -0.2]], np.float32)
    out = r.clamp(v)
    assert out.dtype == np.float32
    assert np.allclose(out, [[0.3, 0.1], [0.6, 0.0]])
    assert r.beyond(v) == ["jawOpen 0.70 asked, 0.60 rendered (the clip: 0.00-0.60)",
                           "mouthSmileLeft 1.00 asked, 0.10 rendered (the clip: 0.00-0.10)"]
    assert r.beyond(out) == []
    assert r.clamp(out) is not None and np.array_equal(r.clamp(out), out)


def test_training_range_is_the_train_split_only(toy_dataset):
    from flamenerf.data.dataset import load_dataset

    ds = load_dataset(toy_dataset)
    r = training_range(ds)
    train = ds.expression_matrix(ds.split("train"))
    assert np.allclose(r.lo, train.min(0)) and np.allclose(r.hi, train.max(0))
    assert r.names == list(ds.expression_names)
