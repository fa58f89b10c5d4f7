"""Which convex pieces an object enters the simulator as, by ``GeometryConfig.object_method``
(the geometry of a simulation preset, ``config.SIM_PRESETS``):

* "coacd" (``coacd_pieces.object_hulls``, both presets): coacd's decomposition of the marching-cubes
  surface, 13-30 s per non-convex object, cached on disk;
* "tiles" (``object_tiles.tile_object_hulls``): hulls over tiles of the object's depth map along
  the closing axis, ~0.15 s from the volume, no cache.  94-95% of trials agree with coacd's
  (benchmarks/RESULTS.md): for new objects when coacd's time matters more than that.

Both return the same ``Hulls`` layout, so every backend and renderer takes either.  Fingers are
always ``finger_tiling.finger_hulls`` (height-map hulls, milliseconds).
"""

from __future__ import annotations

import hashlib

import numpy as np
from tqdm.auto import tqdm

from f2f_jax.config import Config, GeometryConfig
from f2f_jax.errors import F2FError
from f2f_jax.geometry.coacd_pieces import cached_object_hulls, object_hulls, store_object_hulls
from f2f_jax.geometry.hull_pool import object_hulls_many
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.geometry.object_tiles import tile_object_hulls

OBJECT_METHODS = ("tiles", "coacd")


def _geometry(cfg) -> GeometryConfig:
    g = cfg.geometry if isinstance(cfg, Config) else (cfg or GeometryConfig())
    if g.object_method not in OBJECT_METHODS:
        raise ValueError(f"unknown object_method {g.object_method!r}; choose one of {OBJECT_METHODS}")
    return g


def object_pieces(obj_tsdf, cfg=None, *, cache_dir=None) -> Hulls:
    """An object volume's collision pieces by ``cfg.object_method``; cache_dir (coacd): where
    they are cached (default ``hulls.default_cache_dir()``), False for no cache.

    obj_tsdf: [R, R, R], negative inside.  Returns Hulls [cfg.object_hulls, cfg.hull_vertices,
    3] in the object's frame.  Raises VolumeError for an invalid or empty volume,
    DecompositionError when no piece can be made.
    """
    g = _geometry(cfg)
    if g.object_method == "tiles":
        return tile_object_hulls(obj_tsdf, g)
    return object_hulls(obj_tsdf, g, cache_dir=cache_dir)


def cached_pieces(obj_tsdf, cfg=None, *, cache_dir=None) -> Hulls | None:
    """The pieces ``object_pieces`` would read from its cache without computing, or None (tiles
    are never cached: they cost less than reading a file).  Raises VolumeError for an invalid
    volume."""
    g = _geometry(cfg)
    if g.object_method == "tiles":
        return None
    return cached_object_hulls(obj_tsdf, g, cache_dir=cache_dir)


def keep_pieces(obj_tsdf, hulls: Hulls, cfg=None, *, cache_dir=None) -> None:
    """Cache pieces that ``object_pieces(obj_tsdf, cfg, cache_dir=False)`` made in another process
    (a Ray worker), where ``object_pieces`` would have cached them; nothing for tiles."""
    g = _geometry(cfg)
    if g.object_method == "coacd":
        store_object_hulls(obj_tsdf, hulls, g, cache_dir=cache_dir)


def object_pieces_many(objects, cfg=None, *, cache_dir=None, workers: int | None = None,
                       progress: bool | None = None) -> list[Hulls | str]:
    """``object_pieces`` of many volumes, each distinct one once.  Tiles are made here; coacd
    pieces go through ``hull_pool.object_hulls_many`` (disk cache, worker processes).  Returns per
    object its Hulls or the error message of a volume that failed (one bad object does not
    stop a batch)."""
    g = _geometry(cfg)
    if g.object_method == "coacd":
        return object_hulls_many(objects, g, cache_dir=cache_dir, workers=workers,
                                 progress=progress)
    made: dict[str, Hulls | str] = {}
    out = []
    show = progress if progress is not None else len(objects) > 1000
    for obj in tqdm(objects, desc="object pieces (tiles)", unit="obj", disable=not show):
        arr = np.ascontiguousarray(obj, np.float32)
        key = hashlib.sha1(arr.tobytes()).hexdigest()
        if key not in made:
            try:
                made[key] = tile_object_hulls(arr, g)
            except (F2FError, ValueError) as exc:
                made[key] = f"{type(exc).__name__}: {exc}"
        out.append(made[key])
    return out
