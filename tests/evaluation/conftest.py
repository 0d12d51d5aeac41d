"""Toy dataset and runs (src/flamenerf/evaluation/toy.py): every split of the built-in
scene at 16x16, made in about a second."""

from __future__ import annotations

import pytest

from flamenerf.evaluation.toy import make_toy_dataset, make_toy_run


@pytest.fixture(scope="session")
def toy_dataset(tmp_path_factory):
    return make_toy_dataset(tmp_path_factory.mktemp("toy") / "dataset")


@pytest.fixture(scope="session")
def toy_run(toy_dataset, tmp_path_factory):
    return make_toy_run(toy_dataset, tmp_path_factory.mktemp("toy") / "run", "masked")
