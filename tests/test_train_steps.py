"""Jitted training steps: losses fall, frozen parts stay frozen, state is donated, steps compile once,
and the same steps run data-parallel over several devices."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.geometry import imprint_fingers
from f2f_jax.train import steps as S
from f2f_jax.train.state import (
    init_autoencoder,
    init_fitness,
    init_generator,
    new_state,
    optimizer,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cfg():
    tiny = config.tiny()  # a higher learning rate than the runs': a few steps must show learning
    return tiny.replace(train=dataclasses.replace(tiny.train, lr=3e-3))


@pytest.fixture(scope="module")
def volumes(sphere_tsdf):
    """Four object volumes (sphere, shifted spheres) and their imprint fingers."""
    objs = np.stack([sphere_tsdf, np.roll(sphere_tsdf, 3, 0), np.roll(sphere_tsdf, -3, 1),
                     np.roll(sphere_tsdf, 2, 2)]).astype(np.float32)
    pairs = [imprint_fingers(o) for o in objs]
    return objs, np.stack([a for a, _ in pairs]), np.stack([b for _, b in pairs])


def _run(step, state, args, n):
    losses = []
    for _ in range(n):
        state, m = step(state, *args)
        losses.append(float(m["loss"]))
    return state, losses


@pytest.fixture(scope="module")
def trained_fn(cfg, volumes):
    """A fitness net fitted for 30 steps on two holding and two failing triples."""
    objs, lefts, rights = volumes
    y = np.zeros((4, 11), np.float32)
    y[:2] = 1.0
    fn = S.replicate(new_state(init_fitness(cfg), optimizer(cfg.train)))
    fn, losses = _run(S.fn_step(cfg), fn, S.shard(objs, lefts, rights, y), 30)
    return fn, losses, y


def test_ae_and_fitness_losses_fall(cfg, volumes, trained_fn):
    objs, lefts, rights = volumes
    ae = new_state(init_autoencoder(cfg), optimizer(cfg.train))
    step = S.ae_step(cfg)
    old_params = ae.params
    ae, losses = _run(step, ae, (jnp.asarray(objs), jax.random.key(0)), 15)
    assert losses[-1] < 0.9 * losses[0], losses
    with pytest.raises(RuntimeError, match="deleted"):  # the state was donated to the step
        np.asarray(jax.tree.leaves(old_params)[0])
    assert step._cache_size() == 1  # one compile for 15 steps

    fn, losses, y = trained_fn  # two triples that hold, two that do not
    assert S.fn_step(cfg)._cache_size() == 1  # replicated state, sharded batches: one program
    assert losses[-1] < 0.65 * losses[0], losses
    bce, prob = S.fn_eval(cfg)(fn.variables, objs, lefts, rights, y)
    prob = np.asarray(prob)  # evaluation mode (running statistics) ranks them as trained
    assert prob[:2].mean(1).min() > prob[2:].mean(1).max(), prob.mean(1)


def test_generator_steps_train_only_the_embedding(cfg, volumes, trained_fn):
    objs, lefts, rights = volumes
    gn = new_state(init_generator(cfg), S.generator_optimizer(cfg))
    before = jax.tree.map(np.array, gn.params)
    gn, losses = _run(S.gn_imprint_step(cfg), gn, (objs, lefts, rights), 10)
    assert losses[-1] < losses[0], losses
    fit = trained_fn[0].variables
    gn, g_losses = _run(S.gn_fitness_step(cfg), gn, (fit, objs), 10)
    assert -1.0 <= min(g_losses) and max(g_losses) <= 0.0
    assert g_losses[-1] < g_losses[0], g_losses  # the generator raises the predicted fitness
    for part in ("encoder", "decoder"):
        for a, b in zip(jax.tree.leaves(before[part]), jax.tree.leaves(gn.params[part])):
            np.testing.assert_array_equal(a, np.asarray(b))
    changed = [not np.array_equal(a, np.asarray(b)) for a, b in
               zip(jax.tree.leaves(before["embedding"]), jax.tree.leaves(gn.params["embedding"]))]
    assert all(changed)


@pytest.mark.slow
def test_steps_run_data_parallel_on_two_devices():
    """Two host devices (XLA flag): the batch is split over them and every stage still runs."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "train_throughput.py"), "--config",
                          "tiny", "--batch", "4", "--steps", "1"], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "x 2" in out.stdout  # two devices seen
    assert out.stdout.count("samples/s") == 4
