"""Fitness network: (left finger, object, right finger) -> logits of the 11 simulated outcomes.

``fitness_input`` places both fingers in the object's world frame and concatenates the three
volumes along the closing axis x, ``[left | object | right]``, a ``[B, 120, 40, 40]`` volume laid
out as the grasp is (paper Sec. 3.2).  ``FitnessNet`` is the paper's 3D ResNet (appendix B.2, and
``SpatialConcatResFitnessNet`` of the original code):

    C(32,5,2) - R(32) - R(32) - C(64,3,2) - R(64) - R(64) - C(128,3,2) - R(128) - C(256,3,2) - R(256)
    - C(512,3,2) - R(512) - C(1024,3,2) - R(1024) - C(1024,3,2) - FC(512) - FC(256) - FC(128) - FC(11)

C is a convolution (padding 2 for the 5^3 one, 1 otherwise) + BatchNorm + leaky ReLU; R(N) is a
residual block, conv-BN-ReLU-conv-BN, plus its input, then ReLU.  Spatial sizes: 120x40x40 -> 60x20x20
-> 30x10x10 -> 15x5x5 -> 8x3x3 -> 4x2x2 -> 2x1x1 -> 1x1x1, then 1024 features.  The output stays as
logits (the paper's final sigmoid lives in the losses, which is numerically safer).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn

from f2f_jax.config import TRIAL_NAMES
from f2f_jax.errors import VolumeError
from f2f_jax.nets.shape import RESOLUTION, Net, VolumeConv, batch_norm

N_OUTPUTS = len(TRIAL_NAMES)  # grasp, S1..S4, R-30..R+30
STEM_KERNEL = 5  # the first stride-2 convolution's kernel (paper: 5^3, padded to "same")


def left_to_world(finger: jax.Array) -> jax.Array:
    """Left finger volume in the world layout of an object volume.

    The left finger sits at -x with ``w -> +x``, ``u -> +y``, ``v -> +z`` (``f2f_jax.config``), so
    ``world[x, y, z] = finger[u=y, v=z, w=x]``: the last axis moves to the front.

    finger: [..., 40, 40, 40] indexed [u, v, w]. Returns [..., 40, 40, 40] indexed [x, y, z].
    """
    return jnp.moveaxis(finger, -1, -3)


def right_to_world(finger: jax.Array) -> jax.Array:
    """Right finger volume in the world layout of an object volume.

    The right finger sits at +x with ``w -> -x``, ``u -> -y``, ``v -> +z`` (the left finger turned
    180 degrees about z), so ``world[x, y, z] = finger[u=R-1-y, v=z, w=R-1-x]``.

    finger: [..., 40, 40, 40] indexed [u, v, w]. Returns [..., 40, 40, 40] indexed [x, y, z].
    """
    return jnp.moveaxis(jnp.flip(finger, axis=(-3, -1)), -1, -3)


def fitness_input(obj: jax.Array, left: jax.Array, right: jax.Array) -> jax.Array:
    """Concatenate ``[left | object | right]`` along world x, fingers turned to face the object.

    Parameters
    ----------
    obj: [..., 40, 40, 40] float32 object TSDF indexed [x, y, z].
    left, right: [..., 40, 40, 40] float32 finger TSDFs indexed [u, v, w] (finger frame).

    Returns
    -------
    [..., 120, 40, 40] float32: x in [0, 40) the left finger (its mount at x = 0), [40, 80) the
    object, [80, 120) the right finger (its mount at x = 119).
    """
    r = RESOLUTION
    for name, v in (("object", obj), ("left finger", left), ("right finger", right)):
        if v.ndim < 3 or tuple(v.shape[-3:]) != (r, r, r):
            raise VolumeError(f"fitness_input {name}: expected [..., {r}, {r}, {r}], got shape "
                              f"{tuple(v.shape)}")
    if not (obj.shape == left.shape == right.shape):
        raise VolumeError(f"fitness_input: object {tuple(obj.shape)}, left {tuple(left.shape)} and "
                          f"right {tuple(right.shape)} differ in shape")
    obj = jnp.asarray(obj)
    return jnp.concatenate([left_to_world(left), obj, right_to_world(right)], axis=-3)


class ResidualBlock(Net):
    """R(N): conv3-BN-ReLU-conv3-BN, add the input, ReLU (paper B.2). Keeps shape and width."""


    @nn.compact
    def __call__(self, x: jax.Array, *, train: bool) -> jax.Array:
        """x: [B, D, H, W, N] -> [B, D, H, W, N]."""
        width = x.shape[-1]
        y = VolumeConv(width, 3, 1, 1, dtype=self.dtype)(x)
        y = nn.relu(batch_norm(self.config, train, self.dtype)(y))
        y = VolumeConv(width, 3, 1, 1, dtype=self.dtype)(y)
        y = batch_norm(self.config, train, self.dtype)(y)
        return nn.relu(x + y)


class FitnessNet(Net):
    """3D ResNet on the ``[B, 120, 40, 40]`` grasp layout -> ``[B, 11]`` outcome logits.

    Attributes
    ----------
    config: NetConfig (fitness_channels, fitness_blocks, fitness_fc, bn_momentum, leaky_slope).
    n_outputs: number of predicted outcomes (11: grasp, S1..S4, R-30..R+30).
    dtype: computation dtype; parameters stay float32.
    """

    n_outputs: int = N_OUTPUTS

    @nn.compact
    def __call__(self, volume: jax.Array, *, train: bool) -> jax.Array:
        """Predict outcome logits.

        Parameters
        ----------
        volume: [B, 120, 40, 40] float32 from ``fitness_input``.
        train: BatchNorm uses batch statistics (and updates ``batch_stats``) when True.

        Returns
        -------
        logits: [B, n_outputs] float32; ``sigmoid(logits)`` are outcome probabilities.
        """
        cfg = self.config
        r = RESOLUTION
        if volume.ndim != 4 or tuple(volume.shape[1:]) != (3 * r, r, r):
            raise VolumeError(f"FitnessNet input: expected [B, {3 * r}, {r}, {r}] (fitness_input), "
                              f"got shape {tuple(volume.shape)}")
        if len(cfg.fitness_blocks) != len(cfg.fitness_channels):
            raise ValueError(f"fitness_blocks {cfg.fitness_blocks} and fitness_channels "
                             f"{cfg.fitness_channels} differ in length")

        def down(x, width, kernel, name):
            x = VolumeConv(width, kernel, 2, kernel // 2, dtype=self.dtype, name=name)(x)
            x = batch_norm(cfg, train, self.dtype, name=f"{name}_bn")(x)
            return nn.leaky_relu(x, cfg.leaky_slope)

        x = volume[..., None].astype(self.dtype)
        for stage, (width, blocks) in enumerate(zip(cfg.fitness_channels, cfg.fitness_blocks)):
            x = down(x, width, STEM_KERNEL if stage == 0 else 3, f"down{stage}")
            for b in range(blocks):
                x = ResidualBlock(cfg, self.dtype, name=f"res{stage}_{b}")(x, train=train)
        x = down(x, cfg.fitness_channels[-1], 3, f"down{len(cfg.fitness_channels)}")
        x = x.reshape(x.shape[0], -1)
        for i, width in enumerate(cfg.fitness_fc):
            x = nn.Dense(width, use_bias=False, dtype=self.dtype, name=f"fc{i}")(x)
            x = batch_norm(cfg, train, self.dtype, name=f"fc{i}_bn")(x)
            x = nn.leaky_relu(x, cfg.leaky_slope)
        logits = nn.Dense(self.n_outputs, dtype=self.dtype, name="logits")(x)
        return logits.astype(jnp.float32)
