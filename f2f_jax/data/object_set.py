"""An object set on disk: meshes turned into TSDF volumes once, with a fixed split."""

from __future__ import annotations

import json
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from f2f_jax.config import GeometryConfig
from f2f_jax.data.objects import builtin_object
from f2f_jax.data.sources import object_source
from f2f_jax.data.splits import load_split, make_split, save_split
from f2f_jax.errors import MeshError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import mesh_to_tsdf

log = logging.getLogger(__name__)


def load_or_make_objects(source: str, n: int | None, seed: int, directory, cfg: GeometryConfig | None = None,
                         *, progress: bool = True, test_fraction: float = 0.2,
                         ) -> tuple[np.ndarray, list[str]]:
    """TSDFs [N, R, R, R] float32 and names of an object set, made once and kept in ``directory``
    (``objects.npz``, ``split.json``, ``source.json``).  Meshes that cannot become a volume are
    skipped and logged.  A directory made from another source, n or seed is refused rather than
    silently reused.  test_fraction: the held-out share of the split (``TrainConfig.test_fraction``);
    sets recorded before it was kept were made with 0.2."""
    cfg = cfg or GeometryConfig()
    directory = Path(directory)
    meta = {"source": str(source), "n": n, "seed": seed, "resolution": cfg.resolution,
            "test_fraction": float(test_fraction)}
    npz, meta_path = directory / "objects.npz", directory / "source.json"
    if npz.exists() and meta_path.exists():
        old = {"test_fraction": 0.2, **json.loads(meta_path.read_text())}
        if old != meta:
            raise ValueError(f"{directory} holds objects made from {old}, not {meta}; "
                             "choose another directory")
        data = np.load(npz)
        return data["tsdf"].astype(np.float32), [str(x) for x in data["names"]]
    meshes = object_source(source, n, seed)
    tsdfs, names = [], []
    for mesh in tqdm(meshes, desc="objects -> TSDF", unit="obj", disable=not progress):
        name = mesh.metadata.get("name", f"object{len(names)}")
        try:
            tsdfs.append(mesh_to_tsdf(mesh, cfg, name=name))
            names.append(name)
        except MeshError as exc:
            log.warning("skipped: %s", exc)
    if not tsdfs:
        raise MeshError(f"no usable object in {source!r}")
    with atomic_path(npz) as tmp:
        np.savez_compressed(tmp, tsdf=np.stack(tsdfs).astype(np.float16), names=np.array(names))
    save_split(directory / "split.json", make_split(names, test_fraction=test_fraction, seed=seed))
    with atomic_path(meta_path) as tmp:  # written last: it marks the set complete
        tmp.write_text(json.dumps(meta))
    return np.stack(tsdfs).astype(np.float16).astype(np.float32), names


def load_or_make_builtin_range(directory, start: int, n: int, seed: int, cfg: GeometryConfig | None = None,
                               *, progress: bool = True, chunk: int = 64, threads: int | None = None,
                               ) -> tuple[np.ndarray, list[str]]:
    """TSDFs [M, R, R, R] float32 and names of the built-in objects ``start .. start + n - 1`` of
    ``seed``'s stream (``builtin_object``; M <= n: meshes that cannot become a volume are skipped
    and logged), made on ``threads`` threads (default: every core) in chunks of ``chunk`` objects,
    each kept in ``directory`` as it is done (``part-SSSSSS.npz``): a killed call loses at most one
    chunk.  A directory made for another range, seed or resolution is refused."""
    if start < 0 or n < 0 or chunk < 1:
        raise ValueError(f"need start >= 0, n >= 0 and chunk >= 1, got {start}, {n}, {chunk}")
    cfg = cfg or GeometryConfig()
    directory = Path(directory)
    meta = {"source": "builtin", "start": start, "n": n, "seed": seed, "resolution": cfg.resolution,
            "chunk": chunk}
    meta_path = directory / "source.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if old != meta:
            raise ValueError(f"{directory} holds built-in objects made as {old}, not {meta}; "
                             "choose another directory")
    else:
        with atomic_path(meta_path) as tmp:
            tmp.write_text(json.dumps(meta))

    def make(index: int) -> tuple[np.ndarray | None, str]:
        mesh = builtin_object(index, seed)
        name = mesh.metadata["name"]
        try:
            return mesh_to_tsdf(mesh, cfg, name=name).astype(np.float16), name
        except MeshError as exc:
            log.warning("skipped: %s", exc)
            return None, name

    tsdfs, names = [], []
    bar = tqdm(total=n, desc="built-in objects -> TSDF", unit="obj", disable=not progress)
    with ThreadPoolExecutor(threads or os.cpu_count() or 1) as pool:  # the TSDF's numpy releases the GIL
        for first in range(start, start + n, chunk):
            path = directory / f"part-{first:06d}.npz"
            if not path.exists():
                indices = range(first, min(first + chunk, start + n))
                made = [m for m in pool.map(make, indices) if m[0] is not None]
                with atomic_path(path) as tmp:
                    np.savez_compressed(tmp, tsdf=np.stack([t for t, _ in made]) if made else
                                        np.zeros((0,) + (cfg.resolution,) * 3, np.float16),
                                        names=np.array([name for _, name in made], dtype=str))
            part = np.load(path)
            tsdfs.append(part["tsdf"])
            names += [str(x) for x in part["names"]]
            bar.update(min(chunk, start + n - first))
    bar.close()
    if not tsdfs:
        return np.zeros((0,) + (cfg.resolution,) * 3, np.float32), []
    return np.concatenate(tsdfs).astype(np.float32), names


def object_split(directory) -> dict[str, list[str]]:
    return load_split(Path(directory) / "split.json")


def run_objects(run_dir, cfg: GeometryConfig | None = None) -> tuple[np.ndarray, list[str]]:
    """A co-training run's whole object set, volumes [N, R, R, R] and names in the set's order
    (``run_dir/objects``, remade from its record if its volumes are missing); ``object_split(
    run_dir / "objects")`` says which are held out."""
    directory = Path(run_dir) / "objects"
    meta_path = directory / "source.json"
    if not meta_path.exists():
        raise FileNotFoundError(f"{directory} holds no object set (no source.json): is {run_dir} a "
                                "co-training run directory?")
    meta = json.loads(meta_path.read_text())
    return load_or_make_objects(meta["source"], meta["n"], meta["seed"], directory, cfg,
                                progress=False, test_fraction=meta.get("test_fraction", 0.2))


def held_out_objects(run_dir, cfg: GeometryConfig | None = None) -> tuple[np.ndarray, list[str]]:
    """A co-training run's held-out object volumes [N, R, R, R] and names, in the order of its
    split (``run_objects``' set)."""
    tsdfs, names = run_objects(run_dir, cfg)
    index = {name: i for i, name in enumerate(names)}
    test = [index[n] for n in object_split(Path(run_dir) / "objects")["test"] if n in index]
    return tsdfs[np.array(test, int)], [names[i] for i in test]
