"""Config from the command line: ``cli.overrides.override`` (``--set SECTION.FIELD=VALUE``)."""

import dataclasses
import json

import pytest

from f2f_jax import config, run_plan
from f2f_jax.cli import overrides
from f2f_jax.errors import CheckpointError
from f2f_jax.train.cotrain import CoTrainRun
from f2f_jax.train.run_dir import write_record


def test_override_reads_each_field_as_its_type():
    cfg = overrides.override(config.default(), [
        "train.generator_lr=3e-4", "sim.timestep=0.002", "net.fitness_fc=(256, 128)",
        "sim.shared_settle=false", "train.objectives=GS", "train.cycles=7",
        "sim.stability_directions=[[1, 0, 0], [0, 1, 0]]"])
    assert cfg.train.generator_lr == pytest.approx(3e-4) and cfg.sim.timestep == 0.002
    assert cfg.net.fitness_fc == (256, 128) and cfg.sim.shared_settle is False
    assert cfg.train.objectives == "GS" and cfg.train.cycles == 7 and isinstance(cfg.train.cycles, int)
    assert cfg.sim.stability_directions == ((1, 0, 0), (0, 1, 0))
    assert overrides.override(cfg, ["train.generator_lr=None"]).train.generator_lr is None
    assert cfg.geometry == config.default().geometry  # nothing else moved
    assert overrides.override(cfg, []) == cfg


@pytest.mark.parametrize("bad, words", [
    ("train.lr", "SECTION.FIELD=VALUE"),
    ("optim.lr=1", "no config section 'optim'"),
    ("train.learning_rate=1", "train has no field 'learning_rate'"),
    ("train.cycles=1.5", "train.cycles takes an int"),
    ("train.cycles=None", "not None"),
    ("sim.timestep=fast", "sim.timestep takes a float"),
    ("sim.shared_settle=2", "true or false"),
    ("net.fitness_fc=3", "takes a tuple"),
])
def test_override_refuses_what_the_field_cannot_hold(bad, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
        overrides.override(config.default(), [bad])


def test_a_run_directory_keeps_its_overrides(tmp_path):
    """A run made with --set records the changed field; resuming without it is refused, naming it."""
    cfg = overrides.override(config.tiny(), ["train.generator_lr=3e-4"])
    run = CoTrainRun(tmp_path, cfg, config_name="tiny", progress=False)
    write_record(tmp_path, run._run_meta())
    assert json.loads((tmp_path / "run.json").read_text())["config"]["train"]["generator_lr"] == 3e-4
    CoTrainRun(tmp_path, cfg, config_name="tiny", progress=False)  # the same settings: accepted
    with pytest.raises(CheckpointError, match="train.generator_lr") as refused:
        CoTrainRun(tmp_path, config.tiny(), config_name="tiny", progress=False)
    # the refusal names the flags that resume the run, and they do
    flags = str(refused.value).split("resume it with ")[1].split("--set ")[1:]
    assert [f.strip() for f in flags] == ["train.generator_lr=0.0003"]
    CoTrainRun(tmp_path, overrides.override(config.tiny(), [f.strip() for f in flags]), config_name="tiny",
               progress=False)


def test_resume_flags_round_trip_through_override():
    """Every kind of field the resume hint names (int, float, bool, str, tuple, None) reads back
    through ``--set`` as the value recorded."""
    from f2f_jax.train.run_dir import differing_fields, meta_config, set_flags

    tiny = config.tiny()
    recorded = tiny.replace(
        train=dataclasses.replace(tiny.train, imprint_objects=7,
                                  generator_lr=None if tiny.train.generator_lr else 2.5e-4),
        net=dataclasses.replace(tiny.net, generator="latent" if tiny.net.generator == "heights" else "heights",
                                fitness_fc=(96, 48)),
        sim=dataclasses.replace(tiny.sim, shared_settle=not tiny.sim.shared_settle))
    old, now = meta_config(recorded), meta_config(config.tiny())
    fields = differing_fields(old, now)
    assert len(fields) == 5
    flags = [f.strip().strip("'") for f in set_flags(old, fields).split("--set ")[1:]]
    assert meta_config(overrides.override(config.tiny(), flags)) == old


def test_cotrain_refuses_a_bad_set_before_any_work(tmp_path, capsys):
    from f2f_jax.cli import cotrain

    run_dir = tmp_path / "run"
    assert cotrain.main(["--config", "tiny", "--run-dir", str(run_dir), "--set", "train.nope=1"]) == 2
    assert "train has no field 'nope'" in capsys.readouterr().err
    assert not run_dir.exists()


def test_workstation_config_plans_100x_the_defaults_simulations_on_8x_its_objects():
    """The workstation's sizes: the workstation run simulates >= 100x the default run's evaluations, on
    >= 8x its objects, with designs of one object that differ a little in both data sources."""
    default, work = config.default(), config.workstation()
    plan, base = run_plan.planned_simulations(work), run_plan.planned_simulations(default)
    assert base == {"dataset": 51 * 3, "baselines": 26, "cycles": 640, "heldout": 26, "total": 845}
    assert plan["total"] >= 100 * base["total"] and work.train.n_objects >= 8 * default.train.n_objects
    assert work.train.perturbed_pairs > 0 and work.train.cycle_candidates > 1
    assert (work.net, work.sim, work.geometry) == (default.net, default.sim, default.geometry)
    assert config.get("workstation") == work
    assert run_plan.planned_simulations(default, n_objects=10)["dataset"] == 8 * 3  # 2 held out


def test_cotrain_says_what_a_run_simulates_and_warns_when_its_rows_outgrow_the_machine():
    from f2f_jax.cli.cotrain import _plan

    text, warning = _plan(config.workstation(), "workstation", memory=128 * 2**30)
    assert "87,424 grasp evaluations" in text and "20.8 GiB" in text and warning is None
    _, warning = _plan(config.workstation(), "workstation", memory=24 * 2**30)
    assert "24 GiB" in warning and "cycle_candidates" in warning
    assert _plan(config.default(), "default", memory=None)[1] is None
