"""``object_hulls`` of many objects in worker processes, with a progress bar.

coacd holds the GIL and a core for seconds per object, so threads would not run it side by side;
the workers are plain ``python -m f2f_jax.geometry.hull_pool`` subprocesses (not multiprocessing),
which needs no ``__main__`` guard in the caller's script and never forks a process that runs JAX
threads.  Each worker writes into the disk cache of ``object_hulls``; the caller reads it back.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from f2f_jax.config import GeometryConfig, geometry_config
from f2f_jax.errors import F2FError
from f2f_jax.geometry.coacd_pieces import (
    CoacdSettings,
    cache_path,
    default_cache_dir,
    object_hulls,
    stored_hulls,
)
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.geometry.tsdf import check_tsdf

log = logging.getLogger(__name__)


def _object_hulls_or_error(obj, cfg, cache_dir, settings=None) -> Hulls | str:
    try:
        return object_hulls(obj, cfg, cache_dir=cache_dir, settings=settings)
    except (F2FError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"


def _worker_main(argv: list[str]) -> int:
    """``python -m f2f_jax.geometry.hull_pool VOLUMES.npy INDICES CACHE_DIR GEOMETRY_JSON SETTINGS_JSON
    ERR_DIR``: decompose the listed volumes into the cache; failures go to ERR_DIR/<index>.txt."""
    volumes_path, indices, cache_dir, geometry, settings, err_dir = argv
    volumes = np.load(volumes_path, mmap_mode="r")
    g = GeometryConfig(**json.loads(geometry))
    coacd_settings = CoacdSettings(**json.loads(settings))
    for i in json.loads(indices):
        res = _object_hulls_or_error(np.array(volumes[i]), g, cache_dir, coacd_settings)
        if isinstance(res, str):
            Path(err_dir, f"{i}.txt").write_text(res)
    return 0


def object_hulls_many(objects, cfg=None, *, cache_dir=None, workers: int | None = None,
                      progress: bool | None = None,
                      settings: CoacdSettings | None = None) -> list[Hulls | str]:
    """``object_hulls`` of many object volumes: cached ones read here, the rest decomposed by
    coacd in ``workers`` worker processes (default: one per CPU).  coacd holds the GIL and a core
    for seconds per object, so threads would not run it side by side; the workers are plain
    ``python -m`` subprocesses (not multiprocessing), which needs no ``__main__`` guard in the
    caller's script and never forks a process that runs JAX threads.

    objects: sequence of [R, R, R] volumes (duplicates are decomposed once).  settings: coacd's
    (default ``CoacdSettings()``), e.g. another seed for a decomposition retest
    (``research/sim_retest.py --perturb pieces``); they are part of the cache key.
    Returns one entry per object: its Hulls, or the error message of a volume that could not be
    decomposed (so one bad object does not stop a batch).
    """
    g = geometry_config(cfg)
    settings = settings or CoacdSettings()
    objs = [np.asarray(o, np.float32) for o in objects]
    keys = [hashlib.sha1(np.ascontiguousarray(o).tobytes()).hexdigest() for o in objs]
    first: dict[str, int] = {}
    for i, key in enumerate(keys):
        first.setdefault(key, i)
    directory = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    made: dict[str, Hulls | str] = {}
    todo: list[tuple[str, Path]] = []
    for key, i in first.items():
        try:
            arr = check_tsdf(objs[i], "object", g)
        except (F2FError, ValueError) as exc:
            made[key] = f"{type(exc).__name__}: {exc}"
            continue
        path = cache_path(arr, g, g.object_hulls, g.hull_vertices, settings, cache_dir)
        cached = stored_hulls(path, g.object_hulls, g.hull_vertices)
        if cached is not None:
            made[key] = cached
        else:
            todo.append((key, path))
    workers = max(1, min(int(workers or os.cpu_count() or 1), len(todo)))
    show = progress if progress is not None else len(todo) > 1
    bar = tqdm(total=len(todo), desc="object hulls (coacd)", unit="obj", disable=not show)
    if len(todo) > 1 and workers > 1:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="f2f-hulls-") as tmp:
            np.save(Path(tmp) / "volumes.npy", np.stack([objs[first[k]] for k, _ in todo]))
            env = dict(os.environ)
            root = str(Path(__file__).resolve().parents[2])  # this checkout, installed or not
            env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
            geometry = json.dumps(dataclasses.asdict(g))
            procs = [subprocess.Popen(
                [sys.executable, "-m", "f2f_jax.geometry.hull_pool", str(Path(tmp) / "volumes.npy"),
                 json.dumps(list(range(w, len(todo), workers))), str(directory), geometry,
                 json.dumps(dataclasses.asdict(settings)), tmp],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for w in range(workers)]
            while any(p.poll() is None for p in procs):
                time.sleep(0.5)
                bar.n = sum(p.exists() for _, p in todo) + len(list(Path(tmp).glob("*.txt")))
                bar.refresh()
            for p in procs:
                err = p.stderr.read().decode(errors="replace")
                p.stderr.close()
                if p.returncode:
                    log.warning("hull worker exited with %s: %s", p.returncode, err[-500:])
            for j, (key, path) in enumerate(todo):
                err_file = Path(tmp) / f"{j}.txt"
                if err_file.exists():
                    made[key] = err_file.read_text()
                else:  # a cache hit, or (worker died) computed here
                    made[key] = _object_hulls_or_error(objs[first[key]], g, cache_dir, settings)
        bar.n = len(todo)
    else:
        for key, _ in todo:
            made[key] = _object_hulls_or_error(objs[first[key]], g, cache_dir, settings)
            bar.update(1)
    bar.close()
    return [made[k] for k in keys]


if __name__ == "__main__":
    sys.exit(_worker_main(sys.argv[1:]))

