"""Inference with trained nets: what design, co-training and the tables all run.

``TrainedNets`` holds a run's generator and fitness net with the config that sized them; ``propose``
decodes a batch of objects into K candidate finger pairs each (candidate 0 the generator's own
output, the rest with latent noise), ``predict`` scores candidates with the fitness net.  Both are
one jitted call over the whole batch, chunked inside by ``lax.map`` (``CHUNK`` rows at a time) so
memory stays bounded for large batches.

This module sits above the network definitions and below training and design: ``train`` fills
``TrainedNets`` from checkpoints, ``designer`` and ``tables`` run them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from f2f_jax.config import Config, NetConfig
from f2f_jax.nets.fitness import FitnessNet, fitness_input
from f2f_jax.nets.generator import FingerGenerator
from f2f_jax.nets.shape import RESOLUTION

# Standard deviation of the Gaussian added to each finger-latent coordinate of candidates
# 1..K-1: 0.1 of the latent range [-1, 1] (the generator's tanh output, the encoder's means).
LATENT_NOISE = 0.2
# Candidates (or objects) per vectorised chunk inside one jitted call: bounds activation memory
# (default config: ~1 GB per 256 fitness triples on a CPU) without a Python loop.
CHUNK = 256


@dataclasses.dataclass(frozen=True)
class TrainedNets:
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
        return generate(self.config.net, self.generator, jnp.asarray(objects, jnp.float32))

    def predict(self, objects: jax.Array, lefts: jax.Array, rights: jax.Array) -> jax.Array:
        """Fitness probabilities [B, 11] of (object, left, right) triples (eval mode)."""
        return predict_triples(self.config.net, self.fitness, jnp.asarray(objects, jnp.float32),
                        jnp.asarray(lefts, jnp.float32), jnp.asarray(rights, jnp.float32))


@functools.partial(jax.jit, static_argnums=0)
def generate(net_cfg: NetConfig, variables, objects):
    """Finger generator in evaluation mode: objects [B, R, R, R] -> lefts, rights (one jitted call)."""
    return FingerGenerator(net_cfg).apply(variables, objects, train=False)


def _probabilities(net_cfg: NetConfig, variables, objects, lefts, rights) -> jax.Array:
    """The fitness net in evaluation mode: outcome probabilities [B, 11] of B triples."""
    logits = FitnessNet(net_cfg).apply(variables, fitness_input(objects, lefts, rights), train=False)
    return jax.nn.sigmoid(logits)


@functools.partial(jax.jit, static_argnums=0)
def predict_triples(net_cfg: NetConfig, variables, objects, lefts, rights):
    """Fitness probabilities [B, 11] of B (object, left, right) triples, evaluation mode."""
    return _probabilities(net_cfg, variables, objects, lefts, rights)


def propose(nets: TrainedNets, objects: np.ndarray, key, candidates: int,
            noise: float = LATENT_NOISE) -> tuple[np.ndarray, np.ndarray]:
    """Raw generated candidates, before post-processing.

    objects: [B, 40, 40, 40] float32.  Returns lefts, rights: [B, K, 40, 40, 40] float32 host
    arrays (writable); candidate 0 is the generator's own output.
    """
    lefts, rights = _propose_jit(nets.config.net, nets.generator, jnp.asarray(objects),
                                 as_key(key), jnp.float32(noise), candidates=int(candidates),
                                 chunk=CHUNK)
    return np.array(lefts), np.array(rights)


def predict(nets: TrainedNets, objects: np.ndarray, lefts: np.ndarray, rights: np.ndarray) -> np.ndarray:
    """Fitness-net probabilities of every candidate: [B, K, 11] float32 (one jitted call)."""
    p = _fitness_jit(nets.config.net, nets.fitness, jnp.asarray(objects), jnp.asarray(lefts),
                     jnp.asarray(rights), chunk=CHUNK)
    return np.asarray(p, np.float32)


def as_key(key):
    """A PRNG key from None (key 0), an int seed, or a key as it is."""
    if key is None:
        return jax.random.key(0)
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        return jax.random.key(int(key))
    return key


def _chunked_map(f, xs, chunk: int):
    """``vmap(f)(xs)`` over the leading axis, ``chunk`` rows at a time when there are more (a
    ``lax.map`` scan: bounded memory, one compiled body).  Small inputs skip the scan, which
    would otherwise be compiled alongside the remainder."""
    n = jax.tree.leaves(xs)[0].shape[0]
    if n <= chunk:
        return jax.vmap(f)(xs)
    return jax.lax.map(f, xs, batch_size=chunk)


def _decode(module: FingerGenerator, latent: jax.Array) -> jax.Array:
    return module.decoder(latent, train=False)


@functools.partial(jax.jit, static_argnames=("net_cfg", "candidates", "chunk"))
def _propose_jit(net_cfg: NetConfig, variables, objects, key, noise, *, candidates: int, chunk: int):
    """objects [B, R, R, R] -> lefts, rights [B, K, R, R, R]; latent noise on candidates 1..K-1."""
    gen = FingerGenerator(net_cfg)
    r = RESOLUTION

    def latents(obj):  # [R, R, R] -> [2, D]
        left, right = gen.apply(variables, obj[None], train=False, method=FingerGenerator.latents)
        return jnp.concatenate([left, right], axis=0)

    z = _chunked_map(latents, objects, chunk)  # [B, 2, D]
    b, _, d = z.shape
    eps = noise * jax.random.normal(key, (b, candidates, 2, d), jnp.float32)
    eps = eps.at[:, 0].set(0.0)
    z = jnp.clip(z[:, None] + eps, -1.0, 1.0)  # the decoder saw latents in [-1, 1] only

    def decode(latent):  # [D] -> [R, R, R]
        return gen.apply(variables, latent[None], method=_decode)[0]

    fingers = _chunked_map(decode, z.reshape(-1, d), chunk)
    fingers = fingers.reshape(b, candidates, 2, r, r, r)
    return fingers[:, :, 0], fingers[:, :, 1]


@functools.partial(jax.jit, static_argnames=("net_cfg", "chunk"))
def _fitness_jit(net_cfg: NetConfig, variables, objects, lefts, rights, *, chunk: int):
    """objects [B, R, R, R], lefts/rights [B, K, R, R, R] -> probabilities [B, K, 11]."""
    b, k = lefts.shape[:2]
    r = RESOLUTION
    owner = jnp.repeat(jnp.arange(b), k)  # candidates share their object's volume, not a copy

    def one(args):
        i, left, right = args
        return _probabilities(net_cfg, variables, objects[i][None], left[None], right[None])[0]

    p = _chunked_map(one, (owner, lefts.reshape(b * k, r, r, r), rights.reshape(b * k, r, r, r)),
                     chunk)
    return p.reshape(b, k, -1)
