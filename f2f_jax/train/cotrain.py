"""The whole Fit2Form pipeline as one resumable run: objects, grasp dataset, pretraining, co-training.

    run = CoTrainRun("runs/cotrain", cfg, config_name="default")
    summary = run.run(cycles=20)

Stages, in order, each checkpointed (``f2f_jax.train.checkpoint``) so that a killed run continues
where it stopped and ends with the same parameters as one that was never stopped:

1. ``objects``: the object set (built-in, or a mesh directory) as TSDFs with a fixed split.
2. ``dataset``: imprint, WSG50 and cut-finger pairs of every training object, simulated into the
   grasp store; the held-out objects' imprint and WSG50 pairs (the baselines, and the fitness net's
   held-out set).
3. ``ae``: the shape VAE on every object and finger volume (``ae_epochs``).
4. ``fn``: the fitness net on the grasp dataset (``fn_epochs``).
5. ``gn``: the generator regressed onto the training objects' imprint fingers (``gn_epochs`` at
   ``lr``, then ``gn_anneal_epochs`` at ``generator_lr``): the latent generator onto their
   latents, the height generator onto their height maps; with ``imprint_objects`` N, the imprints
   of N more built-in objects too (made into the run's ``imprint_objects/`` in stage 1, never
   simulated).
6. ``cycle`` 1..N: sample training objects, generate fingers, simulate them, append to the store;
   once ``warmup_designs`` designs exist, refit the fitness net on balanced batches (half designs
   of every cycle so far, half the pretraining data) until its BCE < ``fn_target_loss``
   (``min_epochs``..``max_epochs``) and train the generator against it until its loss <
   ``gn_target_loss`` (plus ``imprint_anchor`` x the latent distance to the imprint fingers, or
   with ``anchor_target="best"`` to each object's best-simulated fingers so far).  With
   ``cycle_candidates`` K > 1 each sampled object gets K designs: the generator's own and K - 1
   latent perturbations, all simulated.  ``objectives="imprint"`` is the control of co-training:
   the same cycles, designs simulated and logged, the same generator steps at the same learning
   rate, but on the pretraining's imprint pairs instead of against the fitness net (which is not
   refitted): the generator "pretrained for as many extra steps".

Every source of randomness is derived from (seed, stage, cycle, epoch), never from how far an
earlier process got, which is what makes resuming exact.  Each epoch appends a JSON line to
``log.jsonl``; each cycle redraws ``curves.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import jax
import numpy as np

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES, Config
from f2f_jax.errors import ConfigError, F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import imprint_fingers, is_feasible, postprocess
from f2f_jax.nets import generator_module
from f2f_jax.nets.inference import TrainedNets, propose
from f2f_jax.train import steps as S
from f2f_jax.train.checkpoint import Checkpoints, config_to_dict
from f2f_jax.train.curves import plot_curves
from f2f_jax.train.epochs import LazyBatches, index_batches, run_epoch
from f2f_jax.train.losses import OBJECTIVE_MASKS
from f2f_jax.train.run_data import BASELINES, FMF_KIND, SharedVolumes, prepare_run_data, read_rows
from f2f_jax.train.run_dir import (
    check_cycles,
    check_record,
    copy_pretraining,
    read_record,
    run_meta,
    source_record,
    with_recorded_simulator,
    write_record,
)
from f2f_jax.train.state import fresh_run_state, with_codec_of

log = logging.getLogger(__name__)

STAGES = ("ae", "fn", "gn", "cycle")
_STAGE_ID = {"ae": 1, "fn": 2, "gn": 3, "cycle": 4, "eval": 5}
ANCHOR_TARGETS = ("imprint", "best")  # TrainConfig.anchor_target
# TrainConfig.objectives: the fitness outputs the generator maximises (Table 1's ablations), or
# "imprint": co-training's control, its generator steps spent on the imprints instead
OBJECTIVES = (*OBJECTIVE_MASKS, "imprint")


class CoTrainRun:
    """One run directory: ``objects/``, ``store/``, ``checkpoints/``, ``log.jsonl``, ``run.json``,
    ``curves.png``, ``summary.json``, ``pretrained/`` (the models after pretraining: ImpGN).

    cfg: the run's Config; config_name: its name, recorded (a run directory refuses a different
    config); objects: "builtin", "pybullet" or a mesh directory; backend: the simulator
    ("mujoco", "mjx" or "warp"); executor: where it runs ("threads", or "ray": the pretraining
    dataset's and every cycle's simulation in Ray tasks, ``sim.evaluate``); not part of the
    run: a run may be resumed with either; progress: tqdm bars.
    """

    def __init__(self, run_dir, cfg: Config, *, config_name: str = "custom", objects: str = "builtin",
                 backend: str = "mujoco", progress: bool = True, executor: str = "threads",
                 keep_simulator: bool = True):
        self.dir = Path(run_dir)
        self.cfg = cfg
        self.keep_simulator = keep_simulator
        self.config_name = config_name
        self.source = objects
        self.backend = backend
        self.executor = executor
        self.progress = progress
        self.seed = cfg.train.seed
        t = cfg.train
        if t.anchor_target not in ANCHOR_TARGETS:
            raise ConfigError(f"train.anchor_target must be one of {ANCHOR_TARGETS}, got {t.anchor_target!r}")
        if t.cycle_candidates < 1:
            raise ConfigError(f"train.cycle_candidates must be >= 1, got {t.cycle_candidates}")
        if t.fn_refit_steps is not None and t.fn_refit_steps < 1:
            raise ConfigError(f"train.fn_refit_steps must be >= 1 or None, got {t.fn_refit_steps}")
        if t.gn_passes < 1:
            raise ConfigError(f"train.gn_passes must be >= 1, got {t.gn_passes}")
        if t.imprint_objects < 0:
            raise ConfigError(f"train.imprint_objects must be >= 0, got {t.imprint_objects}")
        if t.gn_anneal_epochs < 0:
            raise ConfigError(f"train.gn_anneal_epochs must be >= 0, got {t.gn_anneal_epochs}")
        if t.objectives not in OBJECTIVES:
            raise ConfigError(f"train.objectives must be one of {OBJECTIVES}, got {t.objectives!r}")
        if cfg.geometry.object_scale not in ("stretch", "fit"):
            raise ConfigError("geometry.object_scale must be 'stretch' or 'fit' (how the run's "
                              f"meshes are placed in the cube), got {cfg.geometry.object_scale!r}")
        generator_module(cfg.net)  # ConfigError on an unknown net.generator
        if cfg.net.generator == "heights" and cfg.net.height_truncation_voxels != cfg.geometry.truncation_voxels:
            raise ConfigError(
                f"net.height_truncation_voxels ({cfg.net.height_truncation_voxels}) must equal "
                f"geometry.truncation_voxels ({cfg.geometry.truncation_voxels}): the height "
                "generator's fingers must be TSDFs like the imprints the fitness net learns from")
        self._check_run_json()

    # -- bookkeeping --------------------------------------------------------------------------
    def _run_meta(self) -> dict:
        return run_meta(self.cfg, self.config_name, self.source, self.backend)

    def _check_run_json(self) -> None:
        path = self.dir / "run.json"
        if path.exists():
            old, recorded = read_record(json.loads(path.read_text()), self.cfg.train.cycles)
            if self.keep_simulator:  # else a chosen simulator is refused by the check below
                self.cfg = with_recorded_simulator(self.cfg, recorded, self.dir)
            check_record(self.dir, old, self._run_meta())

    def _log(self, record: dict) -> None:
        with open(self.dir / "log.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")
        log.info("%s", record)

    def _key(self, stage: str, *counters: int) -> jax.Array:
        key = jax.random.key(self.seed)
        for c in (_STAGE_ID[stage], *counters):
            key = jax.random.fold_in(key, c)
        return key

    def _rng(self, stage: str, *counters: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, _STAGE_ID[stage], *counters])

    def fork_pretrained(self, source) -> None:
        """Start this run, in a new directory, from the end of another run's pretraining
        (``run_dir.copy_pretraining``): the paper's ablations share one pretraining."""
        src = Path(source)
        old, recorded = source_record(self.dir, src, self.cfg.train.cycles)
        if self.keep_simulator:  # the source's store: the source's simulator
            self.cfg = with_recorded_simulator(self.cfg, recorded, self.dir)
        copy_pretraining(self.dir, src, old, self._run_meta())
        print(f"{self.dir}: starts from the pretraining of {src}", flush=True)

    # -- data -----------------------------------------------------------------------------------
    def prepare_data(self) -> None:
        """Objects, split, the grasp dataset and the held-out baselines (``run_data``)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        write_record(self.dir, self._run_meta())
        start = time.perf_counter()
        self.data = data = prepare_run_data(self.dir, self.cfg, self.source, self._simulate,
                                            backend=self.backend, executor=self.executor,
                                            progress=self.progress)
        self.objects, self.names, self.store = data.objects, data.names, data.store
        self.object_table = data.object_table  # the objects as stored: what shared rows index
        self.train_idx, self.test_idx, self.eval_idx = data.train_idx, data.test_idx, data.eval_idx
        self.pre = data.pre  # the pretraining dataset: dict of arrays, float16 volumes (as stored)
        self._log({"stage": "data", "objects": len(self.names), "train": len(self.train_idx),
                   "test": len(self.test_idx), "imprint_objects": len(data.imprint_objects),
                   "store_rows": len(self.store),
                   "seconds": round(time.perf_counter() - start, 2)})

    def _rows(self, select, shared: bool = False) -> dict[str, np.ndarray]:
        """Store rows (``read_rows``); ``shared``: their object volumes shared from the run's
        objects (``SharedVolumes``) rather than read, one copy per object however many rows."""
        if not shared:
            return read_rows(self.store, select)
        return read_rows(self.store, select, objects=(self.object_table, self.names))

    def _simulate(self, objs, lefts, rights, what: str) -> np.ndarray:
        if self.progress:
            where = "" if self.executor == "threads" else f", {self.executor}"
            print(f"simulating {len(objs)} {what} ({self.backend}{where})", flush=True)
        return sim.evaluate(objs, lefts, rights, backend=self.backend, cfg=self.cfg,
                            progress=None if self.progress else False, executor=self.executor)

    # -- state ----------------------------------------------------------------------------------
    def _models_tree(self, st: dict) -> dict:
        return {"generator": st["gn"].variables, "fitness": st["fn"].variables}

    def _save(self, stage: str, epoch: int, cycle: int, **extra) -> None:
        meta = {"stage": stage, "epoch": epoch, "cycle": cycle, "store_rows": len(self.store),
                "config_name": self.config_name, "config": config_to_dict(self.cfg),
                "objectives": self.cfg.train.objectives, **extra}
        self.ckpt.save(self.state, self._models_tree(self.state), meta)
        self.position = (STAGES.index(stage), epoch, cycle)

    def _load_or_init(self) -> None:
        self.ckpt = Checkpoints(self.dir / "checkpoints")
        state, meta = self.ckpt.restore_like(fresh_run_state(self.cfg, self.seed))
        self.state = S.replicate(state)
        if meta is None:
            self.position = (-1, 0, 0)  # nothing done
            return
        self.position = (STAGES.index(meta["stage"]), int(meta["epoch"]), int(meta["cycle"]))
        print(f"resuming {self.dir}: after {meta['stage']} epoch {meta['epoch']} cycle {meta['cycle']}",
              flush=True)

    def _done(self, stage: str, epoch: int = 0, cycle: int = 0) -> bool:
        return (STAGES.index(stage), epoch, cycle) <= self.position

    # -- epochs ---------------------------------------------------------------------------------
    def _epoch(self, stage: str, step_fn, batches, epoch: int, cycle: int = 0, desc: str = "") -> dict:
        """Run the steps of one epoch on the stage's state (``epochs.run_epoch``)."""
        key_name = "gn" if stage.startswith("gn") else stage
        self.state[key_name], rec = run_epoch(self.state[key_name], step_fn, batches, stage, epoch,
                                              cycle, desc=desc, progress=self.progress)
        return rec

    def _batches(self, n: int, batch: int, rng: np.random.Generator,
                 steps: int | None = None) -> list[np.ndarray]:
        """One epoch's index batches, at most ``steps`` of them (None: ``max_steps_per_epoch``)."""
        return index_batches(n, batch, steps or self.cfg.train.max_steps_per_epoch, rng)

    # -- stages ---------------------------------------------------------------------------------
    def pretrain_ae(self) -> None:
        t = self.cfg.train
        pre = self.pre
        finger_rows = np.isin(pre["kind"], ("imprint", "cut"))
        shapes = np.concatenate([self.objects[self.train_idx], pre["left"][finger_rows],
                                 pre["right"][finger_rows]]).astype(np.float32)
        step = S.ae_step(self.cfg)
        for epoch in range(1, t.ae_epochs + 1):
            if self._done("ae", epoch):
                continue
            rng, key = self._rng("ae", epoch), self._key("ae", epoch)
            batches = LazyBatches(lambda i, b, key=key: (S.shard(shapes[b]), jax.random.fold_in(key, i)),
                            self._batches(len(shapes), t.ae_batch_size, rng))
            rec = self._epoch("ae", step, batches, epoch, desc=f"AE epoch {epoch}/{t.ae_epochs}")
            self._log(rec)
            self._save("ae", epoch, 0)

    def ae_iou(self, idx: np.ndarray | None = None) -> float:
        """Mean IoU of the solid voxels of held-out objects and their reconstructions."""
        x = self.objects[self.test_idx if idx is None else idx]
        return S.reconstruction_iou(self.cfg, self.state["ae"].variables, x)

    def _fn_batches(self, *parts: dict, idx_batches) -> LazyBatches:
        """Fitness batches; with several data dicts, ``idx_batches`` holds one index array per
        dict for each batch, and the batch is their rows in that order (no full-set copies)."""
        def make(i, idx):
            idx = idx if len(parts) > 1 else (idx,)
            cols = [np.concatenate([p[k][j] for p, j in zip(parts, idx)]).astype(np.float32)
                    for k in ("object", "left", "right", "outcome")]
            return S.shard(*cols)
        return LazyBatches(make, idx_batches)

    def fn_heldout_bce(self) -> float:
        """Fitness BCE on the held-out baseline triples (imprint and WSG50 on unseen objects)."""
        rows = self.heldout
        f = S.fn_eval(self.cfg)
        cols = [rows[k].astype(np.float32) for k in ("object", "left", "right", "outcome")]
        loss, _ = f(self.state["fn"].variables, *S.shard(*cols))
        return float(loss)

    def pretrain_fn(self) -> None:
        t = self.cfg.train
        step = S.fn_step(self.cfg)
        for epoch in range(1, t.fn_epochs + 1):
            if self._done("fn", epoch):
                continue
            if epoch == 1:
                self._log({"stage": "fn", "epoch": 0, "heldout_bce": self.fn_heldout_bce()})
            rng = self._rng("fn", epoch)
            batches = self._fn_batches(self.pre, idx_batches=self._batches(len(self.pre["outcome"]),
                                                               t.fn_batch_size, rng))
            rec = self._epoch("fn", step, batches, epoch, desc=f"FN epoch {epoch}/{t.fn_epochs}")
            rec["heldout_bce"] = self.fn_heldout_bce()
            self._log(rec)
            self._save("fn", epoch, 0)

    def pretrain_gn(self) -> None:
        t = self.cfg.train
        data = self._imprint_pairs()
        total = t.gn_epochs + t.gn_anneal_epochs
        if not self._done("gn", 1):
            # the generator's frozen encoder and decoder are the pretrained VAE's
            self.state["gn"] = S.replicate(with_codec_of(self.state["gn"], self.state["ae"]))
        for epoch in range(1, total + 1):
            if self._done("gn", epoch):
                continue
            # the annealing epochs at the co-training's generator learning rate
            step = S.gn_imprint_step(self.cfg if epoch <= t.gn_epochs else self._cycle_cfg())
            rng = self._rng("gn", epoch)
            index = [b for _ in range(t.gn_passes)
                     for b in self._batches(len(data["object"]), t.fn_batch_size, rng)]
            batches = LazyBatches(lambda i, b: S.shard(*(data[k][b].astype(np.float32)
                                                   for k in ("object", "left", "right"))), index)
            rec = self._epoch("gn", step, batches, epoch, desc=f"GN epoch {epoch}/{total}")
            self._log(rec)
            self._save("gn", epoch, 0)

    def _imprint_pairs(self) -> dict[str, np.ndarray]:
        """The generator's pretraining data, float16: the training objects' imprint rows, then the
        imprint pairs of the run's extra imprint objects (``TrainConfig.imprint_objects``)."""
        if getattr(self, "_pairs", None) is not None:
            return self._pairs
        imprint = self.pre["kind"] == "imprint"
        data = {k: self.pre[k][imprint] for k in ("object", "left", "right")}
        extra = self.data.imprint_objects
        if len(extra):
            pairs = [imprint_fingers(o.astype(np.float32), self.cfg.geometry) for o in extra]
            more = {"object": extra, "left": np.stack([p[0] for p in pairs]).astype(np.float16),
                    "right": np.stack([p[1] for p in pairs]).astype(np.float16)}
            data = {k: np.concatenate([data[k], more[k]]) for k in data}
        self._pairs = data
        return data

    def generate(self, objects: np.ndarray, batch: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Generated (lefts, rights, feasible) for object volumes, post-processed like design()."""
        lefts, rights = S.generate_batched(self.cfg.net, self.state["gn"].variables, objects, batch)
        lefts, rights = lefts[:, None], rights[:, None]
        feasible = postprocess(lefts, rights, self.cfg.geometry)[:, 0]  # in place, as design() does
        return lefts[:, 0], rights[:, 0], feasible

    def evaluate_heldout(self, label: str) -> dict:
        """Simulated success of the current generator on the held-out evaluation objects."""
        objs = self.objects[self.eval_idx]
        lefts, rights, feasible = self.generate(objs)
        out = self._simulate(objs, lefts, rights, f"held-out designs ({label})")
        res = {"stage": "eval", "label": label, "objects": len(objs),
               "feasible": float(feasible.mean()), "success": out.mean(0).round(4).tolist()}
        self._log(res)
        return res

    def _cycle_cfg(self) -> Config:
        """The config of the generator's co-training steps: its own learning rate (the fitness
        net refits at ``lr``); the optimiser state is kept, its structure does not change."""
        t = self.cfg.train
        if t.generator_lr is None or t.generator_lr == t.lr:
            return self.cfg
        return self.cfg.replace(train=dataclasses.replace(t, lr=t.generator_lr))

    def _generated(self, c: int) -> dict[str, np.ndarray]:
        """Every design simulated in cycles 1..c (the original's co-training dataset), read back
        from the store (float16, as on a resume) and kept between cycles."""
        got = getattr(self, "_gen", None)
        if got is not None and got[0] == c - 1 and len(got[1]["outcome"]):
            new = self._rows(lambda cyc, k: cyc == c, shared=True)
            rows = got[1] if not len(new["outcome"]) else {
                k: (got[1][k].concatenate(v) if isinstance(v, SharedVolumes) else np.concatenate([got[1][k], v]))
                for k, v in new.items()}
        else:
            rows = self._rows(lambda cyc, k: 1 <= cyc <= c, shared=True)
        self._gen = (c, rows)
        return rows

    def _imprints(self, obj_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The imprint fingers (pretraining rows) of training objects, by object index."""
        if not hasattr(self, "_imprint_row"):
            rows = np.flatnonzero(self.pre["kind"] == "imprint")
            self._imprint_row = {str(self.pre["name"][r]): r for r in rows}
        missing = [self.names[i] for i in obj_idx if self.names[i] not in self._imprint_row]
        if missing:
            raise F2FError(f"no imprint fingers for {missing[:3]} in the pretraining data: "
                           "--imprint-anchor needs every training object's imprint pair")
        r = np.array([self._imprint_row[self.names[i]] for i in obj_idx])
        return self.pre["left"][r].astype(np.float32), self.pre["right"][r].astype(np.float32)

    def _candidates(self, objs: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``cycle_candidates`` designs per object (the generator's own, then latent perturbations),
        post-processed like design(): objects repeated, lefts, rights, each [N*K, R, R, R]."""
        k = self.cfg.train.cycle_candidates
        if k == 1:
            return (objs, *self.generate(objs)[:2])
        nets = TrainedNets(self.cfg, self.state["gn"].variables, self.state["fn"].variables)
        lefts, rights = propose(nets, objs, self._key("cycle", c, 3), k)
        postprocess(lefts, rights, self.cfg.geometry)
        r = lefts.shape[2:]
        return np.repeat(objs, k, 0), lefts.reshape(-1, *r), rights.reshape(-1, *r)

    def _best_fingers(self, obj_idx: np.ndarray, gen: dict) -> tuple[np.ndarray, np.ndarray]:
        """anchor_target="best": per object, the fingers that passed the most simulated trials
        so far, its imprint pair unless a cycle design passed strictly more (the earliest such)."""
        lefts, rights = self._imprints(obj_idx)  # also indexes the imprint rows (_imprint_row)
        if len(gen["outcome"]) == 0:
            return lefts, rights
        passed = gen["outcome"].sum(1)
        names = gen["name"].astype(str)
        for j, i in enumerate(obj_idx):
            rows = np.flatnonzero(names == self.names[i])
            if len(rows) == 0:
                continue
            best = rows[np.argmax(passed[rows])]  # argmax: the earliest of the best
            if passed[best] > self.pre["outcome"][self._imprint_row[self.names[i]]].sum():
                lefts[j], rights[j] = gen["left"][best], gen["right"][best]
        return lefts, rights

    def run_cycle(self, c: int) -> dict:
        t = self.cfg.train
        start = time.perf_counter()
        key = f"cycle-{c}"
        if key not in self.store.done_keys():
            rng = self._rng("cycle", c, 0)
            pick = rng.choice(self.train_idx, t.objects_per_cycle,
                              replace=t.objects_per_cycle > len(self.train_idx))
            objs, lefts, rights = self._candidates(self.objects[pick], c)
            pick = np.repeat(pick, t.cycle_candidates)
            out = self._simulate(objs, lefts, rights, f"cycle {c} designs")
            self.store.append(objs, lefts, rights, out, kind="generated",
                              names=[self.names[i] for i in pick], keys=[key], cycle=c)
        gen = self._generated(c)
        new = {k: v[gen["cycle"] == c] for k, v in gen.items() if k != "object"}
        g = self.cfg.geometry
        feasible = np.array([is_feasible(a, g) and is_feasible(b, g) for a, b in zip(new["left"], new["right"])])
        sim_seconds = time.perf_counter() - start
        fn_epochs = gn_epochs = 0
        warm = len(gen["outcome"]) >= t.warmup_designs
        control = t.objectives == "imprint"  # the generator's steps on imprints; no fitness net
        # refit the fitness net on balanced batches: half designs of all cycles so far, half
        # pretraining rows; then train the generator against it (both after the warm-up)
        half = max(1, t.cotrain_batch_size // 2)
        step = S.fn_step(self.cfg)
        for epoch in range(1, t.max_epochs + 1 if warm and not control else 1):
            rng = self._rng("cycle", c, 1, epoch)
            nb = self._batches(len(gen["outcome"]), half, rng, steps=t.fn_refit_steps)
            ob = [rng.choice(len(self.pre["outcome"]), len(b)) for b in nb]
            batches = self._fn_batches(gen, self.pre, idx_batches=list(zip(nb, ob)))
            rec = self._epoch("fn", step, batches, epoch, c, desc=f"cycle {c} FN epoch {epoch}")
            self._log(rec)
            fn_epochs = epoch
            if epoch >= t.min_epochs and rec["loss"] < t.fn_target_loss:
                break
        gstep = (S.gn_imprint_step if control else S.gn_fitness_step)(self._cycle_cfg())
        fit_vars = self.state["fn"].variables
        pairs = self._imprint_pairs() if control else None

        def gn_batch(i, b):
            if control:  # b indexes the imprint pairs
                return S.shard(*(pairs[k][b].astype(np.float32) for k in ("object", "left", "right")))
            idx = self.train_idx[b]
            target = () if not t.imprint_anchor else (
                self._best_fingers(idx, gen) if t.anchor_target == "best" else self._imprints(idx))
            arrays = (self.objects[idx], *target)
            put = S.shard(*arrays)
            return (fit_vars, *(put if len(arrays) > 1 else (put,)))

        for epoch in range(1, t.max_epochs + 1 if warm else 1):
            rng = self._rng("cycle", c, 2, epoch)
            index = self._batches(len(self.train_idx), t.cotrain_batch_size, rng)
            if control:  # as many steps of as many pairs, drawn from all the imprint pairs
                drawn = rng.permutation(len(pairs["object"]))
                index = [drawn[s - len(b):s] for b, s in zip(index, np.cumsum([len(b) for b in index]))]
            batches = LazyBatches(gn_batch, index)
            rec = self._epoch("gn", gstep, batches, epoch, c, desc=f"cycle {c} GN epoch {epoch}")
            self._log(rec)
            gn_epochs = epoch
            if (not control and epoch >= t.min_epochs
                    and rec.get("fitness_loss", rec["loss"]) < t.gn_target_loss):
                break
        summary = {"stage": "cycle", "cycle": c, "designs": len(new["outcome"]),
                   "designs_so_far": len(gen["outcome"]),
                   "feasible": float(feasible.mean()) if len(feasible) else 0.0,
                   "success": new["outcome"].mean(0).round(4).tolist(), "fn_epochs": fn_epochs,
                   "gn_epochs": gn_epochs, "sim_seconds": round(sim_seconds, 2),
                   "seconds": round(time.perf_counter() - start, 2)}
        self._log(summary)
        self._save("cycle", 0, c)
        return summary

    # -- the whole run --------------------------------------------------------------------------
    def run(self, cycles: int | None = None) -> dict:
        cycles = self.cfg.train.cycles if cycles is None else cycles
        if cycles < 0:
            raise ValueError(f"cycles must be >= 0, got {cycles}")
        t0 = time.perf_counter()
        check_cycles(self.dir, cycles)
        self.prepare_data()
        hb = self._rows(lambda c, k: c == -2)
        keep = np.isin(hb["name"], [self.names[i] for i in self.eval_idx])
        self.heldout = {k: v[keep] for k, v in hb.items()}
        self._load_or_init()
        self.pretrain_ae()
        iou = self.ae_iou()
        self._log({"stage": "ae", "heldout_iou": iou})
        self.pretrain_fn()
        self.pretrain_gn()
        self._keep_pretrained()
        evals = self._eval_record("cycle 0", 0)
        for c in range(1, cycles + 1):
            if self._done("cycle", 0, c):
                continue
            s = self.run_cycle(c)
            if self.progress:
                print(f"cycle {c}/{cycles}: {s['designs']} designs, feasible {s['feasible']:.2f}, "
                      f"grasp {s['success'][0]:.2f}, FN {s['fn_epochs']} / GN {s['gn_epochs']} epochs, "
                      f"{s['seconds']:.0f} s", flush=True)
            self.plot()
        if cycles:
            evals.update(self._eval_record(f"cycle {cycles}", cycles))
        summary = self.summary(evals, iou, time.perf_counter() - t0)
        with atomic_path(self.dir / "summary.json") as tmp:
            tmp.write_text(json.dumps(summary, indent=1))
        self.plot()
        return summary

    def _keep_pretrained(self) -> None:
        """The models at the end of pretraining, kept apart from the rolling checkpoints: the
        paper's ImpGN row (``load_trained_nets(run_dir / "pretrained")``) and a start for variants."""
        if self._done("cycle", 0, 1):
            return  # a resumed run already past pretraining: the state is no longer that
        ckpt = Checkpoints(self.dir / "pretrained" / "checkpoints", max_to_keep=1)
        if not ckpt.steps():
            t = self.cfg.train
            meta = {"stage": "gn", "epoch": t.gn_epochs + t.gn_anneal_epochs, "cycle": 0,
                    "store_rows": len(self.store), "config_name": self.config_name,
                    "config": config_to_dict(self.cfg), "objectives": "imprint"}
            ckpt.save(self.state, self._models_tree(self.state), meta)

    def _eval_record(self, label: str, cycle: int) -> dict:
        """Held-out evaluation of the generator after ``cycle``, cached in the run directory so
        that a resumed run reports the figure of the run that produced it."""
        path = self.dir / f"eval-cycle{cycle}.json"
        if path.exists():
            return {label: json.loads(path.read_text())}
        res = self.evaluate_heldout(label)
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(res))
        return {label: res}

    def summary(self, evals: dict, iou: float, seconds: float) -> dict:
        rows = {}
        hb = self.heldout
        for kind in (*BASELINES, FMF_KIND):
            sel = hb["kind"] == kind
            rows[kind] = hb["outcome"][sel].mean(0).round(4).tolist() if sel.any() else None
        for label, res in evals.items():
            rows[f"generator, {label}"] = res["success"]
        return {"held_out_objects": int(len(self.eval_idx)), "ae_heldout_iou": round(iou, 4),
                "success": rows, "trials": list(TRIAL_NAMES), "seconds_this_process": round(seconds, 1)}

    def plot(self) -> Path | None:
        """Draw the curves of log.jsonl to curves.png (``curves.plot_curves``)."""
        return plot_curves(self.dir)
