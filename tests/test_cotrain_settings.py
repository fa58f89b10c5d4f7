"""The settings a co-training run checks before any work, and the run records of earlier versions
(``RETIRED_FIELDS``, ``RETIRED_VALUES`` in ``train.checkpoint``): a retired setting at the value
whose behaviour stayed loads as today's config; any other value is refused, naming it."""

import dataclasses
import json

import pytest

from f2f_jax import config
from f2f_jax.errors import CheckpointError, F2FError
from f2f_jax.train.checkpoint import config_from_dict, config_to_dict
from f2f_jax.train.cotrain import CoTrainRun
from f2f_jax.train.run_dir import meta_config


def _with(cfg, **train):
    return cfg.replace(train=dataclasses.replace(cfg.train, **train))


def test_run_settings_are_checked():
    cfg = config.tiny()
    for field, value, words in [("cycle_candidates", 0, "cycle_candidates must be >= 1"),
                                ("imprint_objects", -1, "imprint_objects must be >= 0"),
                                ("gn_passes", 0, "gn_passes must be >= 1"),
                                ("objectives", "grasp", "objectives must be one of")]:
        with pytest.raises(F2FError, match=words):
            CoTrainRun("/nonexistent-run", _with(cfg, **{field: value}))
    # co-training's imprint control is gone; the message says where its result is
    with pytest.raises(ValueError, match=r"one of \('GS', 'GS\+R', 'GS\+S', 'full'\).*retired"):
        CoTrainRun("/nonexistent-run", _with(cfg, objectives="imprint"))


def _old_record(**changes) -> dict:
    """The tiny config as commit dd4f091 recorded it: with its retired fields, at the values kept."""
    d = config_to_dict(config.tiny())
    d["sim"].update(push_point="com", finger_collisions=True)
    d["net"].update(height_truncation_voxels=5.0, fitness_stem_kernel=5)
    d["train"].update(gn_anneal_epochs=0, fn_refit_steps=None, imprint_anchor=0.0, anchor_target="imprint",
                      perturbed_peak=0.3)
    for key, value in changes.items():
        part, name = key.split(".")
        d[part][name] = value
    return json.loads(json.dumps(d))


def test_an_old_record_at_the_kept_values_loads_as_todays_config():
    assert config_from_dict(_old_record()) == config.tiny()


@pytest.mark.parametrize("key, value", [
    ("train.imprint_anchor", 10.0), ("train.anchor_target", "best"), ("train.gn_anneal_epochs", 5),
    ("train.fn_refit_steps", 32), ("train.perturbed_peak", 0.6), ("net.height_truncation_voxels", 3.0),
    ("net.fitness_stem_kernel", 3), ("sim.push_point", "origin"), ("sim.finger_collisions", False)])
def test_an_old_record_at_another_value_is_refused_naming_the_field(key, value):
    with pytest.raises(CheckpointError, match=f"{key.split('.')[1]}={value!r}".replace("(", r"\(")):
        config_from_dict(_old_record(**{key: value}))


def test_a_record_of_the_imprint_control_is_refused():
    with pytest.raises(CheckpointError, match="objectives='imprint'.*dd4f091"):
        config_from_dict(_old_record(**{"train.objectives": "imprint"}))


def test_an_old_run_directory_goes_on_and_one_of_a_retired_setting_is_refused(tmp_path):
    """run.json of an earlier version: resumed as today's run when its retired fields hold the kept
    values, refused (nothing changed) when one does not."""
    for name, changes in (("kept", {}), ("anchored", {"train.imprint_anchor": 1.0})):
        run_dir = tmp_path / name
        run_dir.mkdir()
        recorded = _old_record(**changes)
        recorded["train"].pop("cycles")
        (run_dir / "run.json").write_text(json.dumps({"config_name": "tiny", "config": recorded,
                                                      "objects": "builtin", "backend": "mujoco"}))
        before = (run_dir / "run.json").read_text()
        if not changes:
            run = CoTrainRun(run_dir, config.tiny(), config_name="tiny", progress=False)
            assert meta_config(run.cfg) == meta_config(config.tiny())
        else:
            with pytest.raises(CheckpointError, match="imprint_anchor=1.0"):
                CoTrainRun(run_dir, config.tiny(), config_name="tiny", progress=False)
        assert (run_dir / "run.json").read_text() == before
