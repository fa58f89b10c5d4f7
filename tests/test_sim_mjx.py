"""The batched MJX backend against plain MuJoCo on the clear cases (tiny phases; one compile)."""

import jax
import numpy as np
import pytest

from f2f_jax.geometry import imprint_fingers, wsg50_fingers
from f2f_jax.geometry.coacd_pieces import object_hulls
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.sim import mjx_batch, mjx_collision
from f2f_jax.sim.protocol import run_trials
from f2f_jax.sim.scene import build_model


@pytest.fixture(scope="module")
def sphere_models(sphere_tsdf, tiny_cfg):
    hulls = object_hulls(sphere_tsdf, tiny_cfg)
    models = []
    for left, right in (imprint_fingers(sphere_tsdf), wsg50_fingers()):
        models.append(build_model(hulls, finger_hulls(left, tiny_cfg), finger_hulls(right, tiny_cfg),
                                  tiny_cfg, pad_collides=True, max_geom_pairs=mjx_collision.MAX_GEOM_PAIRS,
                                  max_contact_points=mjx_collision.MAX_CONTACT_POINTS))
    return models


def test_convex_data_has_fixed_sizes_for_any_piece():
    sizes = mjx_collision.ConvexSizes.for_vertices(32)
    rng = np.random.default_rng(0)
    shapes = set()
    for n in (4, 8, 32):
        c = mjx_collision.convex_data(rng.normal(size=(n, 3)), sizes)
        shapes.add(tuple(np.shape(x) for x in (c.vert, c.face, c.face_normal, c.edge, c.edge_face_normal)))
        # outward unit normals: every vertex lies on or behind every face plane
        d = np.einsum("fk,vk->fv", c.face_normal, c.vert) - np.einsum("fk,fk->f", c.face_normal, c.face[:, 0])[:, None]
        assert d.max() < 1e-5
    assert len(shapes) == 1
    box = mjx_collision.convex_data(np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T, sizes)
    assert len({tuple(np.round(n, 6)) for n in box.face_normal}) == 6  # coplanar triangles merged


@pytest.mark.slow
def test_mjx_grasp_agrees_with_mujoco_and_compiles_once(sphere_models, tiny_cfg):
    cpu = [run_trials(m, tiny_cfg).outcome[0] for m in sphere_models]
    assert cpu == [1, 0]  # imprint holds the sphere, flat tips at mu 0.2 drop it
    sim = mjx_batch.MjxGraspSimulator(sphere_models[0], tiny_cfg)
    batch = sim.batch(sphere_models)
    held, rise, bad, _, _ = sim._call("grasp", 2, batch.fields, batch.convex, batch.planes,
                                      np.zeros(2, np.float32))
    assert list(np.asarray(held)) == [True, False]
    assert not np.asarray(bad).any()
    assert np.asarray(rise)[0] > tiny_cfg.sim.success_min_height
    # A new batch of other candidates has the same array structure: the program is reused.
    again = sim.batch(sphere_models[::-1])
    struct = lambda b: jax.tree_util.tree_map(lambda x: (np.shape(x), np.asarray(x).dtype),  # noqa: E731
                                              (b.fields, b.convex, b.planes))
    assert struct(again) == struct(batch)
    assert sim._program("grasp", 2)._cache_size() == 1


def test_evaluate_mjx_builds_each_feasible_candidate_and_maps_outcomes_back(monkeypatch, sphere_tsdf,
                                                                           tiny_cfg):
    """The host side of evaluate(backend="mjx"): models for the feasible candidates only, in input
    order, their outcomes written back to their rows (the batch itself is mocked: compiling it
    costs minutes on a CPU and is tested above)."""
    from f2f_jax.geometry import imprint_fingers
    from f2f_jax.sim import evaluate_with_info

    seen = []

    def fake_batch(models, cfg):
        seen.extend(models)
        out = np.zeros((len(models), 11), np.uint8)
        out[:, 0] = np.arange(1, len(models) + 1)  # tells the rows apart
        return dict(outcome=out, steps=np.full(len(models), 7), unstable=np.zeros(len(models)))

    monkeypatch.setattr(mjx_batch, "evaluate_models", fake_batch)
    left, right = imprint_fingers(sphere_tsdf, tiny_cfg.geometry)
    empty = np.ones_like(left)  # infeasible: never built
    out, info = evaluate_with_info([sphere_tsdf] * 3, [left, empty, left], [right] * 3, cfg=tiny_cfg,
                                   backend="mjx")
    assert len(seen) == 2 and all(m.ngeom == seen[0].ngeom for m in seen)
    assert out[:, 0].tolist() == [1, 0, 2] and info.infeasible.tolist() == [False, True, False]
    assert info.steps.tolist() == [7, 0, 7]
