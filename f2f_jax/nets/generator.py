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

``HeightGenerator`` (``NetConfig.generator = "heights"``) writes what the simulator meshes, each
finger's height map over its mount, with no shape decoder in between: a column-local 2D CNN over
the object's (y, z) grid with the object's x planes as channels.  An imprint finger is solid from
the mount to the object's surface, so each output column needs only the object's column in
front of it and its neighbours.  Its "finger codes" are the two height maps, flattened, in
voxels; ``decode`` turns them into finger TSDFs solid from the mount to each height, a
projective distance along w as imprints have (an imprint and its height map's TSDF have the
same solid voxels; imprints also hold -1 in their base half, where this holds the distance).
Through the shape auto-encoder an imprint loses ~1.9 trials of 11 (its faces move ~2 voxels);
this generator, pretrained on imprints alone, came within 0.7 trials of them
(``research/finger_fidelity.py``, benchmarks/RESULTS.md).

Both generators answer the same calls: ``latents`` (finger codes), ``decode`` (codes -> TSDFs),
``imprint_distance`` (the pretraining loss), ``code_range`` and
``code_dim`` (the box and size of a finger code), and keep their trainable
network in ``params["embedding"]``; ``generator_module(net_cfg)`` picks one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn

from f2f_jax.config import NetConfig
from f2f_jax.errors import ConfigError
from f2f_jax.nets.shape import (
    RESOLUTION,
    TRUNCATION_VOXELS,
    Net,
    ShapeDecoder,
    ShapeEncoder,
    check_volume_batch,
    dense_layers,
)


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

    def decode_one(self, z: jax.Array) -> jax.Array:
        """Frozen decoder: finger latents [N, latent_dim] -> finger TSDFs [N, 40, 40, 40]."""
        return self.decoder(z, train=False)

    def imprint_distance(self, zl: jax.Array, zr: jax.Array, left: jax.Array, right: jax.Array) -> jax.Array:
        """Latent MSE between finger latents (zl, zr) [B, latent_dim] and the frozen encoder's means
        of fingers (left, right) [B, 40, 40, 40]: the pretraining loss."""
        tl, tr = (jax.lax.stop_gradient(self.encoder(x, train=False)[0]) for x in (left, right))
        return jnp.mean(jnp.square(jnp.concatenate([zl, zr], 1) - jnp.concatenate([tl, tr], 1)))

    @staticmethod
    def code_range(net_cfg: NetConfig) -> tuple[float, float]:
        """The box the finger codes live in: the embedding's tanh, the decoder's training range."""
        return -1.0, 1.0

    @staticmethod
    def code_dim(net_cfg: NetConfig) -> int:
        """Numbers per finger code: the latent size."""
        return net_cfg.latent_dim


# Leaky ReLU slope of the height generator's convolutions (as measured in finger_fidelity).
HEIGHT_LEAKY_SLOPE = 0.2


def heights_to_tsdf(heights: jax.Array, truncation_voxels: float) -> jax.Array:
    """Height maps [..., R, R] (voxels above the mount; below half a voxel: an empty column) ->
    finger TSDFs [..., R, R, R] in the finger frame: solid from the mount (w = 0) to each column's
    height, the signed distance along w over the truncation, clipped to [-1, 1] (imprints' form).

    Differentiable in the heights inside the truncation band; ``tsdf_heights`` inverts it exactly.
    """
    r = heights.shape[-1]
    w = jnp.arange(r, dtype=jnp.float32) + 0.5
    h = heights[..., None]
    tsdf = jnp.clip((w - h) / truncation_voxels, -1.0, 1.0)
    return jnp.where(h >= 0.5, tsdf, 1.0)


def tsdf_heights(tsdf: jax.Array) -> jax.Array:
    """Finger TSDFs [..., R, R, R] -> height maps [..., R, R] in voxels: the w of the zero crossing
    above each column's highest solid voxel, interpolated linearly to the next voxel (the cube's far
    face counts as empty); 0 for columns without solid.  ``geometry.finger_height_map`` in voxels."""
    r = tsdf.shape[-1]
    solid = tsdf < 0
    top = r - 1 - jnp.argmax(solid[..., ::-1], axis=-1)
    above = jnp.concatenate([tsdf, jnp.ones_like(tsdf[..., :1])], axis=-1)
    a = jnp.take_along_axis(tsdf, top[..., None], axis=-1)[..., 0]
    b = jnp.take_along_axis(above, top[..., None] + 1, axis=-1)[..., 0]
    frac = jnp.clip(a / jnp.minimum(a - b, -1e-9), 0.0, 1.0)
    return jnp.where(solid.any(-1), top + 0.5 + frac, 0.0)


class HeightMaps(Net):
    """Object TSDF [B, 40(x), 40(y), 40(z)] -> both fingers' height maps [B, 40(y), 40(z), 2] in
    voxels, indexed by world (y, z): the object's x planes are the channels of 3 x 3 convolutions
    (``height_channels``, leaky ReLU) over (y, z), then a 1 x 1 convolution to two maps."""

    @nn.compact
    def __call__(self, obj: jax.Array, *, train: bool) -> jax.Array:
        del train  # no BatchNorm: a column's height should not depend on the rest of its batch
        x = jnp.transpose(obj.astype(self.dtype), (0, 2, 3, 1))  # [B, y, z, x]
        for width in self.config.height_channels:
            x = nn.leaky_relu(nn.Conv(width, (3, 3), padding=1, dtype=self.dtype)(x), HEIGHT_LEAKY_SLOPE)
        # imprint heights span 0-40 voxels, most within 10-20: start the output there
        return nn.Conv(2, (1, 1), dtype=self.dtype)(x).astype(jnp.float32) * 10.0 + 10.0


class HeightGenerator(Net):
    """Object TSDF -> (left finger TSDF, right finger TSDF) through their height maps.

    Finger codes are the height maps in each finger's own [u, v] frame, flattened: [B, R * R]
    voxels (the right finger's u runs along -y, so its world-indexed map is flipped in u).
    Parameters: ``params["embedding"]`` alone (no encoder or decoder).
    """

    def setup(self):
        self.embedding = HeightMaps(self.config, dtype=self.dtype)

    def latents(self, obj: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """obj: [B, 40, 40, 40] -> left, right height codes [B, R * R] in voxels."""
        check_volume_batch(obj, "HeightGenerator input")
        maps = self.embedding(obj, train=train)
        b, r = maps.shape[0], RESOLUTION
        return maps[..., 0].reshape(b, r * r), maps[:, ::-1, :, 1].reshape(b, r * r)

    def __call__(self, obj: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """obj: [B, 40, 40, 40] -> left, right finger TSDFs [B, 40, 40, 40] in (-1, 1)."""
        return self.decode(*self.latents(obj, train=train))

    def decode(self, left_h: jax.Array, right_h: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Height codes [B, R * R] x2 -> finger TSDFs [B, R, R, R] x2."""
        return self.decode_one(left_h), self.decode_one(right_h)

    def decode_one(self, h: jax.Array) -> jax.Array:
        """Height codes [N, R * R] -> finger TSDFs [N, R, R, R].  Not clipped to [0, R]: a height
        past the cube's far face gives a full column all the same, and a clip would cut the
        gradient that brings an overshooting column back."""
        r = RESOLUTION
        return heights_to_tsdf(h.reshape(h.shape[0], r, r), TRUNCATION_VOXELS)

    def imprint_distance(self, zl: jax.Array, zr: jax.Array, left: jax.Array, right: jax.Array) -> jax.Array:
        """Mean absolute height difference (voxels) between codes (zl, zr) and the height maps of
        fingers (left, right) [B, 40, 40, 40]: the pretraining loss (L1)."""
        n = zl.shape[0]
        target = jax.lax.stop_gradient(tsdf_heights(jnp.concatenate([left, right], 0)).reshape(2 * n, -1))
        return jnp.mean(jnp.abs(jnp.concatenate([zl, zr], 0) - target))

    @staticmethod
    def code_range(net_cfg: NetConfig) -> tuple[float, float]:
        """Heights run from the mount (0) to the cube's far face (R voxels)."""
        return 0.0, float(RESOLUTION)

    @staticmethod
    def code_dim(net_cfg: NetConfig) -> int:
        """Numbers per finger code: one height per column of the mount, R * R."""
        return RESOLUTION * RESOLUTION


GENERATORS = {"latent": FingerGenerator, "heights": HeightGenerator}


def generator_module(net_cfg: NetConfig, dtype=jnp.float32) -> Net:
    """The finger generator ``net_cfg.generator`` names ("latent" or "heights")."""
    try:
        cls = GENERATORS[net_cfg.generator]
    except KeyError:
        raise ConfigError(f"net.generator must be one of {tuple(GENERATORS)}, got "
                          f"{net_cfg.generator!r}") from None
    return cls(net_cfg, dtype=dtype)
