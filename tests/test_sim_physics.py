"""Grasp physics on the plain-MuJoCo backend, with the tiny config's short phases.

Clear cases whose outcome follows from statics: a 50 g sphere (0.49 N) between two flat tips
pressed with 1 N each needs a friction coefficient of at least 0.245 (more while the lift
accelerates it), and 2 x 0.5 x 1 N cannot hold weight plus a 1.5 N downward push.  They run under
both simulation presets (``preset`` fixture): the fast default must pass them as the reference
does.  A full evaluation here is ~5k steps (~0.3 s); failed grasps stop after ~400 steps.
"""

import dataclasses

import mujoco
import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.config import TRIAL_NAMES, voxel_centres
from f2f_jax.errors import VolumeError
from f2f_jax.geometry import imprint_fingers, is_feasible, tsdf_to_mesh, wsg50_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import Hulls, pad_hulls
from f2f_jax.geometry.pieces import object_pieces
from f2f_jax.sim import (
    GraspRunner,
    build_model,
    evaluate,
    evaluate_with_info,
    run_trials,
    scene_ids,
)


@pytest.fixture(scope="module")
def tiny():
    return config.tiny()


@pytest.fixture(scope="module")
def sphere_hulls(sphere_tsdf, tiny):
    # Stand-in for coacd: a sphere is convex, so one hull of its surface is its collision shape.
    return pad_hulls([tsdf_to_mesh(sphere_tsdf, tiny.geometry).vertices],
                     tiny.geometry.object_hulls, tiny.geometry.hull_vertices)


@pytest.fixture(scope="module")
def flat_tips(tiny):
    left, right = wsg50_fingers(tiny)
    return finger_hulls(left, tiny), finger_hulls(right, tiny)


@pytest.fixture(scope="module", params=sorted(config.SIM_PRESETS))
def preset(request, sphere_tsdf, tmp_path_factory):
    """(tiny config under one simulation preset, the sphere's object pieces under it)."""
    cfg = config.with_sim_preset(config.tiny(), request.param)
    return cfg, object_pieces(sphere_tsdf, cfg, cache_dir=tmp_path_factory.mktemp("hulls"))


def box_tsdf(lo, hi, cfg) -> np.ndarray:
    """Truncated signed distance of an axis-aligned box (metres, local frame), [40, 40, 40]."""
    pts = np.stack(np.meshgrid(*voxel_centres(cfg.geometry), indexing="ij"), -1)
    centre, half = (np.add(lo, hi)) / 2, (np.subtract(hi, lo)) / 2
    q = np.abs(pts - centre) - half
    sdf = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)
    return np.clip(sdf / cfg.geometry.truncation, -1, 1).astype(np.float32)


def grasp_only(model, cfg):
    """(success, rise in m) of the first grasp trial alone."""
    ok, rise, touching = GraspRunner(model, cfg).grasp(0.0)
    assert touching == 0
    return ok, rise


def test_sphere_in_its_imprint_fingers_is_lifted_and_survives_the_downward_push(
        sphere_tsdf, preset):
    tiny, sphere_hulls = preset
    left, right = imprint_fingers(sphere_tsdf, tiny)
    out, info = evaluate_with_info([sphere_tsdf], [left], [right], cfg=tiny, object_hulls=sphere_hulls)
    assert out.shape == (1, len(TRIAL_NAMES)) and out.dtype == np.uint8
    assert out[0, 0] == 1, f"imprint fingers dropped the sphere: {out[0]}"
    assert out[0, 1] == 1, f"the downward push broke the imprint cage: {out[0]}"
    assert out[0, 5:].sum() >= 5, f"a turned sphere is the same sphere: {out[0]}"
    heights = info.results[0].heights
    # held at the top of the lift (tiny: 8 cm), not merely above the 5 cm threshold
    assert heights[0] > tiny.sim.lift_height - 0.01
    assert info.unstable[0] == 0 and info.initial_contacts[0] == 0


def test_flat_tips_let_the_sphere_slip_at_mu_02_and_lift_it_at_mu_1(preset, flat_tips):
    tiny, sphere_hulls = preset
    ok, rise = grasp_only(build_model(sphere_hulls, *flat_tips, tiny, friction=0.2), tiny)
    assert not ok and rise < 0.01, f"2 x 0.2 x 1 N < 0.49 N must slip, rose {rise:.3f} m"
    ok, rise = grasp_only(build_model(sphere_hulls, *flat_tips, tiny, friction=1.0), tiny)
    assert ok and rise > tiny.sim.lift_height - 0.01, f"mu 1.0 must hold, rose {rise:.3f} m"


def test_a_dropped_object_ends_the_lift_once_no_finger_can_reach_it(preset, flat_tips):
    tiny, sphere_hulls = preset
    lift = lambda runner: runner.data.qpos[runner.ids.lift_qpos]  # noqa: E731
    slipping = GraspRunner(build_model(sphere_hulls, *flat_tips, tiny, friction=0.2), tiny)
    ok, rise, _ = slipping.grasp(0.0)
    # stopped part-way up, the fingers clear of the sphere on the floor
    assert not ok and rise < 0.01 and lift(slipping) < tiny.sim.lift_height - 0.01
    assert slipping.dropped(slipping.z_start + tiny.sim.success_min_height)
    held = GraspRunner(build_model(sphere_hulls, *flat_tips, tiny, friction=1.0), tiny)
    ok, _, _ = held.grasp(0.0)
    assert ok and lift(held) > tiny.sim.lift_height - 0.002  # a held grasp runs the whole lift
    assert not held.dropped(held.z_start + tiny.sim.success_min_height)


def test_flat_tips_at_mu_05_hold_the_sphere_but_drop_it_when_pushed_down(preset, flat_tips):
    tiny, sphere_hulls = preset
    # 2 x 0.5 x 1 N = 1 N holds 0.49 N but not 0.49 N + 1.5 N
    res = run_trials(build_model(sphere_hulls, *flat_tips, tiny, friction=0.5), tiny)
    assert res.outcome[0] == 1 and res.outcome[1] == 0, res.outcome
    assert res.heights[1] < tiny.sim.success_min_height


def test_effective_finger_object_friction_is_the_fingers_not_the_max(sphere_hulls, flat_tips, tiny):
    """MuJoCo would combine 0.2 (finger) and 0.5 (object) by max; priority makes it 0.2."""
    for mu in (None, 0.7):
        model = build_model(sphere_hulls, *flat_tips, tiny, friction=mu)
        runner = GraspRunner(model, tiny)
        ids = runner.ids
        runner.place(0.0)
        runner.advance(tiny.sim.steps(tiny.sim.settle_time))
        runner.approach()
        runner.data.ctrl[ids.grip_act] = ids.jaw_range[:, 0]
        runner.advance(tiny.sim.steps(tiny.sim.close_time))
        d = runner.data
        geoms = d.contact.geom[: d.ncon]
        friction = d.contact.friction[: d.ncon, 0]
        finger = np.isin(geoms, ids.all_finger_geoms).any(1)
        floor = (geoms == ids.floor_geom).any(1)
        assert finger.sum() >= 2 and floor.sum() >= 1
        want = tiny.sim.finger_friction if mu is None else mu
        np.testing.assert_allclose(friction[finger], want)
        np.testing.assert_allclose(friction[floor], tiny.sim.object_friction)
    # and the physics follows: at 0.2 the sphere slips (test above) though the object's own
    # coefficient, 0.5, would hold it (as the mu 0.5 test shows)


def test_feasible_fingers_that_miss_the_object_score_zero(preset):
    tiny, _ = preset
    low_box = box_tsdf([-0.0285, -0.0285, 0.0015], [0.0285, 0.0285, 0.015], tiny)
    # a finger band over the upper third of the cube: it closes above the low box
    band = box_tsdf([-0.03, 0.01, -0.01], [0.03, 0.03, 0.06], tiny)
    assert is_feasible(band, tiny)
    corners = np.stack(np.meshgrid([-0.0285, 0.0285], [-0.0285, 0.0285], [0.0015, 0.015],
                                   indexing="ij"), -1).reshape(-1, 3)
    hulls = pad_hulls([corners], 8, 32)
    out, info = evaluate_with_info([low_box], [band], [band], cfg=tiny, object_hulls=hulls, threads=1)
    assert not out.any()
    assert not info.infeasible[0] and not info.failed[0]
    # only the grasp trial ran, and it stopped once the lift was done
    one_grasp = sum(tiny.sim.steps(t) for t in (tiny.sim.settle_time, tiny.sim.close_time,
                                                 tiny.sim.lift_time, tiny.sim.hold_time))
    assert 0 < info.steps[0] < one_grasp


def test_infeasible_fingers_score_zero_without_simulating(sphere_tsdf, sphere_hulls, tiny):
    left, right = imprint_fingers(sphere_tsdf, tiny)
    empty = np.ones_like(left)  # no solid voxel
    floating = box_tsdf([-0.01, -0.01, 0.02], [0.01, 0.01, 0.04], tiny)  # not on the mount
    assert not is_feasible(empty, tiny) and not is_feasible(floating, tiny)
    out, info = evaluate_with_info([sphere_tsdf] * 2, [empty, left], [right, floating], cfg=tiny,
                                   object_hulls=sphere_hulls)
    assert not out.any()
    assert info.infeasible.all() and (info.steps == 0).all()
    assert info.results == [None, None]


def test_evaluation_is_deterministic_across_runs_and_threads(sphere_tsdf, sphere_hulls, tiny):
    imprint = imprint_fingers(sphere_tsdf, tiny)
    flat = wsg50_fingers(tiny)
    args = ([sphere_tsdf] * 3, [imprint[0], flat[0], imprint[0]],
            [imprint[1], flat[1], imprint[1]])
    runs = [evaluate_with_info(*args, cfg=tiny, object_hulls=sphere_hulls, threads=t)
            for t in (2, 1)]
    (out_a, info_a), (out_b, info_b) = runs
    np.testing.assert_array_equal(out_a, out_b)
    np.testing.assert_array_equal(info_a.steps, info_b.steps)
    for ra, rb in zip(info_a.results, info_b.results):
        np.testing.assert_array_equal(ra.heights, rb.heights)  # bit for bit, NaNs alike
    # the repeated candidate (0 and 2) gives the same result in the same batch
    np.testing.assert_array_equal(info_a.results[0].heights, info_a.results[2].heights)


def test_exploding_state_is_a_counted_failure_not_a_crash(sphere_hulls, flat_tips, tiny):
    # A speed limit below the jaws' closing speed (grip_force / damping = 0.1 m/s) makes every
    # grasp "explode" during the close: the same path as a real NaN or blow-up.
    strict = tiny.replace(sim=dataclasses.replace(tiny.sim, max_speed=0.05))
    res = run_trials(build_model(sphere_hulls, *flat_tips, strict, friction=1.0), strict)
    assert not res.outcome.any()
    assert res.unstable == 1 and np.isnan(res.heights[0])
    # a real blow-up: NaN in the state during a trial
    model = build_model(sphere_hulls, *flat_tips, tiny, friction=1.0)
    runner = GraspRunner(model, tiny)
    runner.place(0.0)
    runner.data.qvel[scene_ids(model).object_dof] = np.nan
    assert not runner.healthy()
    # a MuJoCo warning since the trial began (the runner reads the counters through a view)
    runner.place(0.0)
    assert runner.healthy()
    runner.data.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number += 1
    assert not runner.healthy()


def test_a_candidate_that_cannot_be_built_fails_alone(sphere_tsdf, sphere_hulls, tiny):
    flat = np.zeros((8, 32, 3), np.float32)
    flat[0, :4] = [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0]]
    counts = np.zeros(8, np.int32)
    counts[0] = 4
    bad = Hulls(flat, counts)
    left, right = wsg50_fingers(tiny)
    out, info = evaluate_with_info([sphere_tsdf] * 2, [left] * 2, [right] * 2, cfg=tiny,
                                   object_hulls=[bad, sphere_hulls])
    assert info.failed.tolist() == [True, False]
    assert "spans no volume" in info.errors[0]
    assert not out[0].any() and info.steps[0] == 0
    assert info.steps[1] > 0  # the second candidate was simulated (mu 0.2: it slips)


def test_evaluate_input_errors(sphere_tsdf, tiny):
    left, right = wsg50_fingers(tiny)
    with pytest.raises(ValueError, match="unknown backend"):
        evaluate([sphere_tsdf], [left], [right], backend="bullet", cfg=tiny)
    with pytest.raises(VolumeError, match=r"lefts\[1\]"):
        evaluate([sphere_tsdf] * 2, [left, left[:20]], [right] * 2, cfg=tiny)
    with pytest.raises(VolumeError, match=r"objects\[0\]"):
        evaluate([np.full_like(sphere_tsdf, np.nan)], [left], [right], cfg=tiny)
    bad = right.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(VolumeError, match=r"rights\[0\]"):
        evaluate([sphere_tsdf], [left], [bad], cfg=tiny)
    with pytest.raises(ValueError, match="one entry per candidate"):
        evaluate([sphere_tsdf] * 2, [left], [right], cfg=tiny)


def test_push_starts_from_the_restored_post_grasp_state(sphere_tsdf, sphere_hulls, tiny):
    """Every push trial begins where the grasp ended: same time, pose and contacts."""
    left, right = imprint_fingers(sphere_tsdf, tiny)
    model = build_model(sphere_hulls, finger_hulls(left, tiny), finger_hulls(right, tiny), tiny)
    runner = GraspRunner(model, tiny)
    ok, _, _ = runner.grasp(0.0)
    assert ok
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, runner.data, state, spec)
    qpos = runner.data.qpos.copy()
    runner.push(state, runner.z_start, (0.0, 0.0, -1.0))
    assert runner.data.time > state[0]
    mujoco.mj_setState(model, runner.data, state, spec)
    np.testing.assert_array_equal(runner.data.qpos, qpos)
    assert not runner.data.xfrc_applied.any()


def test_object_hulls_are_made_once_per_distinct_object(monkeypatch, sphere_tsdf, sphere_hulls,
                                                        tiny, tmp_path):
    """Without object_hulls, evaluate decomposes each distinct volume once (coacd is slow) and a
    decomposition error fails only the candidates of that object."""
    tiny = config.with_sim_preset(tiny, "reference")  # the coacd path
    from f2f_jax.errors import DecompositionError
    from f2f_jax.geometry import hull_pool  # where the coacd path calls object_hulls

    other = sphere_tsdf.copy()
    other[0, 0, 0] = 0.5  # a different volume, same shape
    calls = []

    def fake_object_hulls(obj, cfg, cache_dir=None, settings=None):
        calls.append(cache_dir)
        if obj[0, 0, 0] == 0.5:
            raise DecompositionError("object: coacd found nothing")
        return sphere_hulls

    monkeypatch.setattr(hull_pool, "object_hulls", fake_object_hulls)
    left, right = wsg50_fingers(tiny)
    # one thread: decomposition stays in this process (with more, worker processes run coacd)
    out, info = evaluate_with_info([sphere_tsdf, other, sphere_tsdf], [left] * 3, [right] * 3, cfg=tiny,
                                   cache_dir=tmp_path, progress=False, threads=1)
    assert calls == [tmp_path, tmp_path]
    assert info.failed.tolist() == [False, True, False]
    assert "coacd found nothing" in info.errors[1]
    assert info.steps[0] == info.steps[2] > 0


def test_fingers_that_close_on_nothing_stop_against_each_other(sphere_hulls, flat_tips, tiny):
    """The object 5 cm beside the jaws' path: flat tips closing from fully open meet nothing
    but each other.  The two jaws' fingers collide (as the original's self-collision), so they
    stop there, a tip's depth from the centre plane, instead of passing through each other to
    the jaws' joint limit."""
    model = build_model(sphere_hulls, *flat_tips, tiny, object_xy=(0.0, 0.05))
    runner = GraspRunner(model, tiny)
    runner.place(0.0)  # fully open; no approach: it would set the tips into each other
    runner.data.ctrl[runner.ids.grip_act] = runner.ids.jaw_range[:, 0]
    runner.advance(tiny.sim.steps(1.6))  # 0.1 m/s: 11 cm open to the -3 cm limit and rest
    openings = runner.data.qpos[runner.ids.jaw_qpos].copy()
    assert (openings > 0.01).all(), openings  # 3 cm tips: they meet ~3 cm from it


def test_a_batch_makes_each_distinct_fingers_pieces_once(sphere_tsdf, sphere_hulls, tiny, monkeypatch):
    """The WSG50 pads beside every object of a batch (a dataset's baseline rows) are meshed once:
    their pieces cost as much as the failed grasp's whole simulation."""
    from f2f_jax.geometry import finger_tiling

    left, right = wsg50_fingers(tiny)
    made = []
    real = finger_tiling.finger_hulls
    monkeypatch.setattr(finger_tiling, "_memo", type(finger_tiling._memo)())
    monkeypatch.setattr(finger_tiling, "finger_hulls", lambda *a, **k: made.append(1) or real(*a, **k))
    out = evaluate([sphere_tsdf] * 3, [left] * 3, [right] * 3, cfg=tiny, object_hulls=sphere_hulls,
                   threads=1)
    assert len(made) == len({left.tobytes(), right.tobytes()})
    assert not out.any(), f"flat pads cannot hold the sphere at friction 0.2: {out}"


def test_a_turned_grasp_starts_where_the_first_settle_left_the_object_turned(sphere_hulls, flat_tips):
    """``shared_settle``: the six turned grasps skip their settle and start from the yaw-0 settle's
    pose turned about the vertical.  The floor does not change under that turn, so the pose must
    be the one a settle of the turned object reaches (the coarse sphere hull tips and rolls when
    set down, so the settle does move it)."""
    cfg = config.with_sim_preset(config.tiny(), "fast")
    assert cfg.sim.shared_settle
    model = build_model(sphere_hulls, *flat_tips, cfg)
    runner = GraspRunner(model, cfg)
    runner.grasp(0.0)  # records the settled pose
    ids, d, yaw = runner.ids, runner.data, 0.5
    q = ids.object_qpos
    runner.place(yaw)
    placed = d.qpos[q: q + 7].copy()
    runner.turn_settled(yaw)
    turned = d.qpos[q: q + 7].copy()
    runner.place(yaw)
    runner.advance(cfg.sim.steps(cfg.sim.settle_time), until_rest=True)
    settled = d.qpos[q: q + 7].copy()

    def angle(a, b):  # radians between two unit quaternions
        return 2 * np.arccos(min(1.0, abs(float(np.dot(a, b)))))

    moved = np.linalg.norm(settled[:3] - placed[:3]) + angle(settled[3:], placed[3:]) * 0.03
    assert moved > 2e-4, f"the settle hardly moved the sphere ({moved:.2e}): the test shows nothing"
    np.testing.assert_allclose(turned[:3], settled[:3], atol=1e-4)
    assert angle(turned[3:], settled[3:]) < np.radians(0.5)
