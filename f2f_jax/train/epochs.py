"""One training epoch: its index batches, its batches made on the device one at a time, its steps
and one host sync for its mean metrics; a NaN loss stops the run with the step that made it."""

from __future__ import annotations

import math
import time

import jax
import numpy as np
from tqdm.auto import tqdm

from f2f_jax.errors import F2FError
from f2f_jax.train.steps import shard


class NaNLossError(F2FError, FloatingPointError):
    """A training loss became NaN or infinite."""


def check_finite(values: np.ndarray, stage: str, first_step: int) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise NaNLossError(f"{stage}: loss is {values[bad[0]]} at step {first_step + int(bad[0])}; "
                           "lower the learning rate or check the inputs")


class LazyBatches:
    """The batches of one epoch, made on the device one at a time (an epoch of paper-size batches
    would not fit in memory at once): ``make(i, index_batch)`` for each index batch."""

    def __init__(self, make, index_batches):
        self.make, self.index_batches = make, list(index_batches)

    def __len__(self) -> int:
        return len(self.index_batches)

    def __iter__(self):
        for i, b in enumerate(self.index_batches):
            yield self.make(i, b)


def row_batches(*parts: dict, idx_batches) -> LazyBatches:
    """Fitness-net batches (object, left, right, outcome) of the rows of data dicts; with several
    dicts, ``idx_batches`` holds one index array per dict for each batch, and the batch is their
    rows in that order (no full-set copies)."""
    def make(i, idx):
        idx = idx if len(parts) > 1 else (idx,)
        cols = [np.concatenate([p[k][j] for p, j in zip(parts, idx)]).astype(np.float32)
                for k in ("object", "left", "right", "outcome")]
        return shard(*cols)
    return LazyBatches(make, idx_batches)


def index_batches(n: int, batch: int, max_steps: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Index batches of one epoch: a shuffled pass, capped at ``max_steps``, the last batch filled
    up so every batch has the same shape (one compile)."""
    batch = min(batch, max(n, 1))
    steps = min(math.ceil(n / batch), max_steps)
    order = rng.permutation(n)
    need = steps * batch
    if need > n:
        order = np.concatenate([order, rng.choice(n, need - n)])
    return [order[i * batch:(i + 1) * batch] for i in range(steps)]


def run_epoch(state, step_fn, batches, stage: str, epoch: int, cycle: int = 0, *, desc: str = "",
              progress: bool = True):
    """``step_fn(state, *batch)`` over the batches; returns the new state and the epoch's record
    (mean loss and metrics, steps, seconds).  Raises NaNLossError on a non-finite loss."""
    start = time.perf_counter()
    first_step = int(state.step)
    metrics = []
    for args in tqdm(batches, desc=desc, leave=False, disable=not progress):
        state, m = step_fn(state, *args)
        metrics.append(m)
    host = jax.device_get(metrics)
    losses = np.array([m["loss"] for m in host], np.float64)
    check_finite(losses, stage, first_step)
    out = {"stage": stage, "epoch": epoch, "cycle": cycle, "loss": float(losses.mean()),
           "steps": len(losses), "seconds": round(time.perf_counter() - start, 3)}
    for k in host[0]:
        if k != "loss":
            out[k] = np.mean([m[k] for m in host], axis=0).round(5).tolist()
    return state, out
