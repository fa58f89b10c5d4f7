"""One co-training cycle (``CoTrainRun``'s stage 6): sample training objects, design fingers for
them, simulate the designs into the store; once ``warmup_designs`` designs exist, refit the fitness
net on them and train the generator against it.

Every source of randomness is derived from (seed, "cycle", c, part, epoch) (``CoTrainRun.rng``
and ``key``), so a resumed cycle repeats exactly what an uninterrupted one does.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from f2f_jax.config import Config
from f2f_jax.geometry import is_feasible, postprocess
from f2f_jax.nets.inference import TrainedNets, propose
from f2f_jax.train import steps as S
from f2f_jax.train.epochs import LazyBatches, row_batches
from f2f_jax.train.run_data import SharedVolumes
from f2f_jax.train.run_state import RunState

if TYPE_CHECKING:
    from f2f_jax.train.cotrain import CoTrainRun


def generate(cfg: Config, generator: dict, objects: np.ndarray,
             batch: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The generator's (lefts, rights, feasible) for object volumes, post-processed like design()."""
    lefts, rights = S.generate_batched(cfg.net, generator, objects, batch)
    lefts, rights = lefts[:, None], rights[:, None]
    feasible = postprocess(lefts, rights, cfg.geometry)[:, 0]  # in place, as design() does
    return lefts[:, 0], rights[:, 0], feasible


def generator_cfg(cfg: Config) -> Config:
    """The config of the generator's co-training steps: its own learning rate (the fitness net
    refits at ``lr``); the optimiser state is kept, its structure does not change."""
    t = cfg.train
    if t.generator_lr is None or t.generator_lr == t.lr:
        return cfg
    return cfg.replace(train=dataclasses.replace(t, lr=t.generator_lr))


def candidates(run: CoTrainRun, st: RunState, objs: np.ndarray,
               c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cycle_candidates`` designs per object (the generator's own, then latent perturbations),
    post-processed like design(): objects repeated, lefts, rights, each [N*K, R, R, R]."""
    cfg = run.cfg
    k = cfg.train.cycle_candidates
    if k == 1:
        return (objs, *generate(cfg, st.nets["gn"].variables, objs)[:2])
    nets = TrainedNets(cfg, st.nets["gn"].variables, st.nets["fn"].variables)
    lefts, rights = propose(nets, objs, run.key("cycle", c, 3), k)
    postprocess(lefts, rights, cfg.geometry)
    r = lefts.shape[2:]
    return np.repeat(objs, k, 0), lefts.reshape(-1, *r), rights.reshape(-1, *r)


def simulate_designs(run: CoTrainRun, st: RunState, c: int) -> None:
    """Cycle ``c``'s designs of ``objects_per_cycle`` sampled training objects, simulated and
    appended to the store as one chunk (keyed "cycle-c": done once, however often resumed)."""
    t, data = run.cfg.train, st.data
    key = f"cycle-{c}"
    if key in data.store.done_keys():
        return
    rng = run.rng("cycle", c, 0)
    pick = rng.choice(data.train_idx, t.objects_per_cycle, replace=t.objects_per_cycle > len(data.train_idx))
    objs, lefts, rights = candidates(run, st, data.objects[pick], c)
    pick = np.repeat(pick, t.cycle_candidates)
    out = run.simulate(objs, lefts, rights, f"cycle {c} designs")
    data.store.append(objs, lefts, rights, out, kind="generated", names=[data.names[i] for i in pick],
                      keys=[key], cycle=c)


def generated_rows(st: RunState, c: int) -> dict[str, np.ndarray]:
    """Every design simulated in cycles 1..c (the original's co-training dataset), read back from
    the store (float16, as on a resume) and kept in ``st.generated`` between cycles."""
    got = st.generated
    if got is not None and got[0] == c - 1 and len(got[1]["outcome"]):
        new = st.rows(lambda cyc, k: cyc == c, shared=True)
        rows = got[1] if not len(new["outcome"]) else {
            k: (got[1][k].concatenate(v) if isinstance(v, SharedVolumes) else np.concatenate([got[1][k], v]))
            for k, v in new.items()}
    else:
        rows = st.rows(lambda cyc, k: 1 <= cyc <= c, shared=True)
    st.generated = (c, rows)
    return rows


def refit_fitness(run: CoTrainRun, st: RunState, c: int, gen: dict[str, np.ndarray]) -> int:
    """The fitness net refitted on balanced batches, half designs of all cycles so far (``gen``),
    half pretraining rows, until its BCE < ``fn_target_loss`` (``min_epochs``..``max_epochs``).
    Returns the epochs run."""
    t, pre = run.cfg.train, st.data.pre
    half = max(1, t.cotrain_batch_size // 2)
    step = S.fn_step(run.cfg)
    epochs = 0
    for epoch in range(1, t.max_epochs + 1):
        rng = run.rng("cycle", c, 1, epoch)
        nb = run.batches(len(gen["outcome"]), half, rng)
        ob = [rng.choice(len(pre["outcome"]), len(b)) for b in nb]
        batches = row_batches(gen, pre, idx_batches=list(zip(nb, ob)))
        rec = run.epoch(st, "fn", step, batches, epoch, c, desc=f"cycle {c} FN epoch {epoch}")
        run.log(rec)
        epochs = epoch
        if epoch >= t.min_epochs and rec["loss"] < t.fn_target_loss:
            break
    return epochs


def train_generator(run: CoTrainRun, st: RunState, c: int) -> int:
    """The generator trained against the (frozen) fitness net on the training objects until its
    loss < ``gn_target_loss`` (``min_epochs``..``max_epochs``), at ``generator_lr``.  Returns the
    epochs run."""
    t, data = run.cfg.train, st.data
    step = S.gn_fitness_step(generator_cfg(run.cfg))
    fit_vars = st.nets["fn"].variables

    def batch(i, b):
        return fit_vars, S.shard(data.objects[data.train_idx[b]])

    epochs = 0
    for epoch in range(1, t.max_epochs + 1):
        rng = run.rng("cycle", c, 2, epoch)
        index = run.batches(len(data.train_idx), t.cotrain_batch_size, rng)
        rec = run.epoch(st, "gn", step, LazyBatches(batch, index), epoch, c,
                         desc=f"cycle {c} GN epoch {epoch}")
        run.log(rec)
        epochs = epoch
        if epoch >= t.min_epochs and rec["loss"] < t.gn_target_loss:
            break
    return epochs


def run_cycle(run: CoTrainRun, st: RunState, c: int) -> dict:
    """Cycle ``c``: its designs simulated (``simulate_designs``), then, after the warm-up, the
    fitness net refitted and the generator trained against it; logged, checkpointed, and its
    summary returned."""
    t, g = run.cfg.train, run.cfg.geometry
    start = time.perf_counter()
    simulate_designs(run, st, c)
    gen = generated_rows(st, c)
    new = {k: v[gen["cycle"] == c] for k, v in gen.items() if k != "object"}
    feasible = np.array([is_feasible(a, g) and is_feasible(b, g) for a, b in zip(new["left"], new["right"])])
    sim_seconds = time.perf_counter() - start
    warm = len(gen["outcome"]) >= t.warmup_designs
    fn_epochs = refit_fitness(run, st, c, gen) if warm else 0
    gn_epochs = train_generator(run, st, c) if warm else 0
    summary = {"stage": "cycle", "cycle": c, "designs": len(new["outcome"]),
               "designs_so_far": len(gen["outcome"]),
               "feasible": float(feasible.mean()) if len(feasible) else 0.0,
               "success": new["outcome"].mean(0).round(4).tolist(), "fn_epochs": fn_epochs,
               "gn_epochs": gn_epochs, "sim_seconds": round(sim_seconds, 2),
               "seconds": round(time.perf_counter() - start, 2)}
    run.log(summary)
    run.save(st, "cycle", 0, c)
    return summary
