"""Object hulls: coacd once per object, cached on disk.

Objects are fixed for a run, so they get a careful decomposition once (``object_hulls``):
coacd on the marching-cubes mesh (or the mesh's hull when it is convex), merged down to K
pieces, free slots spent on cutting the pieces that V vertices fit worst, cached on disk by a
hash of the volume and the settings.

The pieces of the builtin objects that runs, benchmarks and tests start from ship with the
package (``builtin_pieces.npz``, rebuilt by ``python -m f2f_jax.cli.bundle_pieces``): objects 0-639
of seed 0 as an object set stores them (float16; 64-299 are the teacher config's extra objects,
64-639 those of a 627-object teacher set), and 0-63 also as ``mesh_to_tsdf`` makes them (the
tests' and benchmarks' form).  A fresh machine reads them under the same keys instead of spending
8-10 minutes of coacd on each 64 of them.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.config import GeometryConfig, geometry_config
from f2f_jax.errors import DecompositionError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry.hulls import Hulls, clip_halfspace, convex_vertices, pad_hulls, reduce_with_error
from f2f_jax.geometry.tsdf import check_tsdf, tsdf_to_mesh

log = logging.getLogger(__name__)

# Bump when anything that changes cached object hulls changes (algorithm, file layout).
_CACHE_VERSION = 1
_CACHE_ENV = "F2F_CACHE_DIR"
# An object whose hull reaches at most this far into its empty space is one convex piece.
_CONVEX_TOLERANCE_VOXELS = 1.0
_CONVEX_TEST_VERTICES = 64  # its hull is judged by a 64-vertex inner approximation
# Free object slots go to pieces whose V-vertex reduction misses more than this.
_REFINE_TOLERANCE_VOXELS = 0.5
_MAX_COACD_FACES = 80_000
# Pieces of the builtin objects, shipped: {cache key: hulls} (module docstring)
BUNDLE_PATH = Path(__file__).with_name("builtin_pieces.npz")

@dataclass(frozen=True)
class CoacdSettings:
    """Settings of coacd.run_coacd (see its documentation) plus our mesh preparation.

    coacd's quality defaults (concavity threshold 0.05, 20 MCTS nodes, depth 3) with fewer MCTS
    iterations and concavity samples (100 / 1000 instead of 150 / 2000), and its manifold
    pre-processing off: marching-cubes meshes are closed and manifold already.  On primitive
    objects that took 60-75% of the quality defaults' time (3.6-22 s against 5-30 s on one
    core) for the same fit once the pieces are merged down to 8.
    """

    threshold: float = 0.05  # concavity allowed per piece (coacd's normalised units)
    preprocess_mode: str = "off"
    preprocess_resolution: int = 50
    resolution: int = 1000  # surface samples for the concavity metric
    mcts_nodes: int = 20
    mcts_iterations: int = 100
    mcts_max_depth: int = 3
    merge: bool = True  # coacd's own merging of pieces that stay under the threshold together
    seed: int = 0
    smooth_iterations: int = 0  # Taubin passes on the mesh before coacd (staircase removal)


def decompose_mesh(mesh: trimesh.Trimesh, settings: CoacdSettings | None = None, *,
                   name: str = "mesh") -> list[np.ndarray]:
    """Approximate convex decomposition of a closed mesh by coacd.

    Returns a list of [n_k, 3] float64 vertex arrays (mesh units), one per convex piece, as many
    as coacd makes.  If coacd fails or returns nothing, warns and returns the mesh's convex hull
    as the single piece; raises DecompositionError if even that fails.
    """
    import coacd

    settings = settings or CoacdSettings()
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int32)
    if len(verts) < 4 or len(faces) == 0 or not np.all(np.isfinite(verts)):
        raise DecompositionError(f"{name}: cannot decompose a mesh with {len(verts)} vertices and "
                                 f"{len(faces)} faces (or NaN vertices)")
    if len(faces) > _MAX_COACD_FACES:
        # marching-cubes meshes of real objects have 10-25k faces; a noise-like volume gives
        # 200k+, on which coacd runs for many minutes
        warnings.warn(f"{name}: {len(faces)} faces is more than coacd gets here "
                      f"({_MAX_COACD_FACES}); using one convex hull of the whole mesh",
                      RuntimeWarning, stacklevel=2)
        return [convex_vertices(verts)]
    if settings.smooth_iterations > 0:
        smooth = trimesh.Trimesh(verts.copy(), faces.copy(), process=False)
        trimesh.smoothing.filter_taubin(smooth, iterations=settings.smooth_iterations)
        verts = np.asarray(smooth.vertices, dtype=np.float64)
    params = dataclasses.asdict(settings)
    params.pop("smooth_iterations")
    pieces: list[np.ndarray] = []
    try:
        coacd.set_log_level("error")  # coacd logs every step at "info" by default
        parts = coacd.run_coacd(coacd.Mesh(verts, faces), **params)
        pieces = [np.asarray(v, dtype=np.float64) for v, _ in parts if len(v) >= 4]
    except Exception as exc:  # the C++ library fails in many ways; any failure -> fallback
        warnings.warn(f"{name}: coacd failed ({type(exc).__name__}: {exc}); using one convex "
                      "hull of the whole mesh", RuntimeWarning, stacklevel=2)
    else:
        if not pieces:
            warnings.warn(f"{name}: coacd returned no pieces; using one convex hull of the whole "
                          "mesh", RuntimeWarning, stacklevel=2)
    if not pieces:
        pieces = [convex_vertices(verts)]
    return pieces


def _hull_volume(pts: np.ndarray) -> float:
    try:
        return float(ConvexHull(pts).volume)
    except (QhullError, ValueError):
        return 0.0


def reduce_pieces(pieces: list[np.ndarray], max_pieces: int) -> tuple[list[np.ndarray], dict]:
    """Bring a piece list down to at most ``max_pieces`` convex pieces.

    Repeatedly takes the cheaper of: merging the two pieces whose joint hull adds the least
    volume, or dropping the smallest piece (cost: its volume).  Returns (pieces as hull-vertex
    arrays, report dict(pieces_in, merged, dropped, added_volume, dropped_volume) in the units
    of the input cubed).
    """
    hulls = [convex_vertices(np.asarray(p, dtype=np.float64)) for p in pieces]
    vols = [_hull_volume(p) for p in hulls]
    report = dict(pieces_in=len(hulls), merged=0, dropped=0, added_volume=0.0, dropped_volume=0.0)
    if len(hulls) <= max_pieces:
        return hulls, report
    merge_cost: dict[tuple[int, int], float] = {}
    alive = list(range(len(hulls)))

    def pair_cost(i, j):
        key = (min(i, j), max(i, j))
        if key not in merge_cost:
            merge_cost[key] = _hull_volume(np.concatenate([hulls[i], hulls[j]])) - vols[i] - vols[j]
        return merge_cost[key]

    while len(alive) > max_pieces:
        pairs = [(pair_cost(i, j), i, j) for n, i in enumerate(alive) for j in alive[n + 1:]]
        cost, i, j = min(pairs)
        small = min(alive, key=lambda k: vols[k])
        if vols[small] <= cost:
            alive.remove(small)
            report["dropped"] += 1
            report["dropped_volume"] += vols[small]
            continue
        hulls.append(convex_vertices(np.concatenate([hulls[i], hulls[j]])))
        vols.append(_hull_volume(hulls[-1]))
        alive = [k for k in alive if k not in (i, j)] + [len(hulls) - 1]
        report["merged"] += 1
        report["added_volume"] += max(cost, 0.0)
    return [hulls[k] for k in alive], report


def refine_pieces(pieces: list[np.ndarray], max_pieces: int, max_vertices: int, *,
                  tolerance: float) -> list[np.ndarray]:
    """Spend free slots on detail: while there are fewer than max_pieces pieces, cut the piece
    that its max_vertices reduction fits worst (furthest dropped vertex, if beyond tolerance, m)
    in two by the plane through its centre across its longest principal axis.

    The union of the pieces does not change; a round piece gets twice the vertices per cut.
    pieces: list of [n_k, 3].  Returns the new list (hull vertices)."""
    pieces = [convex_vertices(np.asarray(p, dtype=np.float64)) for p in pieces]
    misfit = [reduce_with_error(p, max_vertices)[1] for p in pieces]
    while len(pieces) < max_pieces and misfit and max(misfit) > tolerance:
        worst = int(np.argmax(misfit))
        piece = pieces[worst]
        centre = piece.mean(axis=0)
        axis = np.linalg.eigh(np.cov((piece - centre).T))[1][:, -1]
        hull = ConvexHull(piece)
        try:
            halves = [convex_vertices(clip_halfspace(piece, hull, s * axis, s * centre @ axis))
                      for s in (1.0, -1.0)]
        except DecompositionError:  # a sliver that cannot be cut: leave it
            misfit[worst] = 0.0
            continue
        pieces[worst:worst + 1] = halves
        misfit[worst:worst + 1] = [reduce_with_error(h, max_vertices)[1] for h in halves]
    return pieces


def pieces_to_hulls(pieces: list[np.ndarray], k: int, v: int, g: GeometryConfig, name: str) -> Hulls:
    """Pieces in any number -> exactly the fixed layout: reduce, refine, pad."""
    pieces, report = reduce_pieces(pieces, k)
    if report["merged"] or report["dropped"]:
        log.info("%s: %d pieces -> %d (merged %d, dropped %d, dropped volume %.3g m^3)", name,
                 report["pieces_in"], len(pieces), report["merged"], report["dropped"],
                 report["dropped_volume"])
    pieces = refine_pieces(pieces, k, v, tolerance=_REFINE_TOLERANCE_VOXELS * g.voxel_size)
    return pad_hulls(pieces, k, v)


def mesh_hulls(mesh: trimesh.Trimesh, cfg=None, *, max_pieces: int | None = None,
               max_vertices: int | None = None, settings: CoacdSettings | None = None,
               name: str = "mesh") -> Hulls:
    """coacd pieces of a mesh in the fixed layout (no cache).

    mesh: closed triangle mesh (metres, any frame: vertices are kept as they are).  Pieces beyond
    max_pieces (cfg.object_hulls) are merged or dropped (``reduce_pieces``, logged), free slots
    are spent on cutting the pieces that fit worst in max_vertices (``refine_pieces``), and each
    piece is reduced to max_vertices (cfg.hull_vertices) by ``reduce_vertices``.
    """
    g = geometry_config(cfg)
    k = max_pieces or g.object_hulls
    v = max_vertices or g.hull_vertices
    return pieces_to_hulls(decompose_mesh(mesh, settings, name=name), k, v, g, name)


def _hull_excess(arr: np.ndarray, pts: np.ndarray, g: GeometryConfig) -> float:
    """How far (m) the hull of pts reaches into the volume's empty space, read from the TSDF at
    the voxel centres inside the hull (an empty voxel's value times the truncation is its
    distance to the surface, up to the truncation)."""
    verts, _ = reduce_with_error(pts, _CONVEX_TEST_VERTICES)
    eq = ConvexHull(verts).equations
    empty = np.argwhere(arr > 0)
    centres = (empty + 0.5) * g.voxel_size - np.array([g.cube_size / 2, g.cube_size / 2, 0.0])
    inside = np.all(centres @ eq[:, :3].T + eq[:, 3] <= 0, axis=1)
    if not inside.any():
        return 0.0
    return float(arr[tuple(empty[inside].T)].max() * g.truncation)


def default_cache_dir() -> Path:
    """Where object hulls are cached: $F2F_CACHE_DIR/hulls, else ~/.cache/f2f_jax/hulls."""
    root = os.environ.get(_CACHE_ENV)
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "f2f_jax"
    return base / "hulls"


def cache_key(arr: np.ndarray, g: GeometryConfig, k: int, v: int,
               settings: CoacdSettings) -> str:
    meta = json.dumps(dict(version=_CACHE_VERSION, max_pieces=k, max_vertices=v,
                           resolution=g.resolution, cube_size=g.cube_size,
                           convex_tolerance=_CONVEX_TOLERANCE_VOXELS,
                           refine_tolerance=_REFINE_TOLERANCE_VOXELS,
                           settings=dataclasses.asdict(settings)), sort_keys=True)
    digest = hashlib.sha1(np.ascontiguousarray(arr, dtype=np.float32).tobytes())
    digest.update(meta.encode())
    return digest.hexdigest()


def load_cached(path: Path, k: int, v: int) -> Hulls | None:
    """The cached hulls, or None when the file is missing, unreadable or of another layout."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            hulls = Hulls(np.array(data["vertices"], dtype=np.float32),
                          np.array(data["counts"], dtype=np.int32))
        if hulls.vertices.shape != (k, v, 3) or not np.all(np.isfinite(hulls.vertices)):
            raise ValueError(f"layout {hulls.vertices.shape}, expected {(k, v, 3)}")
        return hulls
    except Exception as exc:  # truncated zip, wrong keys, bad shapes: all mean "recompute"
        warnings.warn(f"hull cache file {path} is unusable ({type(exc).__name__}: {exc}); "
                      "recomputing it", RuntimeWarning, stacklevel=3)
        return None


@functools.lru_cache(maxsize=1)
def _bundle() -> tuple[dict[str, int], np.ndarray, np.ndarray]:
    """The shipped pieces: ({cache key: row}, vertices [N, K, V, 3], counts [N, K]); empty when
    the file is missing (a checkout before it was built) or unreadable."""
    try:
        with np.load(BUNDLE_PATH, allow_pickle=False) as data:
            keys = [str(k) for k in data["keys"]]
            return {k: i for i, k in enumerate(keys)}, data["vertices"], data["counts"]
    except Exception as exc:  # a broken bundle only costs time: coacd makes the pieces
        if not isinstance(exc, FileNotFoundError):
            warnings.warn(f"shipped object pieces {BUNDLE_PATH} are unusable ({type(exc).__name__}: "
                          f"{exc}); computing them", RuntimeWarning, stacklevel=2)
        return {}, np.zeros((0, 0, 0, 3), np.float32), np.zeros((0, 0), np.int32)


def bundled_hulls(key: str, k: int, v: int) -> Hulls | None:
    """The shipped pieces under a cache key (``cache_key``), or None."""
    rows, vertices, counts = _bundle()
    i = rows.get(key)
    if i is None or vertices.shape[1:] != (k, v, 3):
        return None
    return Hulls(np.array(vertices[i], np.float32), np.array(counts[i], np.int32))


def stored_hulls(path: Path, k: int, v: int) -> Hulls | None:
    """The hulls cached at ``path`` (``cache_path``), else the shipped ones of its key, else None."""
    cached = load_cached(path, k, v)
    return cached if cached is not None else bundled_hulls(path.stem, k, v)


def _save_atomic(path: Path, hulls: Hulls) -> None:
    """Write the npz next to its destination, then rename: readers never see half a file."""
    with atomic_path(path) as tmp:
        np.savez(tmp, vertices=hulls.vertices, counts=hulls.counts)


def cache_path(arr: np.ndarray, g: GeometryConfig, k: int, v: int, settings: CoacdSettings,
                cache_dir) -> Path:
    directory = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    return directory / f"{cache_key(arr, g, k, v, settings)}.npz"


def cached_object_hulls(obj_tsdf, cfg=None, *, cache_dir=None) -> Hulls | None:
    """The cached ``object_hulls`` of a volume (default layout and settings), or None when
    they were never made here.  Raises VolumeError for an invalid volume."""
    g = geometry_config(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k, v = g.object_hulls, g.hull_vertices
    return stored_hulls(cache_path(arr, g, k, v, CoacdSettings(), cache_dir), k, v)


def store_object_hulls(obj_tsdf, hulls: Hulls, cfg=None, *, cache_dir=None) -> None:
    """Cache hulls that ``object_hulls(obj_tsdf, cfg, cache_dir=None)`` made elsewhere (another
    process or machine, e.g. a Ray worker), as ``object_hulls`` would have; atomic."""
    g = geometry_config(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k, v = g.object_hulls, g.hull_vertices
    if hulls.vertices.shape != (k, v, 3):
        raise ValueError(f"hulls of layout {hulls.vertices.shape}, expected {(k, v, 3)}")
    _save_atomic(cache_path(arr, g, k, v, CoacdSettings(), cache_dir), hulls)


def object_hulls(obj_tsdf, cfg=None, *, cache_dir: str | os.PathLike | None | bool = None,
                 max_pieces: int | None = None, max_vertices: int | None = None,
                 settings: CoacdSettings | None = None) -> Hulls:
    """Convex pieces of an object volume, computed once and cached on disk.

    obj_tsdf: [R, R, R] object volume, negative inside.  The marching-cubes surface
    (``tsdf_to_mesh``, metres, the object's local frame) is decomposed by coacd (``mesh_hulls``)
    unless its convex hull reaches at most a voxel into the empty space: then the hull is the
    one piece (coacd would cut a convex shape along the voxel staircase, slowly).
    The result is cached as ``<sha1>.npz`` in cache_dir (default ``default_cache_dir()``; False:
    no cache, neither read nor written, nor the shipped pieces used), keyed by the float32 volume
    bytes, the layout and the settings; writes are atomic and an unreadable file is recomputed.
    A key missing from the cache is looked up in the shipped pieces of the builtin objects.
    Returns Hulls [max_pieces (cfg.object_hulls), max_vertices, 3].
    Raises VolumeError for an invalid or empty volume, DecompositionError if no piece can be made.
    """
    g = geometry_config(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k = max_pieces or g.object_hulls
    v = max_vertices or g.hull_vertices
    settings = settings or CoacdSettings()
    use_cache = cache_dir is not False
    path = cache_path(arr, g, k, v, settings, cache_dir if use_cache else None)
    if use_cache:
        cached = stored_hulls(path, k, v)
        if cached is not None:
            return cached
    start = time.perf_counter()
    name = f"object {path.stem[:10]}"
    mesh = tsdf_to_mesh(arr, g, name="object")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    if _hull_excess(arr, verts, g) <= _CONVEX_TOLERANCE_VOXELS * g.voxel_size:
        # convex up to the voxels' staircase: coacd would only cut it along the stairs
        pieces = [convex_vertices(verts)]
    else:
        pieces = decompose_mesh(mesh, settings, name=name)
    hulls = pieces_to_hulls(pieces, k, v, g, name)
    log.info("object hulls %s: %d pieces in %.1f s", path.stem[:10], hulls.n_pieces,
             time.perf_counter() - start)
    if use_cache:
        _save_atomic(path, hulls)
    return hulls
