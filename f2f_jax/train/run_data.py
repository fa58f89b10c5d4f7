"""A co-training run's data: its object set and split, the pretraining grasp dataset, and the
held-out baselines, each made once into the run directory and read back on a resume.

Rows are read from the grasp store with their volumes as float16 (the store's precision, half the
host memory of float32); batches are cast on their way to the device.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from f2f_jax.config import Config
from f2f_jax.data import load_or_make_builtin_range, load_or_make_objects, object_split
from f2f_jax.data.sources import wsg_fmf_fingers
from f2f_jax.dataset import GraspStore, build_grasp_dataset
from f2f_jax.errors import F2FError
from f2f_jax.geometry import imprint_fingers, wsg50_fingers

log = logging.getLogger(__name__)

BASELINES = ("imprint", "wsg50")  # flat pads, as the store's kind "wsg50" has always been
FMF_KIND = "wsg50-fmf"  # the paper's WSG50 fingers (Schunk WSG-FMF), with the pybullet extra
ROW_FIELDS = ("object", "left", "right", "outcome", "kind", "name", "cycle")
# (objects [N, R, R, R], lefts, rights, what) -> outcomes [N, 11]: the run's simulator
Simulate = Callable[[np.ndarray, np.ndarray, np.ndarray, str], np.ndarray]


@dataclass
class RunData:
    """objects: [N, R, R, R] float32 volumes of the whole set; names: theirs; train_idx, test_idx:
    the split as indices; eval_idx: the held-out objects the generator is evaluated on; store: the
    run's grasp store; pre: the pretraining rows (``read_rows`` of cycle -1, their object volumes
    ``SharedVolumes``); imprint_objects:
    [M, R, R, R] float16 volumes of the objects whose imprints only the generator's pretraining
    sees (``TrainConfig.imprint_objects``; M = 0 without them); object_table: ``objects`` in
    float16, as the store holds them, the table every ``SharedVolumes`` of the run's rows indexes."""

    objects: np.ndarray
    names: list[str]
    train_idx: np.ndarray
    test_idx: np.ndarray
    eval_idx: np.ndarray
    store: GraspStore
    pre: dict[str, np.ndarray]
    imprint_objects: np.ndarray
    object_table: np.ndarray


class SharedVolumes:
    """The object volumes of many rows as one table of the run's objects and a row -> object index:
    the K designs of one object share its volume instead of holding K copies (a third of a row's
    memory; the workstation config's ~87k rows would otherwise hold ~10 GiB of copies).

    Indexing with rows (integers, a slice, a mask) gives the volumes as an array, as indexing the
    full [N, R, R, R] array would; ``len`` and ``shape`` are the full array's."""

    def __init__(self, table: np.ndarray, index: np.ndarray):
        self.table, self.index = table, np.asarray(index, np.int32)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, rows) -> np.ndarray:
        return self.table[self.index[rows]]

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.index), *self.table.shape[1:])

    @property
    def dtype(self):
        return self.table.dtype

    def concatenate(self, other: "SharedVolumes") -> "SharedVolumes":
        if other.table is not self.table:
            raise ValueError("SharedVolumes of different tables cannot be joined")
        return SharedVolumes(self.table, np.concatenate([self.index, other.index]))


def read_rows(store: GraspStore, select: Callable[[int, str], bool],
              objects: tuple[np.ndarray, list[str]] | None = None) -> dict[str, np.ndarray]:
    """Store rows whose (cycle, kind) pass ``select``, as ``ROW_FIELDS`` arrays; volumes float16.

    objects: (float16 volumes [N, R, R, R], their N names), the run's objects as the store holds
    them: rows' object volumes are then not read but shared from it (``SharedVolumes``); the first
    row read is checked against it, and a row naming no object in it is an error."""
    meta = store.read(("cycle", "kind"))
    keep = np.flatnonzero([select(int(c), str(k)) for c, k in zip(meta["cycle"], meta["kind"])])
    if keep.size == 0:
        return {f: np.zeros((0,), np.float32) for f in ROW_FIELDS}
    # rows of one selection are contiguous chunks in practice; read the covering range once
    start, stop = int(keep[0]), int(keep[-1]) + 1
    fields = ROW_FIELDS if objects is None else tuple(f for f in ROW_FIELDS if f != "object")
    got = store.read(fields, start=start, stop=stop)
    local = keep - keep[0]
    out = {k: v[local] for k, v in got.items()}
    for k in ("object", "left", "right"):
        if k in out:
            out[k] = out[k].astype(np.float16)  # exact: the store holds float16
    if objects is not None:
        table, names = objects
        where = {str(n): i for i, n in enumerate(names)}
        unknown = sorted({str(n) for n in out["name"]} - set(where))
        if unknown:
            raise F2FError(f"{store.root}: rows of objects {unknown[:3]} that are not the run's")
        shared = SharedVolumes(table, [where[str(n)] for n in out["name"]])
        first = store.read(("object",), start=start, stop=start + 1)["object"].astype(np.float16)
        if not np.array_equal(first, shared[:1]):
            raise F2FError(f"{store.root}: the stored volume of {out['name'][0]} is not the run's object "
                           "of that name (another object set?)")
        out["object"] = shared
    return {k: out[k] for k in ROW_FIELDS}


def prepare_run_data(run_dir: Path, cfg: Config, source: str, simulate: Simulate, *,
                     backend: str, executor: str, progress: bool) -> RunData:
    """Objects, split, the grasp dataset, the held-out baselines and the generator's extra imprint
    objects of a run (each resumable)."""
    t = cfg.train
    n = t.n_objects if source == "builtin" else None
    tsdfs, names = load_or_make_objects(source, n, t.seed, run_dir / "objects", cfg.geometry,
                                        progress=progress, test_fraction=t.test_fraction)
    split = object_split(run_dir / "objects")
    index = {name: i for i, name in enumerate(names)}
    train_idx = np.array([index[n] for n in split["train"] if n in index])
    test_idx = np.array([index[n] for n in split["test"] if n in index])
    if len(train_idx) < 2 or len(test_idx) < 1:
        raise F2FError(f"{len(names)} usable objects give {len(train_idx)} training and "
                       f"{len(test_idx)} held-out objects; need at least 2 and 1")
    store = GraspStore(run_dir / "store")
    store.clean_temporary()
    build_grasp_dataset(tsdfs[train_idx], [names[i] for i in train_idx], store, cfg=cfg, seed=t.seed,
                        n_cut=t.cut_pairs, n_perturbed=t.perturbed_pairs, backend=backend,
                        progress=progress, executor=executor)
    extra = np.zeros((0,) + tsdfs.shape[1:], np.float16)
    if t.imprint_objects:
        extra, _ = load_or_make_builtin_range(run_dir / "imprint_objects", t.n_objects, t.imprint_objects,
                                              t.seed, cfg.geometry, progress=progress)
        extra = extra.astype(np.float16)  # exact: kept as float16
    data = RunData(objects=tsdfs, names=names, train_idx=train_idx, test_idx=test_idx,
                   eval_idx=test_idx[: t.eval_objects], store=store, pre={}, imprint_objects=extra,
                   object_table=tsdfs.astype(np.float16))  # exact: the store holds float16
    simulate_baselines(data, cfg, simulate)
    simulate_fmf_baseline(data, cfg, simulate)
    # the pretraining rows' objects are the training objects: shared, not one copy per pair
    data.pre = read_rows(store, lambda c, k: c == -1, objects=(data.object_table, names))
    return data


def simulate_baselines(data: RunData, cfg: Config, simulate: Simulate) -> None:
    """Imprint and flat-pad pairs on the held-out objects, simulated once into the store."""
    if "heldout-baselines" in data.store.done_keys():
        return
    objs, lefts, rights, kinds, names = [], [], [], [], []
    wl, wr = wsg50_fingers(cfg.geometry)
    for i in data.test_idx:
        il, ir = imprint_fingers(data.objects[i], cfg.geometry)
        for kind, (left, right) in zip(BASELINES, ((il, ir), (wl, wr))):
            objs.append(data.objects[i])
            lefts.append(left)
            rights.append(right)
            kinds.append(kind)
            names.append(data.names[i])
    out = simulate(np.stack(objs), np.stack(lefts), np.stack(rights), "held-out baselines")
    data.store.append(np.stack(objs), np.stack(lefts), np.stack(rights), out, kind=kinds,
                      names=names, keys=["heldout-baselines"], cycle=-2)


def simulate_fmf_baseline(data: RunData, cfg: Config, simulate: Simulate) -> None:
    """The WSG-FMF fingers on the held-out objects, simulated once into the store (its own chunk:
    runs made before it, or without the pybullet extra, gain it when resumed with it)."""
    if f"heldout-{FMF_KIND}" in data.store.done_keys():
        return
    try:
        left, right = wsg_fmf_fingers(cfg.geometry)
    except ImportError as exc:  # MissingExtraError
        log.info("no %s baseline: %s", FMF_KIND, exc)
        return
    objs = np.stack([data.objects[i] for i in data.test_idx])
    lefts, rights = np.repeat(left[None], len(objs), 0), np.repeat(right[None], len(objs), 0)
    out = simulate(objs, lefts, rights, "held-out WSG-FMF baseline")
    data.store.append(objs, lefts, rights, out, kind=FMF_KIND,
                      names=[data.names[i] for i in data.test_idx],
                      keys=[f"heldout-{FMF_KIND}"], cycle=-2)
