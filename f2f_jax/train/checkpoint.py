"""Orbax checkpoints of a co-training run, verified on load.

A run directory keeps its checkpoints in ``<run>/checkpoints/<n>/`` (orbax ``CheckpointManager``:
each is written to a temporary directory and renamed when complete, so a kill never leaves a
half-written checkpoint under a final name).  Each holds three items:

* ``state``: every stage's ``TrainState`` (params, BatchNorm statistics, optimiser state, step) and
  the run's PRNG key data;
* ``models``: the generator's and the fitness net's variables alone, for ``load_trained_nets``;
* ``meta``: JSON with the stage, epoch, cycle, store offset, config and a SHA-1 of every array.

Loading walks from the newest checkpoint to the oldest and takes the first one that restores and
whose arrays match their recorded digest; a corrupt one is skipped with a warning, never used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from f2f_jax.config import SIM_PRESETS, Config, GeometryConfig, NetConfig, SimConfig, TrainConfig
from f2f_jax.errors import CheckpointError
from f2f_jax.nets.inference import TrainedNets

log = logging.getLogger(__name__)

DEFAULT_RUN_DIR = "runs/cotrain"
MAKE_ONE = "python experiments/cotrain.py --cycles 20"


def default_run_dir() -> Path:
    return Path(os.environ.get("F2F_RUN_DIR", DEFAULT_RUN_DIR))


# -- config <-> JSON ------------------------------------------------------------------------------
def config_to_dict(cfg: Config) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


# Fields added after runs were first saved, with the value those runs were made with: a run
# directory from before the simulation presets was simulated by what is now "reference", on coacd
# object pieces.
_BEFORE_PRESETS = {"GeometryConfig": {"object_method": "coacd"},
                   "SimConfig": SIM_PRESETS["reference"]["sim"]}

# Fields that have left the config (commit dd4f091 is the last to have them), with the value
# whose behaviour stayed: a record holding that value reads as today's config; any other value
# is refused, since today's code cannot run it.
RETIRED_FIELDS = {
    "SimConfig": {"push_point": "com", "finger_collisions": True},
    "NetConfig": {"height_truncation_voxels": 5.0, "fitness_stem_kernel": 5},
    "TrainConfig": {"gn_anneal_epochs": 0, "fn_refit_steps": None, "imprint_anchor": 0.0,
                    "anchor_target": "imprint", "perturbed_peak": 0.3},
}
# Values that have left a field that stays (commit dd4f091 is the last to have them): a record
# holding one is refused.  "imprint" was co-training's control (docs/learning.md has its result).
RETIRED_VALUES = {"TrainConfig": {"objectives": ("imprint",)}}


def _section(cls, values: dict):
    for name, kept in RETIRED_FIELDS.get(cls.__name__, {}).items():
        if name in values and values[name] != kept:
            raise CheckpointError(
                f"the recorded config sets {name}={values[name]!r}, a setting this version no longer "
                f"has (only {kept!r} remains); run it with f2f_jax at commit dd4f091")
    for name, gone in RETIRED_VALUES.get(cls.__name__, {}).items():
        if values.get(name) in gone:
            raise CheckpointError(
                f"the recorded config sets {name}={values[name]!r}, a value this version no longer "
                f"has; run it with f2f_jax at commit dd4f091")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in values:
            if f.name in _BEFORE_PRESETS.get(cls.__name__, {}):
                kwargs[f.name] = _BEFORE_PRESETS[cls.__name__][f.name]
            continue
        v = values[f.name]
        if isinstance(v, list):  # tuples (possibly of tuples) came back as lists
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kwargs[f.name] = v
    return cls(**kwargs)


def config_from_dict(d: dict) -> Config:
    return Config(geometry=_section(GeometryConfig, d["geometry"]), sim=_section(SimConfig, d["sim"]),
                  net=_section(NetConfig, d["net"]), train=_section(TrainConfig, d["train"]))


# -- integrity ------------------------------------------------------------------------------------
def tree_digest(tree: Any) -> str:
    """SHA-1 over the bytes, shapes and dtypes of every array leaf, in tree order."""
    h = hashlib.sha1()
    for leaf in jax.tree.leaves(tree):
        a = np.asarray(leaf)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _to_host(tree: Any) -> Any:
    return jax.tree.map(np.asarray, jax.device_get(tree))


class Checkpoints:
    """The checkpoints of one run directory.

    save(index, state_tree, models_tree, meta): synchronous; index grows with every save.
    restore(abstract_state): newest verified (state, models, meta), or None when there is none.
    """

    def __init__(self, directory, max_to_keep: int = 3):
        self.directory = Path(directory).absolute()
        self.directory.mkdir(parents=True, exist_ok=True)
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                               enable_async_checkpointing=False,
                                               cleanup_tmp_directories=True)
        self._manager = ocp.CheckpointManager(self.directory, options=options,
                                              item_names=("state", "models", "meta"))

    def steps(self) -> list[int]:
        self._manager.reload()
        return sorted(self._manager.all_steps())

    def next_index(self) -> int:
        steps = self.steps()
        return (steps[-1] + 1) if steps else 0

    def save(self, state: Any, models: Any, meta: dict) -> int:
        index = self.next_index()
        state, models = _to_host(state), _to_host(models)
        meta = dict(meta, state_sha1=tree_digest(state), models_sha1=tree_digest(models))
        self._manager.save(index, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), models=ocp.args.StandardSave(models),
            meta=ocp.args.JsonSave(meta)))
        self._manager.wait_until_finished()
        return index

    def _restore(self, index: int, abstract_state: Any | None):
        meta = self._manager.restore(index, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        meta = dict(meta, index=index)
        items = {"models": ocp.args.StandardRestore()}
        if abstract_state is not None:
            items["state"] = ocp.args.StandardRestore(abstract_state)
        got = self._manager.restore(index, args=ocp.args.Composite(**items))
        models = _to_host(got["models"])
        if tree_digest(models) != meta.get("models_sha1"):
            raise CheckpointError("models arrays do not match their recorded digest")
        state = None
        if abstract_state is not None:
            state = _to_host(got["state"])
            if tree_digest(state) != meta.get("state_sha1"):
                raise CheckpointError("state arrays do not match their recorded digest")
        return state, models, meta

    def restore(self, abstract_state: Any | None = None):
        """Newest checkpoint that restores and verifies: (state, models, meta), or None.

        abstract_state: a tree of ``jax.ShapeDtypeStruct`` (or arrays) shaped like the saved
        state; None restores only ``models`` and ``meta``.
        """
        for index in reversed(self.steps()):
            try:
                return self._restore(index, abstract_state)
            except Exception as exc:  # any failure to read or verify: fall back to an older one
                msg = (f"checkpoint {self.directory / str(index)} is unreadable or corrupt "
                       f"({type(exc).__name__}: {str(exc)[:200]}); skipped")
                warnings.warn(msg, stacklevel=2)
                log.warning(msg)
        return None

    def restore_like(self, fresh: Any) -> tuple[Any, dict | None]:
        """The newest checkpoint's state in the pytree types of ``fresh`` (a state of the same
        layout, e.g. before any step) and its meta; ``(fresh, None)`` when there is none."""
        abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(np.shape(a), np.asarray(a).dtype), fresh)
        got = self.restore(abstract) if self.steps() else None
        if got is None:
            return fresh, None
        restored, _, meta = got
        # restored leaves come back as numpy arrays in the saved structure; rebuild the pytree types
        return jax.tree.unflatten(jax.tree.structure(fresh), jax.tree.leaves(restored)), meta


def load_trained_nets(run_dir=None):
    """The generator and fitness net of the newest complete checkpoint of a co-training run.

    run_dir: default ``$F2F_RUN_DIR`` or ``runs/cotrain``.
    Returns ``f2f_jax.nets.inference.TrainedNets``.  Raises CheckpointError, naming the command that makes
    a checkpoint, when the directory holds none that can be read.
    """
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir()
    ckpt_dir = run_dir / "checkpoints"
    if not ckpt_dir.is_dir() or not any(ckpt_dir.iterdir()):
        raise CheckpointError(f"no checkpoint in {run_dir}: train one with `{MAKE_ONE} --run-dir "
                              f"{run_dir}` (or pass params=)")
    got = Checkpoints(ckpt_dir).restore(None)
    if got is None:
        raise CheckpointError(f"no readable checkpoint in {ckpt_dir}; rerun `{MAKE_ONE} --run-dir "
                              f"{run_dir}`")
    _, models, meta = got
    return TrainedNets(config=config_from_dict(meta["config"]), generator=models["generator"],
                  fitness=models["fitness"], objectives=meta.get("objectives", "full"),
                  source=f"{ckpt_dir / str(meta['index'])} (stage {meta.get('stage')}, "
                         f"cycle {meta.get('cycle')})")
