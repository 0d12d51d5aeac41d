"""Config <-> the plain dict a run's config.json stores."""

from __future__ import annotations

import dataclasses
import json

import pytest

from flamenerf.config import PRESETS, Config, from_dict, preset
from flamenerf.errors import UserError


@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_survives_a_round_trip_through_json(name):
    cfg = preset(name)
    saved = json.loads(json.dumps(cfg.to_dict()))  # as config.json stores it
    assert from_dict(saved) == cfg


def test_unknown_keys_are_ignored_and_missing_ones_default():
    cfg = preset("fast")
    d = cfg.to_dict()
    d["removed_top_level_field"] = 1
    d["model"]["removed_model_field"] = {"nested": True}
    d["train"]["removed_train_field"] = [1, 2]
    assert from_dict(d) == cfg
    assert from_dict({}) == Config()
    partial = from_dict({"train": {"steps": 7}})
    assert partial.train.steps == 7
    assert dataclasses.replace(partial.train, steps=Config().train.steps) == Config().train


def test_unknown_preset_is_a_user_error_naming_the_choices():
    with pytest.raises(UserError, match="unknown preset 'nope'.*fast"):
        preset("nope")


def test_override_sets_dotted_fields_and_skips_none():
    from flamenerf.config import override, preset
    from flamenerf.errors import UserError

    cfg = override(preset("fast"), {"train.batch_rays": 512, "train.steps": None,
                                    "model.mesh_guide.enabled": "true",
                                    "train.face_ray_fraction": "0.25"})
    assert cfg.train.batch_rays == 512 and cfg.train.steps == preset("fast").train.steps
    assert cfg.model.mesh_guide.enabled is True and cfg.train.face_ray_fraction == 0.25
    import pytest

    with pytest.raises(UserError, match="train.nope"):
        override(cfg, {"train.nope": 1})


def test_parse_overrides_reads_key_values_and_rejects_the_rest():
    import pytest

    from flamenerf.config import override, parse_overrides, preset
    from flamenerf.errors import UserError

    d = parse_overrides("model.head.band=0.6, model.field.dir_freqs=0,")
    assert d == {"model.head.band": "0.6", "model.field.dir_freqs": "0"}
    cfg = override(preset("fast"), d)
    assert cfg.model.head.band == 0.6 and cfg.model.field.dir_freqs == 0
    assert parse_overrides("") == {}
    # an optional field whose default is None (settled per dataset) takes a number too
    cfg = override(preset("fast"), parse_overrides("model.expression_regions.radius=0.1"))
    assert cfg.model.expression_regions.radius == 0.1
    with pytest.raises(UserError):
        parse_overrides("model.head.band")


def test_parse_variants_names_each_with_its_overrides():
    from flamenerf.config import parse_variants

    assert parse_variants("fast,nerfies") == [("fast", {}), ("nerfies", {})]
    assert parse_variants("a:model.head.band=0.6,train.seed=1;b") == [
        ("a", {"model.head.band": "0.6", "train.seed": "1"}), ("b", {})]
    assert parse_variants("a:model.head.band=0.6,train.seed=1") == [
        ("a", {"model.head.band": "0.6", "train.seed": "1"})]


def test_runs_render_over_the_mean_of_the_backgrounds_they_trained_over():
    assert preset("fast").train.random_background
    assert preset("fast").train.render_background == 0.5
    assert not preset("flame-in-nerf").train.random_background
    assert preset("flame-in-nerf").train.render_background == 0.0


@pytest.mark.parametrize("values, words", [
    ({"train": {"steps": "ten"}}, 'x/config.json: train.steps must be an int, got "ten"'),
    ({"train": {"steps": True}}, "train.steps must be an int, got true"),
    ({"model": {"expression_scale": "1"}}, "model.expression_scale must be a number"),
    ({"model": {"expression_mode": "weird"}}, 'expression_mode must be one of "masked"'),
    ({"model": {"warp": "x"}}, 'model.warp must be an object, got "x"'),
    ({"model": {"warp": {"skips": 4}}}, "model.warp.skips must be a list of ints, got 4"),
    ({"model": {"warp": {"band": "wide"}}}, "model.warp.band must be a number or null"),
    ({"model": {"mesh_guide": {"neighbours": 0}}}, "neighbours must be at least 1, got 0"),
    ({"model": {"sampler": {"num_proposal": -4}}}, "num_proposal must be at least 1, got -4"),
    ({"model": {"expression_scale": 0}}, "expression_scale must be a positive number"),
    ({"train": {"face_ray_fraction": 1.5}}, "face_ray_fraction must be between 0 and 1"),
    ({"train": {"lr": -1e-3}}, "train.lr must be a finite number, at least 0"),
    ([], "the configuration must be an object, got []"),
])
def test_from_dict_names_the_file_and_key_of_a_wrong_value(values, words):
    with pytest.raises(UserError) as e:
        from_dict(values, "x/config.json")
    assert words in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_from_dict_takes_ints_for_floats_lists_for_tuples_and_null_for_optionals():
    cfg = from_dict({"model": {"expression_scale": 2, "warp": {"skips": [1, 2], "band": None},
                               "mesh_guide": {"enabled": None, "max_residual": 0}}})
    assert cfg.model.expression_scale == 2.0 and isinstance(cfg.model.expression_scale, float)
    assert cfg.model.warp.skips == (1, 2) and cfg.model.warp.band is None
    assert cfg.model.mesh_guide.enabled is None and cfg.model.mesh_guide.max_residual == 0.0
