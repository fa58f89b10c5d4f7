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
5. ``gn``: the generator's embedding net regressed onto the imprint fingers' latents (``gn_epochs``).
6. ``cycle`` 1..N: sample training objects, generate fingers, simulate them, append to the store;
   once ``warmup_designs`` designs exist, refit the fitness net on balanced batches (half designs
   of every cycle so far, half the pretraining data) until its BCE < ``fn_target_loss``
   (``min_epochs``..``max_epochs``) and train the generator against it until its loss <
   ``gn_target_loss`` (plus ``imprint_anchor`` x the latent distance to the imprint fingers).

Every source of randomness is derived from (seed, stage, cycle, epoch), never from how far an
earlier process got, which is what makes resuming exact.  Each epoch appends a JSON line to
``log.jsonl``; each cycle redraws ``curves.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES, Config
from f2f_jax.data import load_or_make_objects, object_split
from f2f_jax.data.sources import wsg_fmf_fingers
from f2f_jax.dataset import GraspStore, build_grasp_dataset
from f2f_jax.errors import CheckpointError, F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import imprint_fingers, is_feasible, postprocess, wsg50_fingers
from f2f_jax.train import steps as S
from f2f_jax.train.checkpoint import Checkpoints, config_from_dict, config_to_dict
from f2f_jax.train.state import (
    init_autoencoder,
    init_fitness,
    init_generator,
    new_state,
    optimizer,
)

log = logging.getLogger(__name__)

STAGES = ("ae", "fn", "gn", "cycle")
# Settings that only change the co-training cycles: runs that differ in nothing else can share one
# pretraining (``CoTrainRun.fork_pretrained``), as the paper's ablations do.
COTRAIN_FIELDS = ("cycles", "objectives", "imprint_anchor", "generator_lr", "warmup_designs",
                  "objects_per_cycle", "cotrain_batch_size", "fn_target_loss", "gn_target_loss",
                  "min_epochs", "max_epochs")
_STAGE_ID = {"ae": 1, "fn": 2, "gn": 3, "cycle": 4, "eval": 5}
BASELINES = ("imprint", "wsg50")  # flat pads, as the store's kind "wsg50" has always been
FMF_KIND = "wsg50-fmf"  # the paper's WSG50 fingers (Schunk WSG-FMF), with the pybullet extra


class NaNLossError(F2FError, FloatingPointError):
    """A training loss became NaN or infinite."""


def _check_finite(values: np.ndarray, stage: str, first_step: int) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise NaNLossError(f"{stage}: loss is {values[bad[0]]} at step {first_step + int(bad[0])}; "
                           "lower the learning rate or check the inputs")


def _differing_fields(old: dict, new: dict) -> list[str]:
    """``section.field`` names whose values differ between two recorded configs."""
    return [f"{part}.{k}" for part in new for k in new[part]
            if old.get(part, {}).get(k) != new[part][k]]


class _Lazy:
    """The batches of one epoch, made on the device one at a time (an epoch of paper-size batches
    would not fit in memory at once): ``make(i, index_batch)`` for each index batch."""

    def __init__(self, make, index_batches):
        self.make, self.index_batches = make, list(index_batches)

    def __len__(self) -> int:
        return len(self.index_batches)

    def __iter__(self):
        for i, b in enumerate(self.index_batches):
            yield self.make(i, b)


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
        self._check_run_json()

    # -- bookkeeping --------------------------------------------------------------------------
    @staticmethod
    def _meta_config(cfg: Config) -> dict:
        conf = config_to_dict(cfg)
        conf["train"].pop("cycles")  # a run may be extended by more cycles
        return conf

    def _run_meta(self) -> dict:
        return {"config_name": self.config_name, "config": self._meta_config(self.cfg),
                "objects": self.source, "backend": self.backend}

    def _recorded(self, meta: dict) -> tuple[dict, Config | None]:
        """``meta`` with its config as ``config_from_dict`` reads it (fields added since the run
        was made take the values it was made with), and the Config itself with this run's cycles
        (None when the record holds no readable config: it is compared as it is)."""
        try:
            conf = {part: dict(values) for part, values in meta["config"].items()}
            conf["train"]["cycles"] = self.cfg.train.cycles
            recorded = config_from_dict(conf)
        except (KeyError, TypeError, AttributeError):
            return meta, None
        return {**meta, "config": self._meta_config(recorded)}, recorded

    def _keep_recorded_simulator(self, recorded: Config | None) -> None:
        """A run goes on with the simulator its store was filled by: where the recorded run
        differs from this one in the simulation and geometry settings alone (a newer default, such
        as the 4 ms ``fast`` preset), take the recorded ones, unless the caller chose a simulator
        (``keep_simulator=False``), which is then refused by the check that follows."""
        if recorded is None:
            return
        same_model = (recorded.net, recorded.train) == (self.cfg.net, self.cfg.train)
        if (self.keep_simulator and same_model
                and (recorded.sim, recorded.geometry) != (self.cfg.sim, self.cfg.geometry)):
            log.info("%s: going on with the simulator it was made with (timestep %g s, %s)",
                     self.dir, recorded.sim.timestep, recorded.sim.integrator)
            self.cfg = self.cfg.replace(sim=recorded.sim, geometry=recorded.geometry)

    def _check_run_json(self) -> None:
        path = self.dir / "run.json"
        if path.exists():
            old, recorded = self._recorded(json.loads(path.read_text()))
            self._keep_recorded_simulator(recorded)
            new = self._run_meta()
            if old.get("backend", new["backend"]) != new["backend"]:
                raise CheckpointError(
                    f"{self.dir} was simulated with backend {old['backend']!r}; resume it with "
                    f"--backend {old['backend']} (mixing simulators in one store would change it)")
            if old.get("config") != new["config"] or old.get("objects") != new["objects"]:
                fields = _differing_fields(old.get("config") or {}, new["config"])
                raise CheckpointError(
                    f"{self.dir} holds a run of config {old.get('config_name')!r} on objects "
                    f"{old.get('objects')!r}; this one is {new['config_name']!r} on {new['objects']!r}"
                    + (f" (they differ in {', '.join(fields)})" if fields else "")
                    + ". Choose another --run-dir (nothing was changed)")

    def _write_run_json(self) -> None:
        path = self.dir / "run.json"
        if not path.exists():
            with atomic_path(path) as tmp:
                tmp.write_text(json.dumps(self._run_meta(), indent=1))

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
        """Start this run, in a new directory, from the end of another run's pretraining.

        Takes the source's objects, pretraining rows and held-out baselines, its pretrained models
        (``source/pretrained``) and their cycle-0 evaluation; the configs may differ only in
        ``COTRAIN_FIELDS`` (the objectives of the Table 1 ablations, the imprint anchor, ...).
        Everything is staged in a hidden sibling directory and renamed into place at the end.
        """
        src = Path(source)
        if self.dir.exists() and any(self.dir.iterdir()):
            raise CheckpointError(f"{self.dir} is not empty; a run started from {src} needs a new "
                                  "--run-dir")
        if not (src / "run.json").exists() or not (src / "pretrained" / "checkpoints").is_dir():
            raise CheckpointError(f"{src} holds no finished pretraining (no run.json or pretrained/); "
                                  f"make one with: python experiments/cotrain.py --run-dir {src} --cycles 1")
        old, recorded = self._recorded(json.loads((src / "run.json").read_text()))
        self._keep_recorded_simulator(recorded)  # the source's store: the source's simulator
        new = self._run_meta()
        differ = [f for f in _differing_fields(old["config"], new["config"])
                  if f.split(".")[0] != "train" or f.split(".")[1] not in COTRAIN_FIELDS]
        differ += [k for k in ("objects", "backend") if old.get(k) != new[k]]
        if differ:
            raise CheckpointError(f"{src} was pretrained with other settings ({', '.join(differ)}); "
                                  "only co-training settings may differ from the run it starts from")
        # the pretraining rows and baselines come before any cycle's designs: take the chunks
        # that end before the first designed row
        store = GraspStore(src / "store")
        cycles = store.read(("cycle",))["cycle"]
        first = int(np.argmax(cycles >= 1)) if (cycles >= 1).any() else len(cycles)
        ends = np.cumsum([c.rows for c in store.chunks()])
        pre = [c for c, end in zip(store.chunks(), ends) if end <= first]
        stage = self.dir.with_name(f".{self.dir.name}.fork-{os.getpid()}")
        try:
            shutil.rmtree(stage, ignore_errors=True)
            (stage / "store").mkdir(parents=True)
            shutil.copytree(src / "objects", stage / "objects")
            for c in pre:
                shutil.copy2(c.path, stage / "store" / c.path.name)
            shutil.copytree(src / "pretrained", stage / "pretrained")
            shutil.copytree(src / "pretrained" / "checkpoints", stage / "checkpoints")
            if (src / "eval-cycle0.json").exists():
                shutil.copy2(src / "eval-cycle0.json", stage / "eval-cycle0.json")
            keep = []  # the pretraining part of the source's log
            for line in (src / "log.jsonl").read_text().splitlines():
                try:
                    r = json.loads(line)
                except json.JSONDecodeError:
                    continue
                pretraining = r.get("stage") != "cycle" and r.get("cycle", 0) == 0
                if pretraining and r.get("label", "cycle 0") == "cycle 0":
                    keep.append(line + "\n")
            (stage / "log.jsonl").write_text("".join(keep))
            meta = {**new, "pretrained_from": str(src.resolve())}
            (stage / "run.json").write_text(json.dumps(meta, indent=1))
            self.dir.parent.mkdir(parents=True, exist_ok=True)
            if self.dir.exists():
                self.dir.rmdir()  # empty (checked above)
            os.replace(stage, self.dir)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
        print(f"{self.dir}: starts from the pretraining of {src}", flush=True)

    # -- data -----------------------------------------------------------------------------------
    def prepare_data(self) -> None:
        """Objects, split, the grasp dataset and the held-out baselines (each resumable)."""
        t = self.cfg.train
        self.dir.mkdir(parents=True, exist_ok=True)
        self._write_run_json()
        n = t.n_objects if self.source == "builtin" else None
        tsdfs, names = load_or_make_objects(self.source, n, self.seed, self.dir / "objects",
                                            self.cfg.geometry, progress=self.progress,
                                            test_fraction=self.cfg.train.test_fraction)
        split = object_split(self.dir / "objects")
        index = {name: i for i, name in enumerate(names)}
        self.train_idx = np.array([index[n] for n in split["train"] if n in index])
        self.test_idx = np.array([index[n] for n in split["test"] if n in index])
        if len(self.train_idx) < 2 or len(self.test_idx) < 1:
            raise F2FError(f"{len(names)} usable objects give {len(self.train_idx)} training and "
                           f"{len(self.test_idx)} held-out objects; need at least 2 and 1")
        self.objects = tsdfs
        self.names = names
        self.eval_idx = self.test_idx[: t.eval_objects]

        self.store = GraspStore(self.dir / "store")
        self.store.clean_temporary()
        start = time.perf_counter()
        build_grasp_dataset(tsdfs[self.train_idx], [names[i] for i in self.train_idx], self.store,
                            cfg=self.cfg, seed=self.seed, n_cut=t.cut_pairs, backend=self.backend,
                            progress=self.progress, executor=self.executor)
        self._baselines()
        self._fmf_baseline()
        self._log({"stage": "data", "objects": len(names), "train": len(self.train_idx),
                   "test": len(self.test_idx), "store_rows": len(self.store),
                   "seconds": round(time.perf_counter() - start, 2)})
        rows = self._rows(lambda c, k: c == -1)
        self.pre = rows  # the pretraining dataset: dict of arrays, float16 volumes (as stored)

    def _rows(self, select) -> dict[str, np.ndarray]:
        """Store rows whose (cycle, kind) pass ``select``; volumes float16 (the store's precision,
        half the host memory of float32; batches are cast on their way to the device)."""
        meta = self.store.read(("cycle", "kind"))
        keep = np.flatnonzero([select(int(c), str(k)) for c, k in zip(meta["cycle"], meta["kind"])])
        if keep.size == 0:
            return {f: np.zeros((0,), np.float32)
                    for f in ("object", "left", "right", "outcome", "kind", "name", "cycle")}
        # rows of one selection are contiguous chunks in practice; read the covering range once
        got = self.store.read(("object", "left", "right", "outcome", "kind", "name", "cycle"),
                              start=int(keep[0]), stop=int(keep[-1]) + 1)
        local = keep - keep[0]
        out = {k: v[local] for k, v in got.items()}
        for k in ("object", "left", "right"):
            out[k] = out[k].astype(np.float16)  # exact: the store holds float16
        return out

    def _baselines(self) -> None:
        """Imprint and flat-pad pairs on the held-out objects, simulated once into the store."""
        done = self.store.done_keys()
        if "heldout-baselines" in done:
            return
        objs, lefts, rights, kinds, names = [], [], [], [], []
        wl, wr = wsg50_fingers(self.cfg.geometry)
        for i in self.test_idx:
            il, ir = imprint_fingers(self.objects[i], self.cfg.geometry)
            for kind, (l, r) in zip(BASELINES, ((il, ir), (wl, wr))):
                objs.append(self.objects[i]); lefts.append(l); rights.append(r)
                kinds.append(kind); names.append(self.names[i])
        out = self._simulate(np.stack(objs), np.stack(lefts), np.stack(rights), "held-out baselines")
        self.store.append(np.stack(objs), np.stack(lefts), np.stack(rights), out, kind=kinds,
                          names=names, keys=["heldout-baselines"], cycle=-2)

    def _fmf_baseline(self) -> None:
        """The WSG-FMF fingers on the held-out objects, simulated once into the store (its own
        chunk: runs made before it, or without the pybullet extra, gain it when resumed with it)."""
        if f"heldout-{FMF_KIND}" in self.store.done_keys():
            return
        try:
            left, right = wsg_fmf_fingers(self.cfg.geometry)
        except ImportError as exc:  # MissingExtraError
            log.info("no %s baseline: %s", FMF_KIND, exc)
            return
        objs = np.stack([self.objects[i] for i in self.test_idx])
        lefts, rights = np.repeat(left[None], len(objs), 0), np.repeat(right[None], len(objs), 0)
        out = self._simulate(objs, lefts, rights, "held-out WSG-FMF baseline")
        self.store.append(objs, lefts, rights, out, kind=FMF_KIND,
                          names=[self.names[i] for i in self.test_idx],
                          keys=[f"heldout-{FMF_KIND}"], cycle=-2)

    def _simulate(self, objs, lefts, rights, what: str) -> np.ndarray:
        if self.progress:
            where = "" if self.executor == "threads" else f", {self.executor}"
            print(f"simulating {len(objs)} {what} ({self.backend}{where})", flush=True)
        return sim.evaluate(objs, lefts, rights, backend=self.backend, cfg=self.cfg,
                            progress=None if self.progress else False, executor=self.executor)

    # -- state ----------------------------------------------------------------------------------
    def _fresh_state(self) -> dict:
        cfg = self.cfg
        ae = init_autoencoder(cfg, self.seed)
        fn = init_fitness(cfg, self.seed + 1)
        gn = init_generator(cfg, self.seed + 2)
        gen_opt = S.generator_optimizer(cfg)
        return {
            "ae": new_state(ae, optimizer(cfg.train)),
            "fn": new_state(fn, optimizer(cfg.train)),
            "gn": new_state(gn, gen_opt),
            "key": jax.random.key_data(jax.random.key(self.seed)),
        }

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
        fresh = self._fresh_state()
        abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(np.shape(a), jnp.asarray(a).dtype), fresh)
        got = self.ckpt.restore(abstract) if self.ckpt.steps() else None
        if got is None:
            self.state = S.replicate(fresh)
            self.position = (-1, 0, 0)  # nothing done
            return
        restored, _, meta = got
        # restored leaves come back as numpy arrays in the saved structure; rebuild the pytree types
        leaves = jax.tree.leaves(restored)
        self.state = S.replicate(jax.tree.unflatten(jax.tree.structure(fresh), leaves))
        self.position = (STAGES.index(meta["stage"]), int(meta["epoch"]), int(meta["cycle"]))
        print(f"resuming {self.dir}: after {meta['stage']} epoch {meta['epoch']} cycle {meta['cycle']}",
              flush=True)

    def _done(self, stage: str, epoch: int = 0, cycle: int = 0) -> bool:
        return (STAGES.index(stage), epoch, cycle) <= self.position

    # -- epochs ---------------------------------------------------------------------------------
    def _epoch(self, stage: str, step_fn, batches, epoch: int, cycle: int = 0, desc: str = "") -> dict:
        """Run the steps of one epoch; returns the mean metrics (one host sync per epoch)."""
        key_name = "gn" if stage.startswith("gn") else stage
        start = time.perf_counter()
        first_step = int(self.state[key_name].step)
        metrics = []
        for args in tqdm(batches, desc=desc, leave=False, disable=not self.progress):
            self.state[key_name], m = step_fn(self.state[key_name], *args)
            metrics.append(m)
        host = jax.device_get(metrics)
        losses = np.array([m["loss"] for m in host], np.float64)
        _check_finite(losses, stage, first_step)
        out = {"stage": stage, "epoch": epoch, "cycle": cycle, "loss": float(losses.mean()),
               "steps": len(losses), "seconds": round(time.perf_counter() - start, 3)}
        for k in host[0]:
            if k != "loss":
                out[k] = np.mean([m[k] for m in host], axis=0).round(5).tolist()
        return out

    def _batches(self, n: int, batch: int, rng: np.random.Generator) -> list[np.ndarray]:
        """Index batches of one epoch: a shuffled pass, capped at max_steps_per_epoch, last batch
        filled up so every batch has the same shape (one compile)."""
        batch = min(batch, max(n, 1))
        steps = min(math.ceil(n / batch), self.cfg.train.max_steps_per_epoch)
        order = rng.permutation(n)
        need = steps * batch
        if need > n:
            order = np.concatenate([order, rng.choice(n, need - n)])
        return [order[i * batch:(i + 1) * batch] for i in range(steps)]

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
            batches = _Lazy(lambda i, b, key=key: (S.shard(shapes[b]), jax.random.fold_in(key, i)),
                            self._batches(len(shapes), t.ae_batch_size, rng))
            rec = self._epoch("ae", step, batches, epoch, desc=f"AE epoch {epoch}/{t.ae_epochs}")
            self._log(rec)
            self._save("ae", epoch, 0)

    def ae_iou(self, idx: np.ndarray | None = None) -> float:
        """Mean IoU of the solid voxels of held-out objects and their reconstructions."""
        idx = self.test_idx if idx is None else idx
        x = self.objects[idx]
        f, bs = S.ae_reconstruct(self.cfg), self.cfg.train.ae_batch_size
        recon = np.concatenate([np.asarray(f(self.state["ae"].variables, S.shard(x[s:s + bs])))
                                for s in range(0, len(x), bs)])
        a, b = x < 0, recon < 0
        inter = (a & b).sum(axis=(1, 2, 3))
        union = np.maximum((a | b).sum(axis=(1, 2, 3)), 1)
        return float(np.mean(inter / union))

    def _copy_ae_into_generator(self) -> None:
        """The generator's frozen encoder and decoder are the pretrained VAE's."""
        gn = self.state["gn"]
        params = dict(gn.params)
        stats = dict(gn.batch_stats)
        for part in ("encoder", "decoder"):
            # copies: the generator's state is donated to its steps, the VAE's must survive
            params[part] = jax.tree.map(jnp.copy, self.state["ae"].params[part])
            stats[part] = jax.tree.map(jnp.copy, self.state["ae"].batch_stats[part])
        self.state["gn"] = S.replicate(gn.replace(params=params, batch_stats=stats))

    def _fn_batches(self, *parts: dict, idx_batches) -> "_Lazy":
        """Fitness batches; with several data dicts, ``idx_batches`` holds one index array per
        dict for each batch, and the batch is their rows in that order (no full-set copies)."""
        def make(i, idx):
            idx = idx if len(parts) > 1 else (idx,)
            cols = [np.concatenate([p[k][j] for p, j in zip(parts, idx)]).astype(np.float32)
                    for k in ("object", "left", "right", "outcome")]
            return S.shard(*cols)
        return _Lazy(make, idx_batches)

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
        imprint = self.pre["kind"] == "imprint"
        data = {k: self.pre[k][imprint] for k in ("object", "left", "right")}
        step = S.gn_imprint_step(self.cfg)
        if not self._done("gn", 1):
            self._copy_ae_into_generator()
        for epoch in range(1, t.gn_epochs + 1):
            if self._done("gn", epoch):
                continue
            rng = self._rng("gn", epoch)
            batches = _Lazy(lambda i, b: S.shard(*(data[k][b].astype(np.float32)
                                                   for k in ("object", "left", "right"))),
                            self._batches(len(data["object"]), t.fn_batch_size, rng))
            rec = self._epoch("gn", step, batches, epoch, desc=f"GN epoch {epoch}/{t.gn_epochs}")
            self._log(rec)
            self._save("gn", epoch, 0)

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
        net refits at ``lr``); the optimiser state carries over, its structure does not change."""
        t = self.cfg.train
        if t.generator_lr is None or t.generator_lr == t.lr:
            return self.cfg
        return self.cfg.replace(train=dataclasses.replace(t, lr=t.generator_lr))

    def _generated(self, c: int) -> dict[str, np.ndarray]:
        """Every design simulated in cycles 1..c (the original's co-training dataset), read back
        from the store (float16, as on a resume) and kept between cycles."""
        got = getattr(self, "_gen", None)
        if got is not None and got[0] == c - 1 and len(got[1]["outcome"]):
            new = self._rows(lambda cyc, k: cyc == c)
            rows = {k: np.concatenate([got[1][k], v]) for k, v in new.items()}
        else:
            rows = self._rows(lambda cyc, k: 1 <= cyc <= c)
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

    def run_cycle(self, c: int) -> dict:
        t = self.cfg.train
        start = time.perf_counter()
        key = f"cycle-{c}"
        if key not in self.store.done_keys():
            rng = self._rng("cycle", c, 0)
            pick = rng.choice(self.train_idx, t.objects_per_cycle,
                              replace=t.objects_per_cycle > len(self.train_idx))
            objs = self.objects[pick]
            lefts, rights, feasible = self.generate(objs)
            out = self._simulate(objs, lefts, rights, f"cycle {c} designs")
            self.store.append(objs, lefts, rights, out, kind="generated",
                              names=[self.names[i] for i in pick], keys=[key], cycle=c)
        gen = self._generated(c)
        new = {k: v[gen["cycle"] == c] for k, v in gen.items()}
        g = self.cfg.geometry
        feasible = np.array([is_feasible(a, g) and is_feasible(b, g) for a, b in zip(new["left"], new["right"])])
        sim_seconds = time.perf_counter() - start
        fn_epochs = gn_epochs = 0
        warm = len(gen["outcome"]) >= t.warmup_designs
        # refit the fitness net on balanced batches: half designs of all cycles so far, half
        # pretraining rows; then train the generator against it (both after the warm-up)
        half = max(1, t.cotrain_batch_size // 2)
        step = S.fn_step(self.cfg)
        for epoch in range(1, t.max_epochs + 1 if warm else 1):
            rng = self._rng("cycle", c, 1, epoch)
            nb = self._batches(len(gen["outcome"]), half, rng)
            ob = [rng.choice(len(self.pre["outcome"]), len(b)) for b in nb]
            batches = self._fn_batches(gen, self.pre, idx_batches=list(zip(nb, ob)))
            rec = self._epoch("fn", step, batches, epoch, c, desc=f"cycle {c} FN epoch {epoch}")
            self._log(rec)
            fn_epochs = epoch
            if epoch >= t.min_epochs and rec["loss"] < t.fn_target_loss:
                break
        gstep = S.gn_fitness_step(self._cycle_cfg())
        fit_vars = self.state["fn"].variables

        def gn_batch(i, b):
            idx = self.train_idx[b]
            arrays = (self.objects[idx], *(self._imprints(idx) if t.imprint_anchor else ()))
            put = S.shard(*arrays)
            return (fit_vars, *(put if len(arrays) > 1 else (put,)))

        for epoch in range(1, t.max_epochs + 1 if warm else 1):
            rng = self._rng("cycle", c, 2, epoch)
            batches = _Lazy(gn_batch, self._batches(len(self.train_idx), t.cotrain_batch_size, rng))
            rec = self._epoch("gn", gstep, batches, epoch, c, desc=f"cycle {c} GN epoch {epoch}")
            self._log(rec)
            gn_epochs = epoch
            if epoch >= t.min_epochs and rec.get("fitness_loss", rec["loss"]) < t.gn_target_loss:
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
        self._check_cycles(cycles)
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
        paper's ImpGN row (``load_models(run_dir / "pretrained")``) and a start for variants."""
        if self._done("cycle", 0, 1):
            return  # a resumed run already past pretraining: the state is no longer that
        ckpt = Checkpoints(self.dir / "pretrained" / "checkpoints", max_to_keep=1)
        if not ckpt.steps():
            meta = {"stage": "gn", "epoch": self.cfg.train.gn_epochs, "cycle": 0,
                    "store_rows": len(self.store), "config_name": self.config_name,
                    "config": config_to_dict(self.cfg), "objectives": "imprint"}
            ckpt.save(self.state, self._models_tree(self.state), meta)

    def _check_cycles(self, cycles: int) -> None:
        """Refuse (before touching anything) to stop a run short of the cycles it already has:
        its generator is further along than the label the final evaluation would get."""
        ckpt = self.dir / "checkpoints"
        if not ckpt.is_dir() or not any(ckpt.iterdir()):
            return
        got = Checkpoints(ckpt).restore(None)
        if got is not None and got[2].get("stage") == "cycle" and int(got[2]["cycle"]) > cycles:
            have = int(got[2]["cycle"])
            raise CheckpointError(f"{self.dir} already holds {have} cycles; ask for at least that "
                                  f"many (--cycles {have}) or use another --run-dir")

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
        """Draw the curves of log.jsonl (last record per stage/epoch/cycle) to curves.png."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        path = self.dir / "log.jsonl"
        if not path.exists():
            return None
        recs = {}
        for line in path.read_text().splitlines():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by a kill
            recs[(r.get("stage"), r.get("cycle", 0), r.get("epoch", -1), r.get("label"))] = r
        recs = list(recs.values())
        fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
        for ax, stage, title in zip(axes[:3], ("ae", "fn", "gn"),
                                    ("shape VAE loss", "fitness BCE", "generator loss")):
            pts = [(r.get("cycle", 0), r["epoch"], r["loss"]) for r in recs
                   if r["stage"] == stage and "loss" in r]
            pts.sort()
            ax.plot(range(len(pts)), [p[2] for p in pts], ".-", ms=3)
            ax.set_title(title)
            ax.set_xlabel("epoch (pretraining, then cycles)")
            if stage == "fn":
                ho = [(r.get("cycle", 0), r["epoch"], r["heldout_bce"]) for r in recs
                      if r["stage"] == "fn" and "heldout_bce" in r]
                ho.sort()
                if ho:
                    ax.plot([i for i, _ in enumerate(ho)], [h[2] for h in ho], "r.-", ms=3,
                            label="held-out (pretraining)")
                    ax.legend(fontsize=7)
        cyc = sorted((r["cycle"], r) for r in recs if r["stage"] == "cycle")
        ax = axes[3]
        if cyc:
            xs = [c for c, _ in cyc]
            succ = np.array([r["success"] for _, r in cyc])
            ax.plot(xs, succ[:, 0], "o-", label="grasp")
            ax.plot(xs, succ[:, 1:5].mean(1), "s-", label="stability avg")
            ax.plot(xs, succ[:, 5:].mean(1), "^-", label="robustness avg")
            ax.plot(xs, [r["feasible"] for _, r in cyc], "k--", label="feasible")
            ax.legend(fontsize=7)
        ax.set_ylim(-0.02, 1.02)
        ax.set_title("generated designs per cycle (simulated)")
        ax.set_xlabel("cycle")
        fig.tight_layout()
        out = self.dir / "curves.png"
        with atomic_path(out) as tmp:
            fig.savefig(tmp, dpi=90)
        plt.close(fig)
        return out
