"""The height-map generator (``net.generator = "heights"``): its fingers are the imprints' form, it
learns unseen objects' imprints in both fingers' frames, its candidates are smooth variations of
its own design, and it trains, co-trains and searches through the same calls as the paper's."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.errors import ConfigError, F2FError
from f2f_jax.geometry import imprint_fingers
from f2f_jax.geometry.finger_tiling import finger_height_map
from f2f_jax.nets import HeightGenerator, generator_module, heights_to_tsdf, tsdf_heights
from f2f_jax.nets.inference import TrainedNets, code_noise, generate, propose
from f2f_jax.train import steps as S
from f2f_jax.train.state import generator_optimizer, init_fitness, init_generator, new_state

R = 40


def _ball(centre_vox, radius_vox: float) -> np.ndarray:
    """Object TSDF of a ball (centre in voxel indices), truncated at 5 voxels, negative inside."""
    idx = np.indices((R, R, R), np.float32).transpose(1, 2, 3, 0)
    d = np.linalg.norm(idx - np.asarray(centre_vox, np.float32), axis=-1) - radius_vox
    return np.clip(d / 5.0, -1.0, 1.0).astype(np.float32)


def _balls(n: int, seed: int) -> np.ndarray:
    """n balls of radius 6-12 voxels resting on the floor (z = 0) at random places in x and y
    (y: the fingers' u).  Resting: the imprints leave the columns under a floating object empty."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        radius = rng.uniform(6, 12)
        out.append(_ball((rng.uniform(16, 24), rng.uniform(12, 28), radius - 0.3), radius))
    return np.stack(out)


@pytest.fixture(scope="module")
def cfg():
    tiny = config.tiny()
    return tiny.replace(net=dataclasses.replace(tiny.net, generator="heights", height_channels=(32, 32, 32)),
                        train=dataclasses.replace(tiny.train, lr=3e-3))


@pytest.fixture(scope="module")
def train_set():
    objs = _balls(24, seed=0)
    pairs = [imprint_fingers(o) for o in objs]
    return objs, np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


@pytest.fixture(scope="module")
def pretrained(cfg, train_set):
    """The height generator after 400 imprint steps on the 24 training balls (batch 8)."""
    objs, lefts, rights = train_set
    state = S.replicate(new_state(init_generator(cfg), S.generator_optimizer(cfg)))
    step = S.gn_imprint_step(cfg)
    rng = np.random.default_rng(0)
    losses = []
    for _ in range(400):
        b = rng.choice(len(objs), 8, replace=False)
        state, m = step(state, *S.shard(objs[b], lefts[b], rights[b]))
        losses.append(float(m["loss"]))
    return state, losses


def test_height_maps_are_the_geometry_s_and_invert_exactly(train_set):
    objs, lefts, rights = train_set
    g = config.GeometryConfig()
    fingers = np.concatenate([lefts[:4], rights[:4]])
    heights = np.asarray(tsdf_heights(jnp.asarray(fingers)))
    expected = np.stack([finger_height_map(f, g) for f in fingers]) / g.voxel_size
    np.testing.assert_allclose(heights, expected, atol=1e-4)
    rebuilt = np.asarray(heights_to_tsdf(jnp.asarray(heights), g.truncation_voxels))
    # the imprints' solid, voxel for voxel, and the same height maps read back
    np.testing.assert_array_equal(rebuilt < 0, fingers < 0)
    below_top = heights <= R - 1
    np.testing.assert_allclose(np.asarray(tsdf_heights(jnp.asarray(rebuilt)))[below_top],
                               heights[below_top], atol=1e-4)
    # an empty column (height < half a voxel) has no solid; heights are differentiable
    empty = np.asarray(heights_to_tsdf(jnp.zeros((2, R, R)) + 0.3, 5.0))
    assert (empty > 0).all()
    grad = jax.grad(lambda h: heights_to_tsdf(h, 5.0).sum())(jnp.full((1, R, R), 12.3))
    assert float(jnp.abs(grad).min()) > 0


def test_height_generator_learns_unseen_imprints_in_both_fingers_frames(cfg, pretrained):
    """Column-local by design: after 400 steps on 24 balls, the columns that face 6 unseen balls
    come out within ~2 voxels of their imprints', left and right (~6 untrained); were the right
    finger's map not flipped into its own frame (u along -y), its columns would need the object's
    far side and could not be learnt."""
    state, losses = pretrained
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])
    objs = _balls(6, seed=1)
    pairs = [imprint_fingers(o) for o in objs]
    lefts, rights = generate(cfg.net, state.variables, jnp.asarray(objs))
    for k, (got, want) in enumerate(((lefts, [p[0] for p in pairs]), (rights, [p[1] for p in pairs]))):
        want = np.asarray(tsdf_heights(jnp.asarray(np.stack(want))))
        facing = want < R - 1  # columns that meet the ball; the others are full
        err = np.abs(np.asarray(tsdf_heights(got)) - want)[facing]
        assert err.mean() < 2.5, ("left", "right")[k] + f" finger: {err.mean():.2f} voxels"
    assert set(state.params) == {"embedding"} and not state.batch_stats


def test_height_candidates_are_smooth_variations_of_the_generator_s_own(cfg, pretrained):
    state, _ = pretrained
    nets = TrainedNets(cfg, state.variables, init_fitness(cfg))
    objs = _balls(3, seed=2)
    lefts, rights = propose(nets, objs, jax.random.key(0), 5, noise=0.2)
    assert lefts.shape == rights.shape == (3, 5, R, R, R)
    own_l, own_r = generate(cfg.net, state.variables, jnp.asarray(objs))
    np.testing.assert_allclose(lefts[:, 0], np.asarray(own_l), atol=1e-6)
    np.testing.assert_allclose(rights[:, 0], np.asarray(own_r), atol=1e-6)
    assert all(not np.array_equal(lefts[i, 0], lefts[i, k]) for i in range(3) for k in range(1, 5))
    # the noise on the height codes: ~2 voxels at noise 0.2, a field, not per-column noise
    field = np.asarray(code_noise(cfg.net, jax.random.key(1), (64, 2), 0.2)).reshape(64, 2, R, R)
    spread = field.std()
    assert 1.0 < spread < 3.0, spread
    assert np.abs(np.diff(field, axis=-1)).mean() < 0.2 * spread
    assert np.abs(np.diff(field, axis=-2)).mean() < 0.2 * spread
    assert abs(np.corrcoef(field[:, 0].ravel(), field[:, 1].ravel())[0, 1]) < 0.1  # fingers apart
    again, _ = propose(nets, objs, jax.random.key(0), 5, noise=0.2)
    np.testing.assert_array_equal(again, lefts)


def test_height_generator_co_trains_against_the_fitness_net(cfg, train_set, pretrained):
    objs, _, _ = train_set
    state, _ = pretrained
    fit = init_fitness(cfg, 5)
    # at co-training's own rate (a run steps the generator at generator_lr, 1e-4 by default), from
    # a fresh Adam state: the pretraining's moments, kept, push the steps along the imprint loss's
    # direction for a while (on CI's and an AVX2-only CPU they outweighed this untrained net's small
    # gradient for all 8 steps), which is not what this test asks about
    cotrain = cfg.replace(train=dataclasses.replace(cfg.train, lr=config.get("default").train.generator_lr))
    step = S.gn_fitness_step(cotrain)
    before = jax.tree.map(np.array, state.params)
    st = jax.tree.map(jnp.copy, state)
    st = st.replace(opt_state=generator_optimizer(cotrain).init(st.params))
    losses = []
    for _ in range(8):
        st, m = step(st, fit, S.shard(objs[:8]))
        losses.append(float(m["loss"]))
    assert losses[-1] < losses[0], losses
    assert set(m) == {"loss", "fitness"} and m["fitness"].shape == (11,)
    changed = [not np.array_equal(a, np.asarray(b)) for a, b in
               zip(jax.tree.leaves(before), jax.tree.leaves(st.params))]
    assert all(changed)


def test_the_teachers_generator_steps_at_teacher_lr(cfg, train_set, pretrained):
    """``train.teacher_lr`` is the rate of the generator's steps onto the teacher's targets: from
    one Adam state, one step at a tenth of the rate moves the weights a tenth as far (Adam's first
    step is the rate times the gradient's sign), and None steps at ``train.lr``."""
    from f2f_jax.train.teacher import teacher_generator_cfg

    objs, lefts, rights = train_set
    state, _ = pretrained
    start = state.replace(opt_state=generator_optimizer(cfg).init(state.params))
    moved = {}
    for rate in (None, cfg.train.lr / 10):
        teach = teacher_generator_cfg(cfg.replace(train=dataclasses.replace(cfg.train, teacher_lr=rate)))
        st, _ = S.gn_imprint_step(teach)(jax.tree.map(jnp.copy, start), *S.shard(objs[:8], lefts[:8],
                                                                                  rights[:8]))
        moved[rate] = sum(float(np.abs(np.asarray(a) - np.asarray(b)).sum())
                          for a, b in zip(jax.tree.leaves(start.params), jax.tree.leaves(st.params)))
    assert moved[None] > 0
    assert 0.08 < moved[cfg.train.lr / 10] / moved[None] < 0.12, moved


def test_random_embeddings_of_heights_and_settings_are_checked(cfg):
    from f2f_jax.geometry.fingers import feasibility_report
    from f2f_jax.tables import random_embedding_designer
    from f2f_jax.train.cotrain import CoTrainRun

    nets = TrainedNets(cfg, init_generator(cfg), init_fitness(cfg))
    left, right = random_embedding_designer(nets, jax.random.key(1), samples=2, steps=2)(_balls(2, 3))
    assert left.shape == right.shape == (2, R, R, R)
    assert all(feasibility_report(f, cfg.geometry)["components"] <= 1 for f in (*left, *right))
    assert isinstance(generator_module(cfg.net), HeightGenerator)
    with pytest.raises(ConfigError, match="net.generator must be one of"):
        generator_module(dataclasses.replace(cfg.net, generator="voxels"))
    bad = cfg.replace(net=dataclasses.replace(cfg.net, generator="voxels"))
    with pytest.raises(F2FError, match="net.generator must be one of"):
        CoTrainRun("/nonexistent-run", bad)
    # its fingers are truncated as the geometry's default (the imprints'): another truncation is refused
    bad = cfg.replace(geometry=dataclasses.replace(cfg.geometry, truncation_voxels=3.0))
    with pytest.raises(F2FError, match="geometry.truncation_voxels must be 5.0"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=dataclasses.replace(cfg.train, gn_passes=0))
    with pytest.raises(F2FError, match="gn_passes"):
        CoTrainRun("/nonexistent-run", bad)


@pytest.mark.slow
def test_a_height_generator_run_trains_resumes_and_designs(tmp_path):
    """A tiny co-training run with the height-map generator: its pretraining loss (voxels of L1)
    falls, its checkpoints load as a HeightGenerator's, and design() searches its candidates."""
    import json

    import f2f_jax
    from f2f_jax.train.checkpoint import load_trained_nets
    from f2f_jax.train.cotrain import CoTrainRun

    tiny = config.tiny()
    cfg = tiny.replace(net=dataclasses.replace(tiny.net, generator="heights"),
                       train=dataclasses.replace(tiny.train, gn_passes=4))
    run_dir = tmp_path / "heights"
    CoTrainRun(run_dir, cfg, config_name="tiny", progress=False).run(2)
    log = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    gn = [r for r in log if r.get("stage") == "gn" and "loss" in r and r.get("cycle") == 0]
    assert len(gn) == cfg.train.gn_epochs and gn[-1]["loss"] < gn[0]["loss"], gn
    assert gn[0]["steps"] % 4 == 0 and gn[0]["steps"] >= 4  # gn_passes passes per epoch
    nets = load_trained_nets(run_dir)
    assert nets.config.net.generator == "heights" and set(nets.generator["params"]) == {"embedding"}
    pairs = f2f_jax.design(_balls(2, 4), params=nets, candidates=4, verify=True, imprint=False,
                           progress=False)
    for pair in pairs:
        assert pair.simulated.shape == (11,) and pair.n_candidates == 4
        assert pair.origin in ("generator", "generator + height noise")
