"""Training: losses (``f2f_jax.train.losses``); jitted steps, stages and checkpoints build on them."""

from f2f_jax.train.losses import (
    OBJECTIVE_MASKS,
    fitness_loss,
    generator_loss,
    kl_divergence,
    reconstruction_mse,
    vae_loss,
)

__all__ = [
    "OBJECTIVE_MASKS",
    "fitness_loss",
    "generator_loss",
    "kl_divergence",
    "reconstruction_mse",
    "vae_loss",
]
