"""Losses of the four training stages: shape VAE, fitness net, generator, imprint pretraining.

What the original code did (``train.py`` of real-stanford/fit2form), and what we keep:

* Shape auto-encoder: plain ``MSELoss`` between the decoded sample and the input TSDF, no KL term.
  Its encoder's noise scale was damped (std = exp(0.1 x raw)) instead.  ``vae_loss`` is the MSE
  plus ``kl_weight`` times the KL divergence to N(0, I); ``kl_weight=0`` reproduces the original.
* Fitness net: ``BCELoss`` on sigmoid outputs, averaged over the batch and the 11 outcomes
  (paper eq. 1).  We take logits and optax's stable sigmoid BCE.
* Generator: ``-mean(F(o, G(o)))`` over the optimised outcomes; the ablations GS, GS+R, GS+S select
  grasp, grasp + robustness, grasp + stability (``OBJECTIVE_MASKS``).
* Generator pretraining: the original took the MSE between decoded and imprint finger TSDFs; we
  regress the embedding's finger latents onto the frozen encoder's latents of the imprint fingers,
  which skips the decoder and its backward pass (or, for the height-map generator, the height
  maps' L1): each generator's ``imprint_distance`` in ``f2f_jax.nets.generator``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax

from f2f_jax.config import TRIAL_NAMES

N_OUTPUTS = len(TRIAL_NAMES)


def _objective_mask(*groups: str) -> np.ndarray:
    index = {"grasp": [0], "stability": [1, 2, 3, 4], "robustness": [5, 6, 7, 8, 9, 10]}
    mask = np.zeros(N_OUTPUTS, bool)
    for g in groups:
        mask[index[g]] = True
    mask.setflags(write=False)
    return mask


# Outputs of the fitness net that the generator maximises, per variant of the paper's Table 1.
# Order of the 11 outputs: TRIAL_NAMES = grasp, S1..S4, R-30, R-20, R-10, R+10, R+20, R+30.
OBJECTIVE_MASKS: dict[str, np.ndarray] = {
    "GS": _objective_mask("grasp"),
    "GS+R": _objective_mask("grasp", "robustness"),
    "GS+S": _objective_mask("grasp", "stability"),
    "full": _objective_mask("grasp", "stability", "robustness"),
}


def reconstruction_mse(recon: jax.Array, target: jax.Array) -> jax.Array:
    """Mean squared error over every voxel of the batch: [B, 40, 40, 40] x2 -> scalar."""
    return jnp.mean(jnp.square(recon.astype(jnp.float32) - target.astype(jnp.float32)))


def kl_divergence(mu: jax.Array, logvar: jax.Array) -> jax.Array:
    """KL(N(mu, exp(logvar)) || N(0, I)), averaged over batch and latent dimensions.

    Averaging over dimensions (instead of summing) keeps one ``kl_weight`` meaningful across latent
    sizes (686 in the paper, 32 in the tiny config).

    mu, logvar: [B, latent_dim] float32. Returns a scalar.
    """
    return 0.5 * jnp.mean(jnp.square(mu) + jnp.exp(logvar) - 1.0 - logvar)


def vae_loss(recon: jax.Array, target: jax.Array, mu: jax.Array, logvar: jax.Array,
             kl_weight: float = 0.0) -> jax.Array:
    """Shape-VAE loss: voxel MSE + ``kl_weight`` x per-dimension KL.

    Parameters
    ----------
    recon: [B, 40, 40, 40] float32 decoded volumes.
    target: [B, 40, 40, 40] float32 input volumes.
    mu, logvar: [B, latent_dim] float32 posterior of each input.
    kl_weight: 0 (the original's pure reconstruction objective) or small, e.g. 1e-4 .. 1e-2.

    Returns
    -------
    scalar float32.
    """
    loss = reconstruction_mse(recon, target)
    if kl_weight:
        loss = loss + kl_weight * kl_divergence(mu, logvar)
    return loss


def fitness_loss(logits: jax.Array, targets: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """Mean binary cross-entropy of the fitness net's outcome logits (paper eq. 1).

    Parameters
    ----------
    logits: [B, 11] float32 fitness-net outputs (before sigmoid).
    targets: [B, 11] simulated outcomes, 0/1 (uint8, bool or float).
    mask: optional weights broadcastable to [B, 11] (e.g. [B, 1] for padded rows, [11] for a subset
        of outcomes); the mean runs over the weighted entries only.

    Returns
    -------
    scalar float32.
    """
    bce = optax.sigmoid_binary_cross_entropy(logits.astype(jnp.float32),
                                             targets.astype(jnp.float32))
    if mask is None:
        return jnp.mean(bce)
    weights = jnp.broadcast_to(jnp.asarray(mask, jnp.float32), bce.shape)
    return jnp.sum(bce * weights) / jnp.maximum(jnp.sum(weights), 1e-6)


def generator_loss(fitness_logits: jax.Array, objectives: str = "full") -> jax.Array:
    """Negative mean predicted success over the selected outcomes: ``-mean sigmoid(F)``.

    Parameters
    ----------
    fitness_logits: [B, 11] float32 fitness-net logits of generated fingers.
    objectives: a key of ``OBJECTIVE_MASKS``: "GS", "GS+R", "GS+S" or "full".

    Returns
    -------
    scalar float32 in [-1, 0]; -1 when every selected outcome is predicted certain.
    """
    try:
        mask = OBJECTIVE_MASKS[objectives]
    except KeyError:
        raise ValueError(f"unknown objectives {objectives!r}; choose one of "
                         f"{sorted(OBJECTIVE_MASKS)}") from None
    if fitness_logits.shape[-1] != N_OUTPUTS:
        raise ValueError(f"generator_loss: expected [B, {N_OUTPUTS}] logits, got shape "
                         f"{tuple(fitness_logits.shape)}")
    # a static column selection: the mask is a numpy constant, so this traces to a gather
    selected = jax.nn.sigmoid(fitness_logits.astype(jnp.float32))[..., np.flatnonzero(mask)]
    return -jnp.mean(selected)
