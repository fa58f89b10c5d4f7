"""A co-training run directory's record: what ``run.json`` holds, the checks that keep one
directory to one run, and starting a run from another run's pretraining.

``run.json`` records the config (less ``train.cycles``: a run may be extended), the object source
and the simulator backend.  A directory refuses a run that differs in any of them, naming the
differing fields; a run made before a newer simulator default goes on with the simulator its
store was filled by.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from f2f_jax.config import Config
from f2f_jax.dataset import GraspStore
from f2f_jax.errors import CheckpointError
from f2f_jax.fileio import atomic_path
from f2f_jax.train.checkpoint import Checkpoints, config_from_dict, config_to_dict

log = logging.getLogger(__name__)

# Settings that only change the co-training cycles: runs that differ in nothing else can share one
# pretraining (``copy_pretraining``), as the paper's ablations do.
COTRAIN_FIELDS = ("cycles", "objectives", "cycle_candidates", "generator_lr", "warmup_designs",
                  "objects_per_cycle", "cotrain_batch_size", "fn_target_loss", "gn_target_loss",
                  "min_epochs", "max_epochs", "teacher", "teacher_objects", "teacher_seed",
                  "teacher_candidates", "teacher_epochs", "teacher_lr", "teacher_chunk",
                  "teacher_fn_holdout", "teacher_copies", "teacher_tolerance", "teacher_min_lead")


def meta_config(cfg: Config) -> dict:
    """The config as ``run.json`` records it: without ``train.cycles``."""
    conf = config_to_dict(cfg)
    conf["train"].pop("cycles")
    return conf


def run_meta(cfg: Config, config_name: str, objects: str, backend: str) -> dict:
    return {"config_name": config_name, "config": meta_config(cfg), "objects": objects,
            "backend": backend}


def differing_fields(old: dict, new: dict) -> list[str]:
    """``section.field`` names whose values differ between two recorded configs."""
    return [f"{part}.{k}" for part in new for k in new[part]
            if old.get(part, {}).get(k) != new[part][k]]


def read_record(meta: dict, cycles: int) -> tuple[dict, Config | None]:
    """``meta`` with its config as ``config_from_dict`` reads it (fields added since the run was
    made take the values it was made with), and the Config itself with ``cycles`` (None when the
    record holds no readable config: it is compared as it is)."""
    try:
        conf = {part: dict(values) for part, values in meta["config"].items()}
        conf["train"]["cycles"] = cycles
        recorded = config_from_dict(conf)
    except (KeyError, TypeError, AttributeError):
        return meta, None
    return {**meta, "config": meta_config(recorded)}, recorded


def with_recorded_simulator(cfg: Config, recorded: Config | None, run_dir: Path) -> Config:
    """A run goes on with the simulator its store was filled by: where the recorded run differs
    from ``cfg`` in the simulation and geometry settings alone (a newer default, such as the 4 ms
    ``fast`` preset), the recorded ones; otherwise ``cfg`` as it is."""
    if recorded is None:
        return cfg
    same_model = (recorded.net, recorded.train) == (cfg.net, cfg.train)
    if same_model and (recorded.sim, recorded.geometry) != (cfg.sim, cfg.geometry):
        log.info("%s: going on with the simulator it was made with (timestep %g s, %s)",
                 run_dir, recorded.sim.timestep, recorded.sim.integrator)
        return cfg.replace(sim=recorded.sim, geometry=recorded.geometry)
    return cfg


def set_flags(old: dict, fields: list[str]) -> str:
    """The ``--set`` flags that give ``fields`` the values recorded in ``old`` (a run.json config),
    quoted for a shell where they hold spaces or brackets."""
    flags = []
    for key in fields:
        part, name = key.split(".", 1)
        value = old.get(part, {}).get(name)
        if isinstance(value, bool):
            text = str(value).lower()
        elif value is None:
            text = "none"
        elif isinstance(value, list):
            text = "(" + ", ".join(map(str, value)) + ("," if len(value) == 1 else "") + ")"
        else:
            text = str(value)
        flag = f"{key}={text}"
        flags.append("--set " + (f"'{flag}'" if any(c in flag for c in " ()[]") else flag))
    return " ".join(flags)


def check_record(run_dir: Path, old: dict, new: dict) -> None:
    """Refuse to go on in ``run_dir`` (recorded ``old``) with a run described by ``new``; where they
    differ in config fields alone, say which ``--set`` flags resume it."""
    if old.get("backend", new["backend"]) != new["backend"]:
        raise CheckpointError(
            f"{run_dir} was simulated with backend {old['backend']!r}; resume it with "
            f"--backend {old['backend']} (mixing simulators in one store would change it)")
    if old.get("config") != new["config"] or old.get("objects") != new["objects"]:
        fields = differing_fields(old.get("config") or {}, new["config"])
        raise CheckpointError(
            f"{run_dir} holds a run of config {old.get('config_name')!r} on objects "
            f"{old.get('objects')!r}; this one is {new['config_name']!r} on {new['objects']!r}"
            + (f" (they differ in {', '.join(fields)})" if fields else "")
            + ". Choose another --run-dir (nothing was changed)"
            + (f", or resume it with {set_flags(old['config'], fields)}"
               if fields and all(old.get(k) == new[k] for k in ("config_name", "objects")) else ""))


def write_record(run_dir: Path, meta: dict) -> None:
    """``run.json``, once: the first process of a run writes it."""
    path = run_dir / "run.json"
    if not path.exists():
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(meta, indent=1))


def check_cycles(run_dir: Path, cycles: int) -> None:
    """Refuse (before touching anything) to stop a run short of the cycles it already has: its
    generator is further along than the label the final evaluation would get."""
    ckpt = run_dir / "checkpoints"
    if not ckpt.is_dir() or not any(ckpt.iterdir()):
        return
    got = Checkpoints(ckpt).restore(None)
    if got is not None and got[2].get("stage") == "cycle" and int(got[2]["cycle"]) > cycles:
        have = int(got[2]["cycle"])
        raise CheckpointError(f"{run_dir} already holds {have} cycles; ask for at least that "
                              f"many (--cycles {have}) or use another --run-dir")


def _pretraining_log(path: Path) -> str:
    """The pretraining part of a run's log.jsonl (lines cut by a kill are dropped)."""
    keep = []
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            continue
        pretraining = r.get("stage") != "cycle" and r.get("cycle", 0) == 0
        if pretraining and r.get("label", "cycle 0") == "cycle 0":
            keep.append(line + "\n")
    return "".join(keep)


def source_record(run_dir: Path, src: Path, cycles: int) -> tuple[dict, Config | None]:
    """The record of the run that a new run in ``run_dir`` starts from (``read_record``), after
    checking that ``run_dir`` is new and that ``src`` finished its pretraining."""
    if run_dir.exists() and any(run_dir.iterdir()):
        raise CheckpointError(f"{run_dir} is not empty; a run started from {src} needs a new "
                              "--run-dir")
    if not (src / "run.json").exists() or not (src / "pretrained" / "checkpoints").is_dir():
        raise CheckpointError(f"{src} holds no finished pretraining (no run.json or pretrained/); "
                              f"make one with: python experiments/cotrain.py --run-dir {src} --cycles 1")
    return read_record(json.loads((src / "run.json").read_text()), cycles)


def copy_pretraining(run_dir: Path, src: Path, old: dict, new: dict) -> None:
    """Start the run recorded as ``new`` (a ``run_meta``) in the new directory ``run_dir`` from the
    end of the pretraining of the run in ``src`` (recorded as ``old``).

    Takes the source's objects, pretraining rows and held-out baselines, its pretrained models
    (``src/pretrained``) and their cycle-0 evaluation; the configs may differ only in
    ``COTRAIN_FIELDS`` (the objectives of the Table 1 ablations, the cycles' sizes, ...).
    Everything is staged in a hidden sibling directory and renamed into place at the end.
    """
    differ = [f for f in differing_fields(old["config"], new["config"])
              if f.split(".")[0] != "train" or f.split(".")[1] not in COTRAIN_FIELDS]
    differ += [k for k in ("objects", "backend") if old.get(k) != new[k]]
    if differ:
        raise CheckpointError(f"{src} was pretrained with other settings ({', '.join(differ)}); "
                              "only co-training settings may differ from the run it starts from")
    # the pretraining rows and baselines come before any cycle's designs: take the chunks that end
    # before the first designed row
    store = GraspStore(src / "store")
    cycles = store.read(("cycle",))["cycle"]
    first = int(np.argmax(cycles >= 1)) if (cycles >= 1).any() else len(cycles)
    ends = np.cumsum([c.rows for c in store.chunks()])
    pre = [c for c, end in zip(store.chunks(), ends) if end <= first]
    stage = run_dir.with_name(f".{run_dir.name}.fork-{os.getpid()}")
    try:
        shutil.rmtree(stage, ignore_errors=True)
        (stage / "store").mkdir(parents=True)
        shutil.copytree(src / "objects", stage / "objects")
        if (src / "imprint_objects").is_dir():  # the same config: the same extra objects
            shutil.copytree(src / "imprint_objects", stage / "imprint_objects")
        for c in pre:
            shutil.copy2(c.path, stage / "store" / c.path.name)
        shutil.copytree(src / "pretrained", stage / "pretrained")
        shutil.copytree(src / "pretrained" / "checkpoints", stage / "checkpoints")
        if (src / "eval-cycle0.json").exists():
            shutil.copy2(src / "eval-cycle0.json", stage / "eval-cycle0.json")
        (stage / "log.jsonl").write_text(_pretraining_log(src / "log.jsonl"))
        meta = {**new, "pretrained_from": str(src.resolve())}
        (stage / "run.json").write_text(json.dumps(meta, indent=1))
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        if run_dir.exists():
            run_dir.rmdir()  # empty (checked by source_record)
        os.replace(stage, run_dir)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
