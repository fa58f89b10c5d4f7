"""Simulation presets (the fast default ends phases at rest) and the object tiles option.

The agreement of the two on many triples is a benchmark (``benchmarks/sim_agreement.py``); here
are the behaviours it relies on: the presets are what they say, old run directories keep the
simulator they were made with, tiles cover what a finger closing along x can touch and nothing
beside it, and ending a phase at rest does not change a clear outcome.
"""

import dataclasses
import json

import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.config import voxel_centres
from f2f_jax.errors import VolumeError
from f2f_jax.geometry import imprint_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import hull_fit, points_in_hulls
from f2f_jax.geometry.object_tiles import depth_map, tile_object_hulls
from f2f_jax.geometry.pieces import object_pieces, object_pieces_many
from f2f_jax.sim import build_model, evaluate, run_trials
from f2f_jax.train.checkpoint import config_from_dict, config_to_dict


def union_tsdf(boxes, cfg) -> np.ndarray:
    """Truncated signed distance of a union of axis-aligned boxes [(lo, hi), ...] (metres)."""
    pts = np.stack(np.meshgrid(*voxel_centres(cfg.geometry), indexing="ij"), -1)
    sdf = np.full(pts.shape[:3], np.inf)
    for lo, hi in boxes:
        centre, half = (np.add(lo, hi)) / 2, (np.subtract(hi, lo)) / 2
        q = np.abs(pts - centre) - half
        sdf = np.minimum(sdf, np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0))
    return np.clip(sdf / cfg.geometry.truncation, -1, 1).astype(np.float32)


def test_presets_set_what_they_name_and_the_configs_are_fast():
    for name in ("tiny", "default", "paper"):
        assert config.sim_preset_name(config.get(name)) == "fast"
    ref = config.with_sim_preset(config.default(), "reference")
    assert config.sim_preset_name(ref) == "reference"
    assert ref.sim.rest_speed == 0.0 and config.default().sim.rest_speed > 0
    # only the preset's fields change
    assert ref.net == config.default().net and ref.sim.grip_force == config.default().sim.grip_force
    custom = ref.replace(sim=dataclasses.replace(ref.sim, rest_speed=0.01))
    assert config.sim_preset_name(custom) == "custom"
    with pytest.raises(ValueError, match="unknown simulation preset 'exact'"):
        config.with_sim_preset(ref, "exact")
    bad = ref.replace(geometry=dataclasses.replace(ref.geometry, object_method="vhacd"))
    with pytest.raises(ValueError, match="unknown object_method 'vhacd'"):
        object_pieces(np.ones((40, 40, 40), np.float32), bad)


def old_run_config(**sim) -> dict:
    """The default config as a run directory saved before SimConfig.integrator existed stores
    it: 2 ms steps, no integrator field (MuJoCo's Euler was the only one used)."""
    saved = config_to_dict(config.default())
    del saved["sim"]["integrator"], saved["sim"]["shared_settle"]  # neither existed then
    saved["sim"].update(timestep=0.002, **sim)
    return saved


def test_a_run_saved_before_the_presets_loads_as_the_reference():
    saved = old_run_config()
    del saved["geometry"]["object_method"], saved["sim"]["rest_speed"]
    cfg = config_from_dict(saved)
    assert config.sim_preset_name(cfg) == "reference"
    assert cfg.sim.integrator == "euler" and cfg.sim.timestep == 0.002
    assert config_from_dict(config_to_dict(config.default())) == config.default()


def test_a_run_of_the_first_fast_preset_resumes_with_its_own_simulator():
    # 2 ms Euler steps with the early exits at rest: not a preset any more, kept as saved
    cfg = config_from_dict(old_run_config())
    assert (cfg.sim.timestep, cfg.sim.integrator, cfg.sim.rest_speed) == (0.002, "euler", 0.002)
    assert config.sim_preset_name(cfg) == "custom"


def test_a_run_of_the_4ms_preset_from_before_the_shared_settle_goes_on_settling_every_grasp(tmp_path):
    from f2f_jax.train.run_dir import with_recorded_simulator

    saved = config_to_dict(config.default())
    del saved["sim"]["shared_settle"]  # as run.json files written before it existed hold it
    recorded = config_from_dict(saved)
    assert recorded.sim.shared_settle is False and recorded.sim.timestep == 0.004
    assert config.sim_preset_name(recorded) == "custom"
    resumed = with_recorded_simulator(config.default(), recorded, tmp_path)
    assert resumed.sim == recorded.sim  # its store was filled that way: it goes on that way
    assert config.sim_preset_name(config.with_sim_preset(recorded, "fast")) == "fast"


def test_depth_map_reads_where_the_object_begins_and_ends_along_x(cfg):
    box = union_tsdf([((-0.02, -0.01, 0.0015), (0.01, 0.01, 0.03))], cfg)
    x_min, x_max = depth_map(box, cfg)
    iy, iz = 20, 10  # a line through the box
    assert abs(x_min[iy, iz] + 0.02) < 2e-4 and abs(x_max[iy, iz] - 0.01) < 2e-4
    assert np.isnan(x_min[2, 10]) and np.isnan(x_max[20, 30])  # lines that miss it


def test_tiles_follow_a_step_seen_along_x_and_do_not_fill_beside_it(cfg):
    # a low slab over the whole width and a tower on its -x half: lines along x above the slab
    # end at the tower's +x face, so a piece there must not reach into the empty corner
    step = union_tsdf([((-0.027, -0.02, 0.0015), (0.027, 0.02, 0.015)),
                       ((-0.027, -0.02, 0.0015), (-0.005, 0.02, 0.055))], cfg)
    hulls = tile_object_hulls(step, cfg)
    fit = hull_fit(step, hulls, cfg)
    assert fit["max_intrusion_m"] < 1.5 * cfg.geometry.voxel_size, fit
    assert fit["iou"] > 0.9, fit
    corner = np.array([[0.015, 0.0, 0.04], [0.005, 0.01, 0.03]])  # empty, beside the tower
    assert not points_in_hulls(hulls, corner).any()


def test_tiles_fill_a_hollow_no_finger_closing_along_x_can_reach(cfg):
    # a box open at the top (a tray): its well is enclosed along x by the walls
    walls = [((-0.027, -0.027, 0.0015), (0.027, 0.027, 0.006)),
             ((-0.027, -0.027, 0.0015), (-0.021, 0.027, 0.04)),
             ((0.021, -0.027, 0.0015), (0.027, 0.027, 0.04)),
             ((-0.027, -0.027, 0.0015), (0.027, -0.021, 0.04)),
             ((-0.027, 0.021, 0.0015), (0.027, 0.027, 0.04))]
    tray = union_tsdf(walls, cfg)
    hulls = tile_object_hulls(tray, cfg)
    assert points_in_hulls(hulls, [[0.0, 0.0, 0.03]]).all()  # the well's middle
    assert not points_in_hulls(hulls, [[0.0, 0.0, 0.05], [0.035, 0.0, 0.02]]).any()


def test_object_pieces_many_makes_each_distinct_volume_once_and_reports_bad_ones(cfg, sphere_tsdf):
    cfg = cfg.replace(geometry=dataclasses.replace(cfg.geometry, object_method="tiles"))
    got = object_pieces_many([sphere_tsdf, np.ones_like(sphere_tsdf), sphere_tsdf], cfg)
    assert got[0] is got[2] and got[0].n_pieces >= 1
    assert isinstance(got[1], str) and "empty" in got[1]
    with pytest.raises(VolumeError):
        object_pieces(np.ones_like(sphere_tsdf), cfg)


def test_ending_phases_at_rest_keeps_the_outcome_and_saves_steps(sphere_tsdf):
    fast = config.tiny()
    full = fast.replace(sim=dataclasses.replace(fast.sim, rest_speed=0.0))
    hulls = object_pieces(sphere_tsdf, fast)
    left, right = imprint_fingers(sphere_tsdf, fast.geometry)
    model = build_model(hulls, finger_hulls(left, fast), finger_hulls(right, fast), fast)
    early, late = run_trials(model, fast), run_trials(model, full)
    np.testing.assert_array_equal(early.outcome, late.outcome)
    assert early.outcome.all(), early.outcome  # the sphere in its imprint: every trial holds
    # (tiny phases are short already: ~20% here, about half with the default phases)
    assert early.steps < 0.9 * late.steps, (early.steps, late.steps)
    # held at the same height: the holds cut short had nothing left to change
    np.testing.assert_allclose(early.heights, late.heights, atol=2e-3)
    # evaluate(preset=...) applies the preset to the config it is given
    out = evaluate([sphere_tsdf], [left], [right], cfg=full, preset="fast", object_hulls=hulls,
                   threads=1)
    np.testing.assert_array_equal(out[0], early.outcome)


def test_a_run_directory_goes_on_with_the_simulator_it_was_made_with(tmp_path):
    from f2f_jax.errors import CheckpointError
    from f2f_jax.train.cotrain import CoTrainRun

    saved = old_run_config()  # the first fast preset: 2 ms Euler
    saved["train"].pop("cycles")
    (tmp_path / "run.json").write_text(json.dumps(
        {"config_name": "default", "config": saved, "objects": "builtin", "backend": "mujoco"}))
    run = CoTrainRun(tmp_path, config.default(), config_name="default", progress=False)
    assert (run.cfg.sim.timestep, run.cfg.sim.integrator) == (0.002, "euler")
    assert run.cfg.net == config.default().net and run.cfg.train == config.default().train
    # a simulator asked for explicitly (--sim-preset) is refused, naming what differs
    with pytest.raises(CheckpointError, match="sim.timestep"):
        CoTrainRun(tmp_path, config.default(), config_name="default", progress=False,
                   keep_simulator=False)
    # a run of other training settings is refused as before, whatever its simulator
    other = config.default().replace(train=dataclasses.replace(config.default().train, lr=0.5))
    with pytest.raises(CheckpointError, match="train.lr"):
        CoTrainRun(tmp_path, other, config_name="default", progress=False)
