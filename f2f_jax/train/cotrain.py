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
5. ``gn``: the generator regressed onto the training objects' imprint fingers (``gn_epochs``): the
   latent generator onto their latents, the height generator onto their height maps; with
   ``imprint_objects`` N, the imprints of N more built-in objects too (made into the run's
   ``imprint_objects/`` in stage 1, never simulated).
6. ``cycle`` 1..N (``f2f_jax.train.cycle``): sample training objects, generate fingers, simulate
   them, append to the store; once ``warmup_designs`` designs exist, refit the fitness net on
   balanced batches (half designs of every cycle so far, half the pretraining data) until its BCE
   < ``fn_target_loss`` (``min_epochs``..``max_epochs``) and train the generator against it until
   its loss < ``gn_target_loss``.  With ``cycle_candidates`` K > 1 each sampled object gets K
   designs: the generator's own and K - 1 latent perturbations, all simulated.  With
   ``train.teacher`` "simulator" the cycles are expert iteration instead (``f2f_jax.train.teacher``:
   the generator regressed onto each teacher object's best-simulated pair), with "imprint" its
   control.

The run's settings are fixed when it is made; what changes while it runs (its data, the nets'
states, its checkpoints and how far they go) is one ``run_state.RunState``, made by ``run`` and
handed to every stage.  Every source of randomness is derived from (seed, stage, cycle, epoch),
never from how far an earlier process got, which is what makes resuming exact.  Each epoch appends
a JSON line to ``log.jsonl``; each cycle redraws ``curves.png``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import jax
import numpy as np

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES, Config
from f2f_jax.errors import CheckpointError, ConfigError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import imprint_fingers
from f2f_jax.nets import generator_module
from f2f_jax.nets.shape import TRUNCATION_VOXELS
from f2f_jax.train import steps as S
from f2f_jax.train.checkpoint import Checkpoints, config_to_dict
from f2f_jax.train.curves import plot_curves
from f2f_jax.train.cycle import generate, run_cycle
from f2f_jax.train.epochs import LazyBatches, index_batches, row_batches, run_epoch
from f2f_jax.train.losses import OBJECTIVE_MASKS
from f2f_jax.train.run_data import BASELINES, FMF_KIND, RunData, prepare_run_data, read_rows
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
from f2f_jax.train.run_state import NOTHING_DONE, STAGES, RunState
from f2f_jax.train.teacher import check_teacher, run_teacher_cycle
from f2f_jax.train.state import fresh_run_state, with_codec_of

log = logging.getLogger(__name__)

_STAGE_ID = {"ae": 1, "fn": 2, "gn": 3, "cycle": 4, "eval": 5}
OBJECTIVES = tuple(OBJECTIVE_MASKS)  # TrainConfig.objectives: the fitness outputs the generator maximises


def check_config(cfg: Config) -> None:
    """Raise ConfigError (a ValueError) for a config a run cannot train."""
    t = cfg.train
    if t.cycle_candidates < 1:
        raise ConfigError(f"train.cycle_candidates must be >= 1, got {t.cycle_candidates}")
    if t.gn_passes < 1:
        raise ConfigError(f"train.gn_passes must be >= 1, got {t.gn_passes}")
    if t.imprint_objects < 0:
        raise ConfigError(f"train.imprint_objects must be >= 0, got {t.imprint_objects}")
    problems = check_teacher(t)
    if problems:
        raise ConfigError("; ".join(problems))
    if t.objectives not in OBJECTIVES:
        retired = (" (co-training's imprint control was retired after commit dd4f091; its result is "
                   "in docs/learning.md)") if t.objectives == "imprint" else ""
        raise ConfigError(f"train.objectives must be one of {OBJECTIVES}, got {t.objectives!r}{retired}")
    if cfg.geometry.object_scale not in ("stretch", "fit"):
        raise ConfigError("geometry.object_scale must be 'stretch' or 'fit' (how the run's "
                          f"meshes are placed in the cube), got {cfg.geometry.object_scale!r}")
    generator_module(cfg.net)  # ConfigError on an unknown net.generator
    if cfg.net.generator == "heights" and cfg.geometry.truncation_voxels != TRUNCATION_VOXELS:
        raise ConfigError(
            f"geometry.truncation_voxels must be {TRUNCATION_VOXELS} with the height generator, got "
            f"{cfg.geometry.truncation_voxels}: its fingers are TSDFs truncated at {TRUNCATION_VOXELS} "
            "voxels, and must be like the imprints the fitness net learns from")


class CoTrainRun:
    """One run directory: ``objects/``, ``store/``, ``checkpoints/``, ``log.jsonl``, ``run.json``,
    ``curves.png``, ``summary.json``, ``pretrained/`` (the models after pretraining: ImpGN).

    cfg: the run's Config (a directory made before a newer simulator default goes on with its own
    simulator unless ``keep_simulator`` is False); config_name: its name, recorded (a run directory
    refuses a different config); objects: "builtin", "pybullet" or a mesh directory; backend: the
    simulator ("mujoco", "mjx" or "warp"); executor: where it runs ("threads", or "ray": the
    pretraining dataset's and every cycle's simulation in Ray tasks, ``sim.evaluate``); not part
    of the run: a run may be resumed with either; progress: tqdm bars.
    """

    def __init__(self, run_dir, cfg: Config, *, config_name: str = "custom", objects: str = "builtin",
                 backend: str = "mujoco", progress: bool = True, executor: str = "threads",
                 keep_simulator: bool = True):
        check_config(cfg)
        self.dir = Path(run_dir)
        self.config_name = config_name
        self.source = objects
        self.backend = backend
        self.executor = executor
        self.progress = progress
        self.seed = cfg.train.seed
        self.cfg = self._recorded_cfg(cfg, keep_simulator)

    @classmethod
    def from_pretrained(cls, run_dir, source, cfg: Config, **kwargs) -> CoTrainRun:
        """A run whose cycles start from the end of another run's pretraining, in ``source``
        (``run_dir.copy_pretraining``: the paper's ablations share one pretraining).  A new
        ``run_dir`` is made from it; an existing one goes on when it was made so from ``source``.
        kwargs: the constructor's."""
        src = Path(source).resolve()
        run = cls(run_dir, cfg, **kwargs)
        if (run.dir / "run.json").exists():
            if json.loads((run.dir / "run.json").read_text()).get("pretrained_from") != str(src):
                raise CheckpointError(f"{run.dir} was not started from {src}; choose another --run-dir")
            return run
        old, recorded = source_record(run.dir, src, cfg.train.cycles)
        if kwargs.get("keep_simulator", True):  # the source's store: the source's simulator
            cfg = with_recorded_simulator(cfg, recorded, run.dir)
        copy_pretraining(run.dir, src, old, run_meta(cfg, run.config_name, run.source, run.backend))
        print(f"{run.dir}: starts from the pretraining of {src}", flush=True)
        return cls(run_dir, cfg, **kwargs)

    # -- bookkeeping --------------------------------------------------------------------------
    def _run_meta(self) -> dict:
        return run_meta(self.cfg, self.config_name, self.source, self.backend)

    def _recorded_cfg(self, cfg: Config, keep_simulator: bool) -> Config:
        """``cfg``, checked against the directory's ``run.json`` (when there is one), with the
        simulator the run was made with when ``keep_simulator``."""
        path = self.dir / "run.json"
        if not path.exists():
            return cfg
        old, recorded = read_record(json.loads(path.read_text()), cfg.train.cycles)
        if keep_simulator:  # else a chosen simulator is refused by the check below
            cfg = with_recorded_simulator(cfg, recorded, self.dir)
        check_record(self.dir, old, run_meta(cfg, self.config_name, self.source, self.backend))
        return cfg

    def log(self, record: dict) -> None:
        """Append ``record`` to the run's ``log.jsonl``."""
        with open(self.dir / "log.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")
        log.info("%s", record)

    def key(self, stage: str, *counters: int) -> jax.Array:
        """The JAX PRNG key of (seed, stage, counters...)."""
        key = jax.random.key(self.seed)
        for c in (_STAGE_ID[stage], *counters):
            key = jax.random.fold_in(key, c)
        return key

    def rng(self, stage: str, *counters: int) -> np.random.Generator:
        """The numpy generator of (seed, stage, counters...)."""
        return np.random.default_rng([self.seed, _STAGE_ID[stage], *counters])

    def simulate(self, objs, lefts, rights, what: str) -> np.ndarray:
        """Outcomes [N, 11] of the triples in the run's simulator (``sim.evaluate``)."""
        if self.progress:
            where = "" if self.executor == "threads" else f", {self.executor}"
            print(f"simulating {len(objs)} {what} ({self.backend}{where})", flush=True)
        return sim.evaluate(objs, lefts, rights, backend=self.backend, cfg=self.cfg,
                            progress=None if self.progress else False, executor=self.executor)

    def batches(self, n: int, batch: int, rng: np.random.Generator) -> list[np.ndarray]:
        """One epoch's index batches, at most ``max_steps_per_epoch`` of them."""
        return index_batches(n, batch, self.cfg.train.max_steps_per_epoch, rng)

    def epoch(self, st: RunState, stage: str, step_fn, batches, epoch: int, cycle: int = 0,
              desc: str = "") -> dict:
        """Run the steps of one epoch on the stage's net in ``st`` (``epochs.run_epoch``)."""
        st.nets[stage], rec = run_epoch(st.nets[stage], step_fn, batches, stage, epoch, cycle,
                                        desc=desc, progress=self.progress)
        return rec

    def save(self, st: RunState, stage: str, epoch: int, cycle: int) -> None:
        """A checkpoint of ``st``'s nets after (stage, epoch, cycle)."""
        meta = {"stage": stage, "epoch": epoch, "cycle": cycle, "store_rows": len(st.data.store),
                "config_name": self.config_name, "config": config_to_dict(self.cfg),
                "objectives": self.cfg.train.objectives}
        st.ckpt.save(st.nets, st.models_tree(), meta)
        st.position = (STAGES.index(stage), epoch, cycle)

    # -- data and state -------------------------------------------------------------------------
    def prepare_data(self) -> RunData:
        """Objects, split, the grasp dataset and the held-out baselines (``run_data``)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        write_record(self.dir, self._run_meta())
        start = time.perf_counter()
        data = prepare_run_data(self.dir, self.cfg, self.source, self.simulate, backend=self.backend,
                                executor=self.executor, progress=self.progress)
        self.log({"stage": "data", "objects": len(data.names), "train": len(data.train_idx),
                  "test": len(data.test_idx), "imprint_objects": len(data.imprint_objects),
                  "store_rows": len(data.store), "seconds": round(time.perf_counter() - start, 2)})
        return data

    def start(self) -> RunState:
        """The run's data (made once) and its nets from the newest checkpoint, or fresh."""
        data = self.prepare_data()
        hb = read_rows(data.store, lambda c, k: c == -2)
        keep = np.isin(hb["name"], [data.names[i] for i in data.eval_idx])
        ckpt = Checkpoints(self.dir / "checkpoints")
        nets, meta = ckpt.restore_like(fresh_run_state(self.cfg, self.seed))
        st = RunState(data=data, heldout={k: v[keep] for k, v in hb.items()}, ckpt=ckpt,
                      nets=S.replicate(nets), position=NOTHING_DONE)
        if meta is not None:
            st.position = (STAGES.index(meta["stage"]), int(meta["epoch"]), int(meta["cycle"]))
            print(f"resuming {self.dir}: after {meta['stage']} epoch {meta['epoch']} cycle {meta['cycle']}",
                  flush=True)
        return st

    # -- pretraining ----------------------------------------------------------------------------
    def pretrain_ae(self, st: RunState) -> None:
        t, data = self.cfg.train, st.data
        finger_rows = np.isin(data.pre["kind"], ("imprint", "cut"))
        shapes = np.concatenate([data.objects[data.train_idx], data.pre["left"][finger_rows],
                                 data.pre["right"][finger_rows]]).astype(np.float32)
        step = S.ae_step(self.cfg)
        for epoch in range(1, t.ae_epochs + 1):
            if st.done("ae", epoch):
                continue
            rng, key = self.rng("ae", epoch), self.key("ae", epoch)
            batches = LazyBatches(lambda i, b, key=key: (S.shard(shapes[b]), jax.random.fold_in(key, i)),
                                  self.batches(len(shapes), t.ae_batch_size, rng))
            rec = self.epoch(st, "ae", step, batches, epoch, desc=f"AE epoch {epoch}/{t.ae_epochs}")
            self.log(rec)
            self.save(st, "ae", epoch, 0)

    def ae_iou(self, st: RunState, idx: np.ndarray | None = None) -> float:
        """Mean IoU of the solid voxels of held-out objects and their reconstructions."""
        x = st.data.objects[st.data.test_idx if idx is None else idx]
        return S.reconstruction_iou(self.cfg, st.nets["ae"].variables, x)

    def fn_heldout_bce(self, st: RunState) -> float:
        """Fitness BCE on the held-out baseline triples (imprint and WSG50 on unseen objects)."""
        f = S.fn_eval(self.cfg)
        cols = [st.heldout[k].astype(np.float32) for k in ("object", "left", "right", "outcome")]
        loss, _ = f(st.nets["fn"].variables, *S.shard(*cols))
        return float(loss)

    def pretrain_fn(self, st: RunState) -> None:
        t, pre = self.cfg.train, st.data.pre
        step = S.fn_step(self.cfg)
        for epoch in range(1, t.fn_epochs + 1):
            if st.done("fn", epoch):
                continue
            if epoch == 1:
                self.log({"stage": "fn", "epoch": 0, "heldout_bce": self.fn_heldout_bce(st)})
            rng = self.rng("fn", epoch)
            batches = row_batches(pre, idx_batches=self.batches(len(pre["outcome"]), t.fn_batch_size, rng))
            rec = self.epoch(st, "fn", step, batches, epoch, desc=f"FN epoch {epoch}/{t.fn_epochs}")
            rec["heldout_bce"] = self.fn_heldout_bce(st)
            self.log(rec)
            self.save(st, "fn", epoch, 0)

    def pretrain_gn(self, st: RunState) -> None:
        t = self.cfg.train
        data = self.imprint_pairs(st)
        if not st.done("gn", 1):
            # the generator's frozen encoder and decoder are the pretrained VAE's
            st.nets["gn"] = S.replicate(with_codec_of(st.nets["gn"], st.nets["ae"]))
        step = S.gn_imprint_step(self.cfg)
        for epoch in range(1, t.gn_epochs + 1):
            if st.done("gn", epoch):
                continue
            rng = self.rng("gn", epoch)
            index = [b for _ in range(t.gn_passes)
                     for b in self.batches(len(data["object"]), t.fn_batch_size, rng)]
            batches = LazyBatches(lambda i, b: S.shard(*(data[k][b].astype(np.float32)
                                                         for k in ("object", "left", "right"))), index)
            rec = self.epoch(st, "gn", step, batches, epoch, desc=f"GN epoch {epoch}/{t.gn_epochs}")
            self.log(rec)
            self.save(st, "gn", epoch, 0)

    def imprint_pairs(self, st: RunState) -> dict[str, np.ndarray]:
        """The generator's pretraining data, float16: the training objects' imprint rows, then the
        imprint pairs of the run's extra imprint objects (``TrainConfig.imprint_objects``)."""
        if st.pairs is not None:
            return st.pairs
        pre, extra = st.data.pre, st.data.imprint_objects
        imprint = pre["kind"] == "imprint"
        data = {k: pre[k][imprint] for k in ("object", "left", "right")}
        if len(extra):
            pairs = [imprint_fingers(o.astype(np.float32), self.cfg.geometry) for o in extra]
            more = {"object": extra, "left": np.stack([p[0] for p in pairs]).astype(np.float16),
                    "right": np.stack([p[1] for p in pairs]).astype(np.float16)}
            data = {k: np.concatenate([data[k], more[k]]) for k in data}
        st.pairs = data
        return data

    def _keep_pretrained(self, st: RunState) -> None:
        """The models at the end of pretraining, kept apart from the rolling checkpoints: the
        paper's ImpGN row (``load_trained_nets(run_dir / "pretrained")``) and a start for variants."""
        if st.done("cycle", 0, 1):
            return  # a resumed run already past pretraining: the state is no longer that
        ckpt = Checkpoints(self.dir / "pretrained" / "checkpoints", max_to_keep=1)
        if not ckpt.steps():
            meta = {"stage": "gn", "epoch": self.cfg.train.gn_epochs, "cycle": 0,
                    "store_rows": len(st.data.store), "config_name": self.config_name,
                    "config": config_to_dict(self.cfg), "objectives": "imprint"}
            ckpt.save(st.nets, st.models_tree(), meta)

    # -- held-out evaluation --------------------------------------------------------------------
    def evaluate_heldout(self, st: RunState, label: str) -> dict:
        """Simulated success of the current generator on the held-out evaluation objects."""
        objs = st.data.objects[st.data.eval_idx]
        lefts, rights, feasible = generate(self.cfg, st.nets["gn"].variables, objs)
        out = self.simulate(objs, lefts, rights, f"held-out designs ({label})")
        res = {"stage": "eval", "label": label, "objects": len(objs),
               "feasible": float(feasible.mean()), "success": out.mean(0).round(4).tolist()}
        self.log(res)
        return res

    def _eval_record(self, st: RunState, label: str, cycle: int) -> dict:
        """Held-out evaluation of the generator after ``cycle``, cached in the run directory so
        that a resumed run reports the figure of the run that produced it."""
        path = self.dir / f"eval-cycle{cycle}.json"
        if path.exists():
            return {label: json.loads(path.read_text())}
        res = self.evaluate_heldout(st, label)
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(res))
        return {label: res}

    def summary(self, st: RunState, evals: dict, iou: float, seconds: float) -> dict:
        rows = {}
        hb = st.heldout
        for kind in (*BASELINES, FMF_KIND):
            sel = hb["kind"] == kind
            rows[kind] = hb["outcome"][sel].mean(0).round(4).tolist() if sel.any() else None
        for label, res in evals.items():
            rows[f"generator, {label}"] = res["success"]
        return {"held_out_objects": int(len(st.data.eval_idx)), "ae_heldout_iou": round(iou, 4),
                "success": rows, "trials": list(TRIAL_NAMES), "seconds_this_process": round(seconds, 1)}

    # -- the whole run --------------------------------------------------------------------------
    def run(self, cycles: int | None = None) -> dict:
        cycles = self.cfg.train.cycles if cycles is None else cycles
        if cycles < 0:
            raise ValueError(f"cycles must be >= 0, got {cycles}")
        t0 = time.perf_counter()
        check_cycles(self.dir, cycles)
        st = self.start()
        self.pretrain_ae(st)
        iou = self.ae_iou(st)
        self.log({"stage": "ae", "heldout_iou": iou})
        self.pretrain_fn(st)
        self.pretrain_gn(st)
        self._keep_pretrained(st)
        evals = self._eval_record(st, "cycle 0", 0)
        for c in range(1, cycles + 1):
            if st.done("cycle", 0, c):
                continue
            if self.cfg.train.teacher == "fitness":
                s = run_cycle(self, st, c)
                line = (f"{s['designs']} designs, feasible {s['feasible']:.2f}, grasp {s['success'][0]:.2f}, "
                        f"FN {s['fn_epochs']} / GN {s['gn_epochs']} epochs")
            else:
                s = run_teacher_cycle(self, st, c)
                line = f"taught by the {s['teacher']}, {s['designs']} designs"
                if "improved_objects" in s:
                    rho = "n/a" if s["fn_spearman"] is None else f"{s['fn_spearman']:+.2f}"
                    line += (f", {s['improved_objects']} of {s['objects']} objects better than their "
                             f"imprint, FN within-object Spearman {rho}")
            if self.progress:
                print(f"cycle {c}/{cycles}: {line}, {s['seconds']:.0f} s", flush=True)
            self.plot()
        if cycles:
            evals.update(self._eval_record(st, f"cycle {cycles}", cycles))
        summary = self.summary(st, evals, iou, time.perf_counter() - t0)
        with atomic_path(self.dir / "summary.json") as tmp:
            tmp.write_text(json.dumps(summary, indent=1))
        self.plot()
        return summary

    def plot(self) -> Path | None:
        """Draw the curves of log.jsonl to curves.png (``curves.plot_curves``)."""
        return plot_curves(self.dir)
