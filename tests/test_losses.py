"""Losses: values against hand formulas, masks, objective selection."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from f2f_jax.config import TRIAL_NAMES
from f2f_jax.train.losses import (
    OBJECTIVE_MASKS,
    fitness_loss,
    generator_loss,
    kl_divergence,
    vae_loss,
)


def _bce(logits, targets):
    p = 1.0 / (1.0 + np.exp(-logits))
    return -(targets * np.log(p) + (1 - targets) * np.log(1 - p))


def test_fitness_loss_perfect_and_uninformed():
    targets = np.random.default_rng(0).integers(0, 2, (6, 11)).astype(np.uint8)
    perfect = np.where(targets == 1, 30.0, -30.0).astype(np.float32)
    assert float(fitness_loss(jnp.asarray(perfect), jnp.asarray(targets))) < 1e-6
    wrong = -perfect
    assert float(fitness_loss(jnp.asarray(wrong), jnp.asarray(targets))) > 29.0
    zeros = jnp.zeros((6, 11))
    np.testing.assert_allclose(float(fitness_loss(zeros, jnp.asarray(targets))), np.log(2), rtol=1e-6)


def test_fitness_loss_matches_formula_and_mask():
    rng = np.random.default_rng(1)
    logits = rng.normal(size=(5, 11)).astype(np.float32)
    targets = rng.integers(0, 2, (5, 11)).astype(np.float32)
    ref = _bce(logits, targets)
    np.testing.assert_allclose(float(fitness_loss(logits, targets)), ref.mean(), rtol=1e-5)
    # a row mask ([B, 1]): padded rows do not count, whatever their targets
    rows = np.array([1, 1, 0, 1, 0], np.float32)[:, None]
    got = float(fitness_loss(logits, targets, rows))
    np.testing.assert_allclose(got, ref[rows[:, 0] == 1].mean(), rtol=1e-5)
    flipped = targets.copy()
    flipped[2] = 1 - flipped[2]
    np.testing.assert_allclose(float(fitness_loss(logits, flipped, rows)), got, rtol=1e-6)
    # an output mask ([11]): only the grasp column
    grasp = np.zeros(11, np.float32)
    grasp[0] = 1
    np.testing.assert_allclose(float(fitness_loss(logits, targets, grasp)), ref[:, 0].mean(),
                               rtol=1e-5)


def test_objective_masks_select_the_paper_outputs():
    names = np.array(TRIAL_NAMES)
    assert list(names[OBJECTIVE_MASKS["GS"]]) == ["grasp"]
    assert list(names[OBJECTIVE_MASKS["GS+S"]]) == ["grasp", "S1", "S2", "S3", "S4"]
    assert list(names[OBJECTIVE_MASKS["GS+R"]]) == ["grasp", "R-30", "R-20", "R-10", "R+10",
                                                    "R+20", "R+30"]
    assert OBJECTIVE_MASKS["full"].all()


def test_generator_loss_uses_selected_outputs_only():
    # certain success on grasp only, certain failure elsewhere
    logits = jnp.full((3, 11), -40.0).at[:, 0].set(40.0)
    assert float(generator_loss(logits, "GS")) == pytest.approx(-1.0, abs=1e-6)
    assert float(generator_loss(logits, "GS+S")) == pytest.approx(-1 / 5, abs=1e-6)
    assert float(generator_loss(logits, "GS+R")) == pytest.approx(-1 / 7, abs=1e-6)
    assert float(generator_loss(logits, "full")) == pytest.approx(-1 / 11, abs=1e-6)
    rng = np.random.default_rng(2)
    x = rng.normal(size=(4, 11)).astype(np.float32)
    for name, mask in OBJECTIVE_MASKS.items():
        ref = -np.mean(1 / (1 + np.exp(-x[:, mask])))
        assert float(generator_loss(jnp.asarray(x), name)) == pytest.approx(ref, rel=1e-5)
        # no gradient reaches the outputs an ablation ignores
        grad = np.asarray(jax.grad(generator_loss)(jnp.asarray(x), name))
        assert np.all(grad[:, ~mask] == 0) and np.all(grad[:, mask] < 0)
    with pytest.raises(ValueError, match="unknown objectives"):
        generator_loss(jnp.asarray(x), "GS+X")


def test_vae_loss_and_kl():
    rng = np.random.default_rng(3)
    recon = rng.uniform(-1, 1, (2, 40, 40, 40)).astype(np.float32)
    target = rng.uniform(-1, 1, (2, 40, 40, 40)).astype(np.float32)
    mse = np.mean((recon - target) ** 2)
    mu = np.zeros((2, 8), np.float32)
    logvar = np.zeros((2, 8), np.float32)
    assert float(kl_divergence(mu, logvar)) == pytest.approx(0.0, abs=1e-7)
    # per dimension: 0.5 (mu^2 + e^lv - 1 - lv): mu = 1 -> 0.5; lv = -2 -> 0.5 (e^-2 + 1)
    assert float(kl_divergence(mu + 1, logvar)) == pytest.approx(0.5, rel=1e-6)
    assert float(kl_divergence(mu, logvar - 2)) == pytest.approx(0.5 * (np.exp(-2) + 1), rel=1e-6)
    assert float(vae_loss(recon, target, mu + 1, logvar)) == pytest.approx(mse, rel=1e-5)
    assert float(vae_loss(recon, target, mu + 1, logvar, kl_weight=0.1)) == pytest.approx(
        mse + 0.05, rel=1e-5)
    assert float(vae_loss(target, target, mu, logvar, kl_weight=1.0)) == pytest.approx(0.0, abs=1e-7)
