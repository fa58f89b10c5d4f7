"""The candidate pool of ``design``: the imprint variants, the simulated outcomes of candidates
(exact and as moved, printed copies) and their ranking.  Module-level steps, so that tests and
benchmarks can time or replace each one."""

from __future__ import annotations

import numpy as np

from f2f_jax.geometry.fingers import IMPRINT_VARIANTS, imprint_candidates  # noqa: F401 (the pool's)
from f2f_jax.nets.inference import (  # noqa: F401 (re-exported: the pool's origins and moved copies)
    GENERATOR,
    GENERATOR_HEIGHT_NOISE,
    GENERATOR_NOISE,
    HEIGHT_NOISE_GRID,
    perturbed_heights,
    printed_copies,
    tolerance_voxels,
)


def left_out_reason(origin: str) -> str:
    """Why an imprint variant could not be made, in a user's terms."""
    voxels = dict(IMPRINT_VARIANTS).get(origin, 0.0)
    if voxels > 0:
        return "the object grown by a voxel fills the whole design cube (nothing left to imprint)"
    return "the object shrunk by a voxel has no solid left (its walls are thinner than 2 voxels)"


def rank_candidates(feasible: np.ndarray, predicted: np.ndarray,
                    simulated: np.ndarray | None = None, moved: np.ndarray | None = None, *,
                    made: np.ndarray | None = None) -> np.ndarray:
    """Candidate order per object, best first.

    feasible: [B, K] bool; predicted: [B, K, 11] probabilities; simulated: [B, K, 11] 0/1 or None;
    moved: [C, B, K, 11] 0/1 outcomes of C moved copies of each candidate, or None; made: [B, K]
    bool, False for a candidate that could not be made (``imprint_candidates``), or None (all).
    Keys, most important first: made, feasible, simulated trials passed (when given; averaged
    with the moved copies' when those are given), mean predicted probability, lower candidate
    index.  Returns [B, K] int indices.
    """
    feasible = np.asarray(feasible, bool)
    b, k = feasible.shape
    made = np.ones((b, k), bool) if made is None else np.asarray(made, bool)
    pred = np.asarray(predicted, np.float64).mean(axis=-1)
    sim = (np.zeros((b, k)) if simulated is None
           else np.asarray(simulated, np.float64).sum(axis=-1))
    if moved is not None:
        if simulated is None:
            raise ValueError("moved copies are ranked with the exact pairs' simulated outcomes")
        moved = np.asarray(moved, np.float64).sum(axis=-1)
        sim = (sim + moved.sum(axis=0)) / (1 + len(moved))
    index = np.broadcast_to(np.arange(k), (b, k))
    # np.lexsort sorts ascending by the last key first
    return np.lexsort((index, -pred, -sim, ~feasible, ~made), axis=-1)


def simulate_candidates(nets, objects, lefts, rights, feasible, backend, progress=None,
                        object_hulls=None, executor: str = "threads") -> np.ndarray:
    """Simulated outcomes [B, K, T] uint8 (T = ``nets.config.sim.n_trials``, 11 for the whole
    protocol): the feasible candidates in one evaluate call, zeros for the rest (an infeasible
    finger scores all 0 by the protocol).  object_hulls: optional precomputed hulls, one per object."""
    from f2f_jax.sim import evaluate  # MuJoCo only when verifying: `import f2f_jax` stays light

    b, k = feasible.shape
    out = np.zeros((b, k, nets.config.sim.n_trials), np.uint8)
    ib, ik = np.nonzero(feasible)
    if len(ib):
        hulls = None if object_hulls is None else [object_hulls[i] for i in ib]
        out[ib, ik] = evaluate(objects[ib], lefts[ib, ik], rights[ib, ik], backend=backend,
                               cfg=nets.config, progress=progress, object_hulls=hulls,
                               executor=executor)
    return out


def simulate_moved(nets, objects, lefts, rights, feasible, backend, sd_voxels: float, copies: int,
                   rng: np.random.Generator, progress=None, object_hulls=None,
                   executor: str = "threads", shared: bool = False) -> np.ndarray:
    """Simulated outcomes [C, B, K, T] uint8 of C = ``copies`` copies of the feasible candidates,
    each finger's height map moved by a smooth field of ``sd_voxels``
    (``nets.inference.perturbed_heights``, drawn from ``rng``); zeros for infeasible candidates.
    shared=False: every finger its own field; True: one field per copy, object and side, the same
    for all of that object's candidates (common random numbers: candidates are compared under the
    same printing error).  One ``simulate_candidates`` call per copy, so memory holds one copy at
    a time."""
    ib, ik = np.nonzero(feasible)
    tr = nets.config.geometry.truncation_voxels
    out = []
    for _ in range(copies):
        moved_l, moved_r = lefts.copy(), rights.copy()
        if shared:
            grids = rng.standard_normal((len(objects), 2, HEIGHT_NOISE_GRID, HEIGHT_NOISE_GRID))
            moved_l[ib, ik] = perturbed_heights(lefts[ib, ik], sd_voxels, tr, grid=grids[ib, 0])
            moved_r[ib, ik] = perturbed_heights(rights[ib, ik], sd_voxels, tr, grid=grids[ib, 1])
        else:
            moved_l[ib, ik] = perturbed_heights(lefts[ib, ik], sd_voxels, tr, rng)
            moved_r[ib, ik] = perturbed_heights(rights[ib, ik], sd_voxels, tr, rng)
        out.append(simulate_candidates(nets, objects, moved_l, moved_r, feasible, backend, progress,
                                       object_hulls, executor=executor))
    return np.stack(out)
