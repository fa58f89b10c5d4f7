"""Train state and the trained models as pytrees.

``TrainState`` is what one jitted step carries (parameters, BatchNorm statistics, optimiser state,
step count); ``Models`` is what design and evaluation need from a run (the finger generator and the
fitness net, with the config that sized them).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from f2f_jax.config import Config, TrainConfig
from f2f_jax.nets import RESOLUTION, FingerGenerator, FitnessNet, ShapeAutoEncoder, fitness_input


@struct.dataclass
class TrainState:
    """One stage's trainable state; a pytree, donated to and returned by every step.

    params: the module's ``params`` collection; batch_stats: its BatchNorm running statistics;
    opt_state: optax state; step: int32 scalar.
    """

    params: Any
    batch_stats: Any
    opt_state: Any
    step: jax.Array

    @property
    def variables(self) -> dict:
        return {"params": self.params, "batch_stats": self.batch_stats}


def optimizer(tcfg: TrainConfig) -> optax.GradientTransformation:
    """Adam with decoupled weight decay (paper: lr 1e-4, weight decay 1e-5)."""
    return optax.adamw(tcfg.lr, weight_decay=tcfg.weight_decay)


def new_state(variables: dict, opt: optax.GradientTransformation) -> TrainState:
    params = variables["params"]
    return TrainState(params=params, batch_stats=variables.get("batch_stats", {}),
                      opt_state=opt.init(params), step=jnp.zeros((), jnp.int32))


def init_key(seed: int) -> jax.Array:
    """PRNG key for parameter initialisation: the rbg implementation compiles the initialisers in
    a fraction of threefry's time on a CPU (10-15 s saved per net)."""
    return jax.random.key(seed, impl="rbg")


def _init(module, seed: int, x: jax.Array) -> dict:
    # jitted: XLA compiles the initialisers as one program, 2-3x faster than running them eagerly
    return dict(jax.jit(lambda k, v: module.init(k, v, train=False))(init_key(seed), x))


def init_autoencoder(cfg: Config, seed: int = 0) -> dict:
    r = RESOLUTION
    x = jnp.zeros((2, r, r, r), jnp.float32)
    return _init(ShapeAutoEncoder(cfg.net), seed, x)


def init_fitness(cfg: Config, seed: int = 0) -> dict:
    r = RESOLUTION
    x = jnp.zeros((2, 3 * r, r, r), jnp.float32)
    return _init(FitnessNet(cfg.net), seed, x)


def init_generator(cfg: Config, seed: int = 0) -> dict:
    r = RESOLUTION
    x = jnp.zeros((2, r, r, r), jnp.float32)
    return _init(FingerGenerator(cfg.net), seed, x)


@dataclasses.dataclass(frozen=True)
class Models:
    """What a run trained, ready for ``f2f_jax.design`` and evaluation.

    config: the Config that sized the nets.
    generator: ``FingerGenerator`` variables ``{"params": {encoder, embedding, decoder},
        "batch_stats": {...}}``.
    fitness: ``FitnessNet`` variables ``{"params", "batch_stats"}``.
    objectives: the fitness outputs the generator was trained to maximise ("full", "GS", ...).
    source: where they came from (a checkpoint path, or "random init").
    """

    config: Config
    generator: dict
    fitness: dict
    objectives: str = "full"
    source: str = ""

    def generate(self, objects: jax.Array) -> tuple[jax.Array, jax.Array]:
        """[B, 40, 40, 40] object TSDFs -> left, right finger TSDFs [B, 40, 40, 40] (eval mode)."""
        return _generate(self.config.net, self.generator, jnp.asarray(objects, jnp.float32))

    def predict(self, objects: jax.Array, lefts: jax.Array, rights: jax.Array) -> jax.Array:
        """Fitness probabilities [B, 11] of (object, left, right) triples (eval mode)."""
        return _predict(self.config.net, self.fitness, jnp.asarray(objects, jnp.float32),
                        jnp.asarray(lefts, jnp.float32), jnp.asarray(rights, jnp.float32))


@functools.partial(jax.jit, static_argnums=0)
def _generate(net_cfg, variables, objects):
    return FingerGenerator(net_cfg).apply(variables, objects, train=False)


@functools.partial(jax.jit, static_argnums=0)
def _predict(net_cfg, variables, objects, lefts, rights):
    logits = FitnessNet(net_cfg).apply(variables, fitness_input(objects, lefts, rights), train=False)
    return jax.nn.sigmoid(logits)


def init_models(cfg: Config, seed: int = 0, objectives: str = "full") -> Models:
    """Randomly initialised models (tests, and the RandEmb baseline's starting point)."""
    return Models(config=cfg, generator=init_generator(cfg, seed), fitness=init_fitness(cfg, seed + 1),
                  objectives=objectives, source="random init")

