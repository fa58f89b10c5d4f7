"""Flax Linen networks of Fit2Form: shape auto-encoder, generator, fitness net.

Every module is pure (``init``/``apply``), takes ``train`` for its BatchNorm, and reads its sizes
from ``f2f_jax.config.NetConfig``.  Public volumes are ``[B, 40, 40, 40]`` float32 TSDFs.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from f2f_jax.config import NetConfig
from f2f_jax.nets.fitness import (
    N_OUTPUTS,
    FitnessNet,
    ResidualBlock,
    fitness_input,
    left_to_world,
    right_to_world,
)
from f2f_jax.nets.generator import (
    GENERATORS,
    FingerGenerator,
    Generator,
    HeightGenerator,
    generator_module,
    heights_to_tsdf,
    tsdf_heights,
)
from f2f_jax.nets.shape import (
    RESOLUTION,
    ShapeAutoEncoder,
    ShapeDecoder,
    ShapeEncoder,
    reparameterize,
)

__all__ = [
    "N_OUTPUTS",
    "RESOLUTION",
    "GENERATORS",
    "FingerGenerator",
    "FitnessNet",
    "Generator",
    "HeightGenerator",
    "ResidualBlock",
    "ShapeAutoEncoder",
    "ShapeDecoder",
    "ShapeEncoder",
    "count_params",
    "fitness_input",
    "generator_module",
    "heights_to_tsdf",
    "left_to_world",
    "reparameterize",
    "right_to_world",
    "summarize",
    "tsdf_heights",
]


def count_params(tree: Any) -> int:
    """Number of scalars in a pytree of arrays (or ``jax.ShapeDtypeStruct`` from ``eval_shape``)."""
    return int(sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(tree)))


def summarize(cfg: NetConfig, batch: int = 2) -> list[dict[str, Any]]:
    """Parameter counts and output shapes of every network, without allocating parameters.

    Uses ``jax.eval_shape`` on ``init`` and ``apply``, so the paper-size nets cost only tracing.

    Returns
    -------
    rows: one dict per module with keys ``name``, ``params`` (int), ``inputs`` and ``outputs``
        (shape tuples, or tuples of them); the auto-encoder and finger generator also list their
        submodules as ``"<name>/<sub>"`` rows.
    """
    r = RESOLUTION
    volume = jax.ShapeDtypeStruct((batch, r, r, r), jnp.float32)
    latent = jax.ShapeDtypeStruct((batch, cfg.latent_dim), jnp.float32)
    grasp = jax.ShapeDtypeStruct((batch, 3 * r, r, r), jnp.float32)
    nets = [
        ("ShapeEncoder", ShapeEncoder(cfg), (volume,)),
        ("ShapeDecoder", ShapeDecoder(cfg), (latent,)),
        ("Generator", Generator(cfg), (latent,)),
        ("ShapeAutoEncoder", ShapeAutoEncoder(cfg), (volume,)),
        ("FingerGenerator", FingerGenerator(cfg), (volume,)),
        ("HeightGenerator", HeightGenerator(cfg), (volume,)),
        ("FitnessNet", FitnessNet(cfg), (grasp,)),
    ]
    rows = []
    key = jax.random.key(0)
    for name, module, args in nets:
        variables = jax.eval_shape(lambda k, *a, m=module: m.init(k, *a, train=False), key, *args)
        out = jax.eval_shape(lambda v, *a, m=module: m.apply(v, *a, train=False), variables, *args)
        rows.append({
            "name": name,
            "params": count_params(variables["params"]),
            "inputs": tuple(tuple(a.shape) for a in args),
            "outputs": jax.tree.map(lambda a: tuple(a.shape), out),
        })
        if name in ("ShapeAutoEncoder", "FingerGenerator"):
            for sub, tree in sorted(variables["params"].items()):
                rows.append({"name": f"{name}/{sub}", "params": count_params(tree),
                             "inputs": None, "outputs": None})
    return rows
