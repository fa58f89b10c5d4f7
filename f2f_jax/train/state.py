"""Train state and the trained models as pytrees.

``TrainState`` is what one jitted step takes and returns (parameters, BatchNorm statistics, optimiser state,
step count); ``TrainedNets`` is what design and evaluation need from a run (the finger generator and the
fitness net, with the config that sized them).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from f2f_jax.config import Config, TrainConfig
from f2f_jax.nets import RESOLUTION, FitnessNet, ShapeAutoEncoder, generator_module
from f2f_jax.nets.inference import TrainedNets


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


def generator_optimizer(cfg: Config) -> optax.GradientTransformation:
    """Adam on the embedding net only: the pretrained encoder and decoder stay frozen (paper); the
    height-map generator has nothing else."""
    opt = optimizer(cfg.train)

    def labels(params):
        return {k: jax.tree.map(lambda _, k=k: "train" if k == "embedding" else "freeze", v)
                for k, v in params.items()}

    return optax.multi_transform({"train": opt, "freeze": optax.set_to_zero()}, labels)


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
    return _init(generator_module(cfg.net), seed, x)


def init_trained_nets(cfg: Config, seed: int = 0, objectives: str = "full") -> TrainedNets:
    """Randomly initialised models (tests, and the RandEmb baseline's starting point)."""
    return TrainedNets(config=cfg, generator=init_generator(cfg, seed), fitness=init_fitness(cfg, seed + 1),
                  objectives=objectives, source="random init")


def fresh_run_state(cfg: Config, seed: int) -> dict:
    """A co-training run's state before any step: the shape VAE's, the fitness net's and the
    generator's ``TrainState`` (seeds ``seed``, +1, +2) and ``key``, the run's base PRNG key data
    (kept in checkpoints for their layout; the run derives its keys from the seed)."""
    return {
        "ae": new_state(init_autoencoder(cfg, seed), optimizer(cfg.train)),
        "fn": new_state(init_fitness(cfg, seed + 1), optimizer(cfg.train)),
        "gn": new_state(init_generator(cfg, seed + 2), generator_optimizer(cfg)),
        "key": jax.random.key_data(jax.random.key(seed)),
    }


def with_codec_of(gn: TrainState, ae: TrainState) -> TrainState:
    """The generator's state with the shape VAE's encoder and decoder (parameters and BatchNorm
    statistics) in place of its own: the generator's frozen codec is the pretrained VAE's.  A
    generator without a codec (the height-map generator) is returned as it is."""
    if "encoder" not in gn.params:
        return gn
    params, stats = dict(gn.params), dict(gn.batch_stats)
    for part in ("encoder", "decoder"):
        # copies: the generator's state is donated to its steps, the VAE's must survive
        params[part] = jax.tree.map(jnp.copy, ae.params[part])
        stats[part] = jax.tree.map(jnp.copy, ae.batch_stats[part])
    return gn.replace(params=params, batch_stats=stats)
