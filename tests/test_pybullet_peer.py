"""The PyBullet peer (the original Fit2Form protocol): clear cases and its step accounting.

A full evaluation of a held grasp is ~20k PyBullet steps (about 1 s on one core); the module
runs in about 6 s.
"""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("pybullet")

from f2f_jax.bench import pybullet_runs as peer  # noqa: E402
from f2f_jax.geometry import imprint_fingers, wsg50_fingers  # noqa: E402
from f2f_jax.geometry.finger_tiling import finger_hulls  # noqa: E402
from f2f_jax.geometry.hulls import Hulls

PROTO = peer.PROTOCOL
# Fewest steps one grasp attempt can take: settle, open, lower (at least one step), close,
# lift (at least one step), success check.
MIN_GRASP_STEPS = PROTO.settle_min_steps + 2 * PROTO.jaw_motion_steps + 2 + PROTO.check_steps
PUSH_TRIAL_STEPS = PROTO.push_steps + PROTO.push_hold_steps + PROTO.check_steps


@pytest.fixture(scope="module")
def sphere_object(sphere_tsdf, cfg):
    # a sphere is convex: one hull of its surface is its exact collision shape (up to 32 vertices)
    return peer.convex_object_hulls(sphere_tsdf, cfg)


@pytest.fixture(scope="module")
def sphere_imprint(sphere_tsdf, cfg):
    left, right = imprint_fingers(sphere_tsdf, cfg)
    return finger_hulls(left, cfg), finger_hulls(right, cfg)


def beside_the_gripper(hulls: Hulls, cfg) -> Hulls:
    """The same object moved two cube widths along y: the fingers close on empty space."""
    shift = np.array([0.0, 2 * cfg.geometry.cube_size, 0.0], np.float32)
    return Hulls(np.where(hulls.valid[:, None, None], hulls.vertices + shift, 0.0), hulls.counts)


def test_sphere_between_its_imprint_fingers_is_lifted_and_held(sphere_object, sphere_imprint):
    out = peer.simulate_original(sphere_object, *sphere_imprint)
    assert out.shape == (11,) and out.dtype == np.uint8
    assert out[0] == 1, f"imprint fingers dropped the sphere: {out}"
    assert out[1:5].all(), f"a 1.5 N push broke the imprint cage: {out}"
    assert out[5:].sum() >= 4, f"most turned spheres should be grasped again: {out}"


def test_fingers_that_miss_score_zero_after_one_attempt(cfg, sphere_object, sphere_imprint):
    outcomes, stats = peer.evaluate_original(
        [beside_the_gripper(sphere_object, cfg), sphere_object], [sphere_imprint[0]] * 2,
        [sphere_imprint[1]] * 2, cfg=cfg)
    assert outcomes.shape == (2, 11)
    assert not outcomes[0].any(), f"a finger that misses scored {outcomes[0]}"
    assert outcomes[1, 0] == 1
    miss, held = stats["steps_per_evaluation"]
    assert stats["steps"] == miss + held and stats["evaluations"] == 2
    # one attempt only (no pushes, no turned regrasps after a failed grasp), and no move gave up
    # after max_move_steps: settling and the two gripper moves take a few hundred steps each
    assert MIN_GRASP_STEPS <= miss < 3 * MIN_GRASP_STEPS
    # a held grasp runs all 11 trials: 7 grasp attempts and 4 pushes
    assert held >= 7 * MIN_GRASP_STEPS + 4 * PUSH_TRIAL_STEPS
    assert stats["unstable"] == 0
    assert stats["seconds"] >= stats["build_seconds"] > 0
    np.testing.assert_allclose(stats["steps_per_second"], stats["steps"] / stats["seconds"])


def test_flat_fingers_need_more_than_the_papers_friction(cfg, sphere_object):
    """Flat tips squeeze with 2 x 0.2 x 1.0 N < 0.49 N weight: the sphere slips at the paper's
    friction and is lifted when the finger-object coefficient is 1.0 (Bullet multiplies the
    object's coefficient by the fingers' 1.0)."""
    left, right = (finger_hulls(f, cfg) for f in wsg50_fingers(cfg))
    slippery = peer.simulate_original(sphere_object, left, right, cfg=cfg)
    grippy_cfg = cfg.replace(sim=dataclasses.replace(cfg.sim, finger_friction=1.0))
    with peer.OriginalSession(grippy_cfg) as world:
        grippy = world.simulate(sphere_object, left, right)
    assert slippery[0] == 0 and not slippery.any()
    assert grippy[0] == 1


def test_empty_finger_scores_zero_without_simulating(cfg, sphere_object, sphere_imprint):
    empty = Hulls(np.zeros((cfg.geometry.finger_hulls, cfg.geometry.hull_vertices, 3), np.float32),
                  np.zeros(cfg.geometry.finger_hulls, np.int32))
    outcomes, stats = peer.evaluate_original([sphere_object], [empty], [sphere_imprint[1]], cfg=cfg)
    assert not outcomes.any()
    assert stats["steps"] == 0


def test_a_push_beyond_the_friction_grip_breaks_the_hold(cfg, sphere_object):
    """Flat tips at friction 1.0 hold the sphere by 2 x 1.0 x 1.0 N of friction: enough for its
    0.49 N weight, not for 5 N pushes in the plane of the pads (down, and down-sideways along y).
    S3 and S4 also press the sphere into one pad, which raises the normal force: not asserted."""
    left, right = (finger_hulls(f, cfg) for f in wsg50_fingers(cfg))
    pushy = cfg.replace(sim=dataclasses.replace(cfg.sim, finger_friction=1.0, push_force=5.0))
    out = peer.simulate_original(sphere_object, left, right, cfg=pushy)
    assert out[0] == 1
    assert not out[1:3].any(), f"5 N pushes should break a 2 N friction grip: {out}"


def test_self_collision_switch_stops_fingers_that_meet_outside_the_object(cfg):
    """The original's gripper had self-collision on: imprint fingers of a 1 cm slab then meet
    each other before they reach it.  The peer's default lets them pass through each other."""
    import trimesh

    from f2f_jax.geometry import mesh_to_tsdf

    slab = mesh_to_tsdf(trimesh.creation.box((0.01, 0.05, 0.05)), cfg.geometry)
    left, right = (finger_hulls(f, cfg) for f in imprint_fingers(slab, cfg))
    closed = {}
    for collide in (False, True):
        proto = dataclasses.replace(PROTO, self_collision=collide)
        with peer.OriginalSession(cfg, proto) as world:
            g = world.add_gripper(left, right)
            world._jaws(g, g.strokes)
            closed[collide] = [world.api.getJointState(g.body, j)[0] for j in g.jaws]
    # jaw positions: travel inwards, in the x10 world (0.1 = 1 cm); colliding fingers travel less
    assert min(closed[False]) > max(closed[True]) + 0.1, closed


def test_engine_switches_reach_bullet_and_the_default_leaves_bullets_own(cfg):
    """The peer's default run is Bullet as the original had it (one 1/240 s step, 50 solver
    iterations); the ablations' sub-steps and iterations must reach the engine."""
    with peer.OriginalSession(cfg) as world:
        default = world.api.getPhysicsEngineParameters()
    proto = dataclasses.replace(PROTO, substeps=4, solver_iterations=120)
    with peer.OriginalSession(cfg, proto) as world:
        changed = world.api.getPhysicsEngineParameters()
    assert default["numSubSteps"] == 0 and default["numSolverIterations"] == 50, default
    assert default["fixedTimeStep"] == pytest.approx(1 / 240)
    assert changed["numSubSteps"] == 4 and changed["numSolverIterations"] == 120, changed
    assert changed["fixedTimeStep"] == pytest.approx(1 / 240)  # a step is still 1/240 s


@pytest.mark.slow
def test_a_recorded_run_draws_the_same_outcome_as_a_plain_one(cfg, sphere_object, sphere_imprint,
                                                             tmp_path):
    """render_original records the panels of f2f_jax.sim.view without changing the physics:
    same outcome as simulate_original, one panel per trial after settled and closed."""
    from f2f_jax.sim import view

    plain = peer.simulate_original(sphere_object, *sphere_imprint, cfg=cfg)
    strip = peer.render_original(sphere_object, *sphere_imprint, cfg=cfg)
    np.testing.assert_array_equal(strip.outcome, plain)
    assert [name.split(":")[0] for _, name in strip.panels] == [
        "settled", "closed", "grasp", "S1", "S2", "S3", "S4",
        "R-30", "R-20", "R-10", "R+10", "R+20", "R+30"]
    lifted = strip.panels[2][0].geom_xpos[:, 2]  # metres, out of Bullet's x10 world
    assert 0.05 < lifted.max() < 0.3
    out = tmp_path / "both.png"
    view.draw_strips([strip, strip], out, "twice")
    assert out.stat().st_size > 10_000
