"""Generator: object latent -> two finger latents, and the full object -> fingers pipeline.

``Generator`` is the paper's embedding network G_emb (appendix B.2): FC(2096)-FC(4096)-FC(2 x 686)
-tanh, every hidden layer followed by BatchNorm and leaky ReLU, the output layer by tanh alone (the
original code also put a BatchNorm before that tanh; the paper's list has none, and without it the
output's level is free to match the imprint latents it is pretrained on).

``FingerGenerator`` chains ``ShapeEncoder -> Generator -> ShapeDecoder`` with its parameters in three
separable subtrees, ``params["encoder"]``, ``params["embedding"]``, ``params["decoder"]``.  The paper
freezes the pretrained encoder and decoder: here they always run in evaluation mode (running
BatchNorm statistics, never updated) and the object latent is cut from the gradient, so backward
passes skip the encoder; the caller masks the optimiser so that only ``embedding`` changes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn

from f2f_jax.nets.shape import Net, ShapeDecoder, ShapeEncoder, dense_layers


class Generator(Net):
    """Embedding network: object latent -> (left finger latent, right finger latent).

    Attributes
    ----------
    config: NetConfig (latent_dim, generator_fc, bn_momentum, leaky_slope).
    dtype: computation dtype; parameters stay float32.
    """


    @nn.compact
    def __call__(self, object_latent: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """Map one object latent to two finger latents.

        Parameters
        ----------
        object_latent: [B, latent_dim] float32 in [-1, 1].
        train: BatchNorm uses batch statistics (and updates ``batch_stats``) when True.

        Returns
        -------
        left, right: [B, latent_dim] float32 in (-1, 1) each.
        """
        cfg = self.config
        if object_latent.ndim != 2 or object_latent.shape[1] != cfg.latent_dim:
            raise ValueError(f"Generator input: expected [B, {cfg.latent_dim}], got shape "
                             f"{tuple(object_latent.shape)}")
        x = dense_layers(object_latent.astype(self.dtype), cfg.generator_fc, cfg, train, self.dtype)
        x = nn.Dense(2 * cfg.latent_dim, dtype=self.dtype)(x)
        x = jnp.tanh(x).astype(jnp.float32)
        return x[:, : cfg.latent_dim], x[:, cfg.latent_dim:]


class FingerGenerator(Net):
    """Object TSDF -> (left finger TSDF, right finger TSDF): encoder, embedding, decoder.

    Only ``train`` of the embedding network follows the argument: encoder and decoder stay in
    evaluation mode (frozen, as in the paper).  Finger volumes are in the finger frame of
    ``f2f_jax.config`` (``[u, v, w]``, ``w = 0`` at the mount); use
    ``f2f_jax.nets.fitness_input`` to lay them out for the fitness net.
    """


    def setup(self):
        self.encoder = ShapeEncoder(self.config, dtype=self.dtype)
        self.embedding = Generator(self.config, dtype=self.dtype)
        self.decoder = ShapeDecoder(self.config, dtype=self.dtype)

    def object_latent(self, obj: jax.Array) -> jax.Array:
        """Frozen encoder's mean: [B, 40, 40, 40] -> [B, latent_dim], no gradient."""
        mu, _ = self.encoder(obj, train=False)
        return jax.lax.stop_gradient(mu)

    def latents(self, obj: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """Finger latents without decoding (for pretraining towards imprint latents).

        obj: [B, 40, 40, 40] float32. Returns left, right: [B, latent_dim] float32 each.
        """
        return self.embedding(self.object_latent(obj), train=train)

    def __call__(self, obj: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """Design fingers.

        Parameters
        ----------
        obj: [B, 40, 40, 40] float32 object TSDF, negative inside.
        train: training mode of the embedding network's BatchNorm.

        Returns
        -------
        left, right: [B, 40, 40, 40] float32 finger TSDFs in (-1, 1), finger frame.
        """
        return self.decode(*self.latents(obj, train=train))

    def decode(self, left_z: jax.Array, right_z: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Frozen decoder: finger latents [B, latent_dim] x2 -> finger TSDFs [B, 40, 40, 40] x2."""
        # one decoder call for both fingers: with frozen (running) statistics the batch mixes freely
        fingers = self.decoder(jnp.concatenate([left_z, right_z], axis=0), train=False)
        n = left_z.shape[0]
        return fingers[:n], fingers[n:]
