"""Designers: the rows of the paper's tables as callables.

A **designer** is a callable ``objects [N, 40, 40, 40] float32 -> (lefts, rights)``, two numpy
arrays ``[N, 40, 40, 40]`` float32 of finger TSDFs in the finger frame of ``f2f_jax.config``.
This module provides the paper's rows as designers (``wsg_fmf_designer``, the paper's WSG50
fingers; ``wsg50_designer``, flat pads; ``imprint_designer``, ``nets_designer`` for a trained
generator, ``random_embedding_designer`` for RandEmb+FN) and ``pair_designer`` to turn any
per-object function (such as ``f2f_jax.design``) into one; ``make_designs`` runs them once.
"""

from __future__ import annotations

import functools
import logging
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax

from f2f_jax.config import Config
from f2f_jax.data.sources import wsg_fmf_fingers
from f2f_jax.errors import F2FError, VolumeError
from f2f_jax.geometry import imprint_fingers, is_feasible, largest_component, wsg50_fingers
from f2f_jax.nets import FitnessNet, fitness_input, generator_module
from f2f_jax.train.steps import generate_batched

log = logging.getLogger(__name__)

Designer = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def objects_array(objects, r: int = 40) -> np.ndarray:
    arr = np.asarray(objects, np.float32)
    if arr.ndim != 4 or arr.shape[1:] != (r, r, r):
        raise VolumeError(f"objects: expected shape [N, {r}, {r}, {r}], got {arr.shape}")
    return arr


def _empty_finger(r: int = 40) -> np.ndarray:
    """A finger with no solid voxel: infeasible, scored 0 without simulation."""
    return np.ones((r, r, r), np.float32)


def _fixed_pair_designer(left: np.ndarray, right: np.ndarray) -> Designer:
    """The same finger pair for every object."""

    def design(objects):
        n = len(objects_array(objects))
        return np.repeat(left[None], n, 0), np.repeat(right[None], n, 0)

    return design


def wsg50_designer(cfg: Config | None = None) -> Designer:
    """The WSG50's flat fingertips (``geometry.wsg50_fingers``) for every object."""
    return _fixed_pair_designer(*wsg50_fingers(cfg))


def wsg_fmf_designer(cfg: Config | None = None) -> Designer:
    """The paper's WSG50 row: Schunk's standard WSG-FMF fingers (``data.sources.wsg_fmf_fingers``,
    the mesh of the pybullet extra) for every object.  Raises MissingExtraError without it."""
    return _fixed_pair_designer(*wsg_fmf_fingers(cfg))


def imprint_designer(cfg: Config | None = None) -> Designer:
    """Imprint fingers (``geometry.imprint_fingers``: the object's two views along the closing
    axis, negated and split) of every object."""

    def design(objects):
        pairs = [imprint_fingers(o, cfg) for o in objects_array(objects)]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])

    return design


def _postprocess(fingers: np.ndarray) -> np.ndarray:
    """Largest face-connected component of each finger, as co-training does: [B, R, R, R]."""
    return np.stack([largest_component(f) for f in np.asarray(fingers, np.float32)])


def nets_designer(nets, *, batch: int = 8) -> Designer:
    """A trained generator (``nets.inference.TrainedNets``): ``TrainedNets.generate`` then the largest
    connected component of each finger, as in training (an infeasible result stays infeasible
    and scores 0).  batch: objects per call (``train.steps.generate_batched``)."""

    def design(objects):
        lefts, rights = generate_batched(nets.config.net, nets.generator,
                                         objects_array(objects), batch)
        return _postprocess(lefts), _postprocess(rights)

    return design


@functools.lru_cache(maxsize=8)
def _randemb_optimizer(net, steps: int, lr: float, objective: str):
    """Jitted ``(gvars, fvars, obj [R,R,R], z0 [S,2,D]) -> (z [S,2,D], score [S])``: Adam on the
    finger codes (projected onto the generator's code box: latents in [-1, 1]^D, heights in
    [0, R]^D) to maximise the fitness net's prediction for the decoded fingers; ``lr`` is in units
    of half the box's width.  net: the NetConfig (cached per config: one compile)."""
    gen, fit = generator_module(net), FitnessNet(net)
    lo, hi = type(gen).code_range(net)
    opt = optax.adam(lr * (hi - lo) / 2)

    def decode(gvars, z):  # [M, D] -> [M, R, R, R]
        return gen.apply(gvars, z, method=type(gen).decode_one)

    def score(gvars, fvars, obj, z):  # [S]
        s, _, d = z.shape
        fingers = decode(gvars, z.reshape(2 * s, d)).reshape(s, 2, *obj.shape)
        objs = jnp.broadcast_to(obj, (s, *obj.shape))
        p = jax.nn.sigmoid(fit.apply(fvars, fitness_input(objs, fingers[:, 0], fingers[:, 1]),
                                     train=False))
        return p[:, 0] if objective == "grasp" else p.mean(-1)

    def run(gvars, fvars, obj, z0):
        def step(state, _):
            z, opt_state = state
            grads = jax.grad(lambda z: -score(gvars, fvars, obj, z).sum())(z)
            updates, opt_state = opt.update(grads, opt_state, z)
            z = jnp.clip(optax.apply_updates(z, updates), lo, hi)
            return (z, opt_state), None

        (z, _), _ = jax.lax.scan(step, (z0, opt.init(z0)), None, length=steps)
        return z, decode(gvars, z.reshape(-1, z.shape[-1]))

    return jax.jit(run)


def random_embedding_designer(nets, key, *, samples: int = 8, steps: int = 200, lr: float = 0.02,
                              objective: str = "grasp") -> Designer:
    """The paper's RandEmb+FN baseline: test-time optimisation of random finger embeddings with
    the shape decoder and the fitness net, without the generator's embedding network.

    Per object: ``samples`` random (left, right) latent pairs uniform in the latent box
    [-1, 1]^D (for the height-map generator: height maps uniform in [0, R] voxels per column, the
    fingers read from them as the generator's are), each optimised by Adam (``lr``, in half-widths of
    that box) for ``steps`` steps (paper: 200) to maximise the
    fitness net's predicted grasp success (``objective="grasp"``) or the mean of its 11 outputs
    ("mean"); then decoded, reduced to their largest connected components, and the feasible pair
    the fitness net scores best is kept (the best infeasible one if none is feasible: it scores 0).
    key: a JAX PRNG key; object i uses ``fold_in(key, i)``, so a design does not depend on batching.
    """
    if objective not in ("grasp", "mean"):
        raise ValueError(f"objective: 'grasp' or 'mean', got {objective!r}")
    if samples < 1 or steps < 0:
        raise ValueError(f"samples must be >= 1 and steps >= 0, got {samples} and {steps}")
    net = nets.config.net
    run = _randemb_optimizer(net, int(steps), float(lr), objective)
    cls = type(generator_module(net))
    lo, hi = cls.code_range(net)
    d = cls.code_dim(net)
    out_index = 0 if objective == "grasp" else slice(None)

    def design(objects):
        objs = objects_array(objects)
        lefts, rights = [], []
        for i, obj in enumerate(objs):
            z0 = jax.random.uniform(jax.random.fold_in(key, i), (samples, 2, d), minval=lo, maxval=hi)
            _, fingers = run(nets.generator, nets.fitness, obj, z0)
            # decoded from z.reshape(2S, D): row 2s is sample s's left finger, row 2s + 1 its right
            fingers = _postprocess(np.asarray(fingers)).reshape(samples, 2, *obj.shape)
            left, right = fingers[:, 0], fingers[:, 1]
            pred = np.asarray(nets.predict(np.repeat(obj[None], samples, 0), left, right))
            score = pred[:, out_index] if objective == "grasp" else pred.mean(-1)
            ok = np.array([is_feasible(left[k]) and is_feasible(right[k]) for k in range(samples)])
            best = int(np.argmax(np.where(ok, score, -np.inf))) if ok.any() else int(np.argmax(score))
            lefts.append(left[best])
            rights.append(right[best])
        return np.stack(lefts), np.stack(rights)

    return design


def _pair(pair) -> tuple[np.ndarray, np.ndarray]:
    left, right = (pair.left, pair.right) if hasattr(pair, "left") else pair
    return np.asarray(left, np.float32), np.asarray(right, np.float32)


def pair_designer(fn: Callable[[np.ndarray], Any], *, batched: bool = False, progress: bool = False,
                  desc: str = "design") -> Designer:
    """Any design function as a designer: ``fn(obj [R, R, R]) -> pair`` where the pair is
    ``(left, right)`` or has ``.left`` and ``.right`` (``f2f_jax.design``'s FingerPair); with
    ``batched=True``, ``fn(objects [N, R, R, R]) -> N pairs`` in one call (falling back to one
    object at a time if that call raises F2FError).  A per-object call that raises F2FError
    gives an empty (infeasible, scored 0) pair and a warning.

        search = pair_designer(lambda o: f2f_jax.design(o, params=nets, candidates=64,
                                                        verify=True), batched=True)
    """

    def design(objects):
        objs = objects_array(objects)
        if batched:
            try:
                pairs = [_pair(p) for p in fn(objs)]
                if len(pairs) != len(objs):
                    raise VolumeError(f"{desc}: {len(pairs)} pairs for {len(objs)} objects")
                return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])
            except F2FError as exc:
                warnings.warn(f"{desc}: the batch failed ({exc}); designing one object at a time",
                              RuntimeWarning, stacklevel=2)
                fn_one = lambda o: fn(o[None])[0]  # noqa: E731
        else:
            fn_one = fn
        items = enumerate(objs)
        if progress:
            from tqdm.auto import tqdm

            items = tqdm(items, total=len(objs), desc=desc, unit="obj")
        lefts, rights = [], []
        for i, obj in items:
            try:
                left, right = _pair(fn_one(obj))
            except F2FError as exc:
                warnings.warn(f"{desc}: object {i}: {exc}; scored as infeasible", RuntimeWarning,
                              stacklevel=2)
                left = right = _empty_finger(obj.shape[0])
            lefts.append(np.asarray(left, np.float32))
            rights.append(np.asarray(right, np.float32))
        return np.stack(lefts), np.stack(rights)

    return design


@dataclass
class Design:
    """A designer's fingers for an object set: lefts, rights [N, R, R, R] float32; seconds."""

    lefts: np.ndarray
    rights: np.ndarray
    seconds: float = 0.0


def make_designs(designers: Mapping[str, Designer | Design], objects, *,
                 progress: bool = True) -> dict[str, Design]:
    """Run each designer once on ``objects [N, R, R, R]``; a ``Design`` passes through (so one
    set of designs can serve both tables), as does one that a designer returns.  Raises
    VolumeError naming a designer whose output has the wrong shape or NaN values."""
    objs = objects_array(objects)
    out = {}
    for name, designer in designers.items():
        if isinstance(designer, Design):
            d = designer
        else:
            start = time.perf_counter()
            if progress:
                log.info("designing %d objects with %s", len(objs), name)
            made = designer(objs)
            if isinstance(made, Design):  # a designer that knows its own cost (e.g. a stored one)
                d = made
            else:
                lefts, rights = made
                d = Design(np.asarray(lefts, np.float32), np.asarray(rights, np.float32),
                           time.perf_counter() - start)
        for side, arr in (("lefts", d.lefts), ("rights", d.rights)):
            if arr.shape != objs.shape:
                raise VolumeError(f"designer {name!r}: {side} have shape {arr.shape}, expected "
                                  f"{objs.shape}")
            if not np.all(np.isfinite(arr)):
                raise VolumeError(f"designer {name!r}: {side} contain NaN/inf values")
        out[name] = d
    return out


