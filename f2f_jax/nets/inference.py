"""Inference with trained nets: what design, co-training and the tables all run.

``TrainedNets`` holds a run's generator and fitness net with the config that sized them; ``propose``
decodes a batch of objects into K candidate finger pairs each (candidate 0 the generator's own
output, the rest with noise on its finger codes: Gaussian latent noise, or for the height-map
generator a smooth random field added to each height map), ``predict`` scores candidates with
the fitness net.  Both are one jitted call over the whole batch, chunked inside by ``lax.map``
(``CHUNK`` rows at a time) so memory stays bounded for large batches.

This module sits above the network definitions and below training and design: ``train`` fills
``TrainedNets`` from checkpoints, ``designer`` and ``tables`` run them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from f2f_jax.config import Config, GeometryConfig, NetConfig
from f2f_jax.nets.fitness import FitnessNet, fitness_input
from f2f_jax.nets.generator import generator_module, heights_to_tsdf, tsdf_heights
from f2f_jax.nets.shape import RESOLUTION

# Standard deviation of the Gaussian added to each finger-latent coordinate of candidates
# 1..K-1: 0.1 of the latent range [-1, 1] (the generator's tanh output, the encoder's means).
LATENT_NOISE = 0.2
# The height-map generator's candidates: a smooth random field added to each height map, Gaussian
# on a HEIGHT_NOISE_GRID^2 grid over the mount and bilinearly interpolated between, its standard
# deviation at the grid points noise x HEIGHT_NOISE_VOXELS voxels (2 voxels at LATENT_NOISE: about
# how far the shape auto-encoder moves an imprint's faces).
HEIGHT_NOISE_VOXELS = 10.0
HEIGHT_NOISE_GRID = 5
# The origins of candidates, as design()'s pool and the teacher's store name them: candidate 0,
# and the others by their generator's kind of noise.
GENERATOR = "generator"
GENERATOR_NOISE = "generator + latent noise"
GENERATOR_HEIGHT_NOISE = "generator + height noise"  # a height-map generator's candidates
# Candidates (or objects) per vectorised chunk inside one jitted call: bounds activation memory
# (default config: ~1 GB per 256 fitness triples on a CPU) without a Python loop.
CHUNK = 256


@dataclasses.dataclass(frozen=True)
class TrainedNets:
    """What a run trained, ready for ``f2f_jax.design`` and evaluation.

    config: the Config that sized the nets.
    generator: the generator's variables (``nets.generator_module(config.net)``):
        ``{"params": {encoder, embedding, decoder}, "batch_stats": {...}}`` for the paper's
        ``FingerGenerator``, ``{"params": {embedding}}`` for the ``HeightGenerator``.
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
    return generator_module(net_cfg).apply(variables, objects, train=False)


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


def code_noise(net_cfg: NetConfig, key, shape: tuple[int, ...], noise) -> jax.Array:
    """Noise for finger codes [*shape, D] of the configured generator: Gaussian of std ``noise`` per
    latent coordinate, or for height codes (D = R * R) a smooth field over each map (see
    ``HEIGHT_NOISE_VOXELS``)."""
    r = RESOLUTION
    if net_cfg.generator != "heights":
        d = generator_module(net_cfg).code_dim(net_cfg)
        return noise * jax.random.normal(key, (*shape, d), jnp.float32)
    g = HEIGHT_NOISE_GRID
    coarse = jax.random.normal(key, (*shape, g, g), jnp.float32)
    return (noise * HEIGHT_NOISE_VOXELS) * smooth_field(coarse, r).reshape(*shape, r * r)


def smooth_field(coarse, r: int):
    """Values on a G x G grid over the mount [..., G, G] -> a field over its R x R columns
    [..., R, R], bilinear between the grid points (at the mount's corners and evenly between).
    Works in the array's own library: jax arrays in jax, numpy arrays in numpy (float64 stays)."""
    xp = jnp if isinstance(coarse, jax.Array) else np
    g = coarse.shape[-1]
    t = xp.linspace(0.0, g - 1.0, r)
    i0 = xp.clip(xp.floor(t).astype(xp.int32), 0, g - 2)
    f = t - i0
    rows = coarse[..., i0, :] * (1 - f)[:, None] + coarse[..., i0 + 1, :] * f[:, None]
    return rows[..., i0] * (1 - f) + rows[..., i0 + 1] * f


def perturbed_heights(fingers: np.ndarray, sd_voxels: float, truncation_voxels: float,
                      rng: np.random.Generator | None = None, *, grid: np.ndarray | None = None
                      ) -> np.ndarray:
    """Fingers [N, R, R, R] (TSDFs, finger frame) with their height maps moved by a smooth random
    field: standard deviation ``sd_voxels`` at the points of a ``HEIGHT_NOISE_GRID``^2 grid over the
    mount, bilinear between them (``smooth_field``, the form of the height generator's own
    candidates), then voxelised again (``heights_to_tsdf``).  A printer's error, or any change of a
    finger finer than a voxel: ``design(..., tolerance=...)`` and ``research/sim_retest.py
    --perturb heights`` simulate fingers moved so.

    Columns without solid stay empty; columns solid up to the cube's far face stay as they are (a
    TSDF in the cube cannot say how far past it they reach, so their height cannot be moved or even
    re-voxelised exactly); undercuts are filled, as the simulator's meshes fill them.  sd_voxels 0:
    the re-voxelisation alone, which leaves the height maps as they were.  rng: a numpy Generator
    (one field per finger, drawn in order), or grid: the field's standard normal values at the
    grid points [N, G, G] (to move several fingers alike).  Returns float32 [N, R, R, R]."""
    if sd_voxels < 0:
        raise ValueError(f"sd_voxels must be >= 0, got {sd_voxels}")
    if (rng is None) == (grid is None):
        raise ValueError("give the field's rng or its grid values, one of the two")
    fingers = np.asarray(fingers, np.float32)
    n, r = len(fingers), fingers.shape[-1]
    shape = (n, HEIGHT_NOISE_GRID, HEIGHT_NOISE_GRID)
    grid = rng.standard_normal(shape) if grid is None else np.asarray(grid, np.float64)
    if grid.shape != shape:
        raise ValueError(f"grid: expected shape {shape}, got {grid.shape}")
    heights = np.asarray(tsdf_heights(jnp.asarray(fingers)), np.float64)
    field = smooth_field(grid, r)
    # a column with solid keeps at least half a voxel of it (below that heights_to_tsdf empties it)
    moved = np.where(heights > 0, np.clip(heights + sd_voxels * field, 0.5, r - 0.5), 0.0)
    out = np.array(heights_to_tsdf(jnp.asarray(moved, jnp.float32), truncation_voxels), np.float32)
    full = fingers[..., -1] < 0  # solid in the top voxel: up to the far face
    out[full] = fingers[full]
    return out


def tolerance_voxels(tolerance_mm: float, geometry: GeometryConfig) -> float:
    """A printer's tolerance in millimetres -> the moving field's standard deviation in voxels."""
    return tolerance_mm / (1000.0 * geometry.voxel_size)


def printed_copies(lefts: np.ndarray, rights: np.ndarray, tolerance_mm: float,
                   geometry: GeometryConfig, copies: int, seed) -> tuple[np.ndarray, np.ndarray]:
    """Fingers [N, R, R, R] -> ``copies`` moved copies of them, [copies x N, R, R, R] copy-major
    (``perturbed_heights`` with fields of ``tolerance_mm``).  The fields depend only on ``seed``
    (any numpy seed), the copy, the side and the object's index: called with the same seed, the
    designs of every row of a table on the same N objects are moved alike (paired)."""
    n = len(lefts)
    grids = np.random.default_rng(seed).standard_normal(
        (copies, 2, n, HEIGHT_NOISE_GRID, HEIGHT_NOISE_GRID))
    sd, tr = tolerance_voxels(tolerance_mm, geometry), geometry.truncation_voxels
    return (np.concatenate([perturbed_heights(lefts, sd, tr, grid=grids[c, 0]) for c in range(copies)]),
            np.concatenate([perturbed_heights(rights, sd, tr, grid=grids[c, 1]) for c in range(copies)]))


@functools.partial(jax.jit, static_argnames=("net_cfg", "candidates", "chunk"))
def _propose_jit(net_cfg: NetConfig, variables, objects, key, noise, *, candidates: int, chunk: int):
    """objects [B, R, R, R] -> lefts, rights [B, K, R, R, R]; code noise on candidates 1..K-1."""
    gen = generator_module(net_cfg)
    cls = type(gen)
    r = RESOLUTION

    def codes(obj):  # [R, R, R] -> [2, D]
        left, right = gen.apply(variables, obj[None], train=False, method=cls.latents)
        return jnp.concatenate([left, right], axis=0)

    z = _chunked_map(codes, objects, chunk)  # [B, 2, D]
    b, _, d = z.shape
    eps = code_noise(net_cfg, key, (b, candidates, 2), noise)
    eps = eps.at[:, 0].set(0.0)
    lo, hi = cls.code_range(net_cfg)
    # noisy codes back into the generator's box (the decoder saw latents in [-1, 1] only);
    # candidate 0 exactly as generated
    z = jnp.clip(z[:, None] + eps, lo, hi).at[:, 0].set(z)

    def decode(code):  # [D] -> [R, R, R]
        return gen.apply(variables, code[None], method=cls.decode_one)[0]

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


def within_object_spearman(predicted: np.ndarray, simulated: np.ndarray) -> np.ndarray:
    """Per object, the Spearman rank correlation of its candidates' scores (mean predicted
    probability) with the trials they passed: predicted, simulated [N, K, 11] -> [N], nan for an
    object whose candidates all pass the same trials or all score the same (nothing to rank)."""
    from scipy.stats import rankdata

    score, value = np.asarray(predicted, np.float64).mean(-1), np.asarray(simulated, np.float64).sum(-1)
    rho = np.full(len(score), np.nan)
    for i, (sc, va) in enumerate(zip(score, value)):
        if np.ptp(va) > 0 and np.ptp(sc) > 0:
            rho[i] = np.corrcoef(rankdata(sc), rankdata(va))[0, 1]
    return rho
