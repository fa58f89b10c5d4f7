"""Shape volumes -> at most K convex pieces of at most V vertices: the collision geometry.

Every shape enters the simulator as a :class:`Hulls`: ``[K, V, 3]`` vertices (metres, the volume's
local frame, config.py) and ``[K]`` vertex counts.  K and V are fixed per layout, so many shapes
stack into one array that a batched simulator maps over (``stack_hulls``).

Two ways in, because fingers and objects differ in how often they are made:

* **Fingers** are new every training cycle (thousands), so they get a method that costs tens of
  milliseconds (``finger_hulls``).  A finger is mounted on the plane ``w = 0`` and the object
  meets it from ``+w``, so the surface that matters is the height map ``h(u, v)``: how far the
  solid reaches from the mount in each column.  The columns are split by straight cuts into
  tiles, each tile's piece is the convex hull of its columns from ``w = 0`` up to ``h``, cut by
  the tile's best-fit plane.  A hull over-covers where the map is concave inside its tile (a
  bowl's hull fills the bowl); the plane trades that intrusion for a smaller shortfall, and tiles
  are split where the worse of the two is largest.  Simplification: solid hanging over a hollow
  that faces the mount (an undercut) is filled down to the mount; imprint fingers have none.
* **Objects** are fixed for a run, so they get a careful decomposition once (``object_hulls``):
  coacd on the marching-cubes mesh (or the mesh's hull when it is convex), merged down to K
  pieces, free slots spent on cutting the pieces that V vertices fit worst, cached on disk by a
  hash of the volume and the settings.

``hull_fit`` measures any shape's hulls against its volume: IoU, how far the hulls reach into the
shape's empty space (intrusion) and how deep solid is left outside them (shortfall).
"""

from __future__ import annotations

import dataclasses
import hashlib
import heapq
import json
import logging
import os
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.config import Config, GeometryConfig
from f2f_jax.errors import DecompositionError, F2FError
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
_POINT_CHUNK = 4_000_000  # point-facet pairs per block in points_in_hulls (32 MB of float64)


def _geom(cfg) -> GeometryConfig:
    if cfg is None:
        return GeometryConfig()
    return cfg.geometry if isinstance(cfg, Config) else cfg


# --------------------------------------------------------------------------------------------
# The fixed layout
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Hulls:
    """Convex pieces of one shape in a fixed ``[K, V]`` layout.

    vertices: [K, V, 3] float32, metres, the volume's local frame (config.py).  Rows past
        ``counts[k]`` repeat vertex 0 of that piece; unused slots are all zeros.
    counts: [K] int32, real vertices of piece k (>= 4 for a real piece, 0 for an unused slot).
    """

    vertices: np.ndarray
    counts: np.ndarray

    def __post_init__(self):
        v, c = np.asarray(self.vertices), np.asarray(self.counts)
        if v.ndim != 3 or v.shape[2] != 3 or c.shape != v.shape[:1]:
            raise ValueError(f"Hulls: expected vertices [K, V, 3] and counts [K], got {v.shape} "
                             f"and {c.shape}")
        if np.any((c != 0) & (c < 4)) or np.any(c > v.shape[1]):
            raise ValueError(f"Hulls: counts must be 0 or in [4, {v.shape[1]}], got {c.tolist()}")

    @property
    def valid(self) -> np.ndarray:
        """[K] bool, True for slots that hold a piece."""
        return self.counts > 0

    @property
    def n_pieces(self) -> int:
        return int(np.count_nonzero(self.counts))

    @property
    def max_pieces(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def max_vertices(self) -> int:
        return int(self.vertices.shape[1])

    def pieces(self) -> list[np.ndarray]:
        """The real pieces: list of [n_k, 3] float32 vertex arrays, in slot order."""
        return [self.vertices[k, :n] for k, n in enumerate(self.counts) if n > 0]


def reduce_vertices(points, max_vertices: int) -> np.ndarray:
    """Vertices of the convex hull of ``points``, at most ``max_vertices`` of them.

    points: [P, 3], P >= 4, not all in one plane.  Returns [n, 3] float64, 4 <= n <= max_vertices:
    the hull's vertices, or when there are more, a subset grown greedily from a spanning
    tetrahedron by adding the vertex furthest outside the current subset's hull (a greedy
    Hausdorff fit).  The result lies inside the full hull: reducing shrinks a piece, never grows
    it.  Raises DecompositionError when the points span no volume.
    """
    return _reduce(points, max_vertices)[0]


def _reduce(points, max_vertices: int) -> tuple[np.ndarray, float]:
    """reduce_vertices and how far (m) the dropped vertices lie outside the reduced hull."""
    if max_vertices < 4:
        raise ValueError(f"max_vertices must be >= 4 (a tetrahedron), got {max_vertices}")
    verts = _hull_vertices(np.asarray(points, dtype=np.float64))
    if len(verts) <= max_vertices:
        return verts, 0.0
    chosen = np.zeros(len(verts), bool)
    chosen[_spanning_tetrahedron(verts)] = True
    while True:
        eq = ConvexHull(verts[chosen]).equations
        dist = (verts[:, :1] * eq[:, 0] + verts[:, 1:2] * eq[:, 1] + verts[:, 2:] * eq[:, 2]
                + eq[:, 3])  # [P, F]: > 0 outside facet f
        worst = dist.max(axis=1)
        outside = max(float(worst.max()), 0.0)
        room = max_vertices - int(chosen.sum())
        if room == 0 or outside <= 1e-12:
            return verts[chosen], outside
        # Quickhull-like batches: the furthest point beyond each facet, furthest first
        facet = np.argmax(dist, axis=1)
        cand = np.flatnonzero(worst > 1e-12)
        order = cand[np.argsort(-worst[cand], kind="stable")]
        _, first = np.unique(facet[order], return_index=True)
        picks = order[np.sort(first)][:room]
        chosen[picks] = True


def _spanning_tetrahedron(pts: np.ndarray) -> list[int]:
    """Indices of 4 points spanning a large tetrahedron: extreme point, the point furthest from
    it, the one furthest from their line, the one furthest from their plane."""
    i0 = int(np.argmax(np.sum((pts - pts.mean(0)) ** 2, axis=1)))
    i1 = int(np.argmax(np.sum((pts - pts[i0]) ** 2, axis=1)))
    rel = pts - pts[i0]
    axis = rel[i1] / np.linalg.norm(rel[i1])
    i2 = int(np.argmax(np.sum((rel - np.outer(rel @ axis, axis)) ** 2, axis=1)))
    normal = np.cross(rel[i1], rel[i2])
    i3 = int(np.argmax(np.abs(rel @ normal)))
    return [i0, i1, i2, i3]


def _hull_vertices(pts: np.ndarray) -> np.ndarray:
    if len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise DecompositionError(f"a convex piece needs >= 4 finite points, got {len(pts)}")
    try:
        hull = ConvexHull(pts)
    except QhullError as exc:  # flat or degenerate point sets
        raise DecompositionError(f"convex hull of {len(pts)} points failed (flat piece?): "
                                 f"{str(exc).strip().splitlines()[0]}") from None
    return pts[hull.vertices]


def pad_hulls(pieces: list[np.ndarray], max_pieces: int, max_vertices: int) -> Hulls:
    """Pack convex pieces into the fixed ``[max_pieces, max_vertices]`` layout.

    pieces: list of [n_k, 3] arrays (metres); each is replaced by its hull's vertices, reduced to
    ``max_vertices`` when it has more (``reduce_vertices``).  Raises DecompositionError when there
    are more pieces than ``max_pieces`` or a piece spans no volume.
    """
    if max_pieces < 1:
        raise ValueError(f"max_pieces must be >= 1, got {max_pieces}")
    if len(pieces) > max_pieces:
        raise DecompositionError(f"{len(pieces)} pieces do not fit a layout of {max_pieces}; "
                                 "reduce them first (reduce_pieces)")
    return _pack([reduce_vertices(p, max_vertices) for p in pieces], max_pieces, max_vertices)


def with_max_vertices(hulls: Hulls, max_vertices: int) -> Hulls:
    """The same pieces with at most ``max_vertices`` vertices each (``reduce_vertices``: each
    shrinks inside its hull), each in its own slot of a ``[K, max_vertices]`` layout (the scene
    names geoms by slot): a coarser copy of cached pieces without decomposing the shape again."""
    if max_vertices < 4:
        raise ValueError(f"max_vertices must be >= 4, got {max_vertices}")
    vertices = np.zeros((hulls.max_pieces, max_vertices, 3), np.float32)
    counts = np.zeros(hulls.max_pieces, np.int32)
    for k, n in enumerate(hulls.counts):
        if n == 0:
            continue
        piece = hulls.vertices[k, :n]
        verts = reduce_vertices(piece, max_vertices) if n > max_vertices else piece
        vertices[k, : len(verts)] = verts
        vertices[k, len(verts):] = verts[0]
        counts[k] = len(verts)
    return Hulls(vertices, counts)


def _pack(pieces: list[np.ndarray], max_pieces: int, max_vertices: int) -> Hulls:
    """Already reduced pieces ([n_k <= max_vertices, 3]) into the padded arrays."""
    vertices = np.zeros((max_pieces, max_vertices, 3), np.float32)
    counts = np.zeros(max_pieces, np.int32)
    for k, verts in enumerate(pieces):
        vertices[k, : len(verts)] = verts
        vertices[k, len(verts):] = verts[0]
        counts[k] = len(verts)
    return Hulls(vertices, counts)


def stack_hulls(hulls: list[Hulls]) -> tuple[np.ndarray, np.ndarray]:
    """Stack many shapes' hulls for a batched simulator.

    Returns vertices [N, K, V, 3] float32 and counts [N, K] int32.  Every input must share one
    layout (K, V); raises ValueError naming the first that does not.
    """
    if not hulls:
        raise ValueError("stack_hulls: empty list")
    shape = hulls[0].vertices.shape
    for i, h in enumerate(hulls):
        if h.vertices.shape != shape:
            raise ValueError(f"stack_hulls: hulls[{i}] has layout {h.vertices.shape[:2]}, "
                             f"hulls[0] has {shape[:2]}")
    return (np.stack([h.vertices for h in hulls]).astype(np.float32, copy=False),
            np.stack([h.counts for h in hulls]).astype(np.int32, copy=False))


def hulls_to_mesh(hulls: Hulls) -> trimesh.Trimesh:
    """All pieces as one (self-intersecting) triangle mesh, for rendering and inspection."""
    meshes = [trimesh.convex.convex_hull(p.astype(np.float64)) for p in hulls.pieces()]
    if not meshes:
        return trimesh.Trimesh()
    return trimesh.util.concatenate(meshes)


def points_in_hulls(hulls: Hulls, points, tol: float = 1e-9) -> np.ndarray:
    """[P] bool: which points [P, 3] (metres, same frame) lie inside any piece (within tol)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inside = np.zeros(len(pts), bool)
    for piece in hulls.pieces():
        piece = piece.astype(np.float64)
        lo, hi = piece.min(0) - tol, piece.max(0) + tol
        near = np.nonzero(np.all((pts >= lo) & (pts <= hi), axis=1))[0]
        if len(near) == 0:
            continue
        eq = ConvexHull(piece).equations  # [F, 4]: n . x + d <= 0 inside
        chunk = max(1, _POINT_CHUNK // len(eq))  # bounds the [points, facets] temporary
        for start in range(0, len(near), chunk):
            sel = near[start:start + chunk]
            inside[sel] |= np.all(pts[sel] @ eq[:, :3].T + eq[:, 3] <= tol, axis=1)
    return inside


def _grid_in_hulls(hulls: Hulls, axes, tol: float = 1e-9) -> np.ndarray:
    """points_in_hulls for the grid of the three sorted coordinate vectors ``axes``: each piece
    tests only the grid block inside its bounding box.  Returns [n0, n1, n2] bool."""
    covered = np.zeros(tuple(len(a) for a in axes), bool)
    for piece in hulls.pieces():
        piece = piece.astype(np.float64)
        lo, hi = piece.min(0) - tol, piece.max(0) + tol
        block = tuple(slice(np.searchsorted(a, l), np.searchsorted(a, h, side="right"))
                      for a, l, h in zip(axes, lo, hi))
        if any(b.start >= b.stop for b in block):
            continue
        sub = np.stack(np.meshgrid(*(a[b] for a, b in zip(axes, block)), indexing="ij"), -1)
        eq = ConvexHull(piece).equations
        inside = np.ones(sub.shape[:3], bool)
        for f in eq:  # facet by facet: no [points, facets] temporary
            inside &= sub @ f[:3] + f[3] <= tol
        covered[block] |= inside
    return covered


def hull_fit(tsdf, hulls: Hulls, cfg=None, *, supersample: int = 2) -> dict:
    """How well a shape's hulls match its volume, measured on a grid ``supersample`` times finer.

    tsdf: [R, R, R], negative inside.  The shape's solid is the trilinear interpolation of the
    volume below zero (the surface marching cubes draws).  Returns dict of floats:

    * ``iou``: |hulls & solid| / |hulls | solid|.
    * ``coverage``: share of the solid inside the hulls.
    * ``max_intrusion_m`` / ``mean_intrusion_m``: distance from hull points in the shape's empty
      space to the nearest solid, max and mean over those points (0 when the hulls stay inside).
    * ``max_shortfall_m``: the other side: distance from solid points outside every hull to the
      nearest hull point.
    Distances are between fine-cell centres less half a cell, so a surface that is right to
    within a cell reads as about half a cell.
    """
    g = _geom(cfg)
    arr = check_tsdf(tsdf, "tsdf", g)
    s = int(supersample)
    n = g.resolution * s
    pitch = g.voxel_size / s
    # fine sample centres in volume-index coordinates (voxel i's centre is at index i), +1 for
    # the padding that makes the cube's faces empty
    idx = (np.arange(n) + 0.5) / s - 0.5 + 1
    padded = np.pad(arr, 1, constant_values=1.0)
    grid = np.meshgrid(idx, idx, idx, indexing="ij")
    solid = ndimage.map_coordinates(padded, [c.ravel() for c in grid], order=1) < 0
    solid = solid.reshape(n, n, n)
    c = (np.arange(n) + 0.5) * pitch
    covered = _grid_in_hulls(hulls, (c - g.cube_size / 2, c - g.cube_size / 2, c))
    inter = np.count_nonzero(covered & solid)
    union = np.count_nonzero(covered | solid)

    def depth(region: np.ndarray, of: np.ndarray) -> np.ndarray:
        """Distances (m) from the cells of ``of`` to the nearest cell of ``region``."""
        if not of.any():
            return np.zeros(1)
        if not region.any():
            return np.full(1, np.inf)
        d = ndimage.distance_transform_edt(~region, sampling=pitch)[of] - pitch / 2
        return np.maximum(d, 0.0)

    intrusion = depth(solid, covered & ~solid)
    shortfall = depth(covered, solid & ~covered)
    return dict(iou=float(inter / max(union, 1)),
                coverage=float(inter / max(np.count_nonzero(solid), 1)),
                max_intrusion_m=float(intrusion.max()), mean_intrusion_m=float(intrusion.mean()),
                max_shortfall_m=float(shortfall.max()))


# --------------------------------------------------------------------------------------------
# Fingers: hulls over tiles of the height map
# --------------------------------------------------------------------------------------------

# Tiling measures intrusion exactly up to this many voxels from the solid (a windowed 2.5D
# distance); beyond it by the height above the column's own solid, an upper bound.
_REACH_VOXELS = 4
_TILE_POINTS = 256  # top corners per tile hull at most (bigger tiles are subsampled)
_JUDGE_COLUMNS = 300  # tiles with more columns are judged on every other column
_BISECTIONS = 14  # balance offset to ~(height range) / 2^14, well under a micrometre
# The clip plane allows intrusion into the empty space 0.8 times the shortfall it cuts from the
# solid: a simulated finger that hits the object where the real one would not (premature contact,
# the imprint's typical failure) is a worse error than a few missing millimetres of solid.
_INTRUSION_WEIGHT = 0.8
_EXACT = 1e-6  # m; tile errors below this are rounding (float32 facet planes), not misfit
_MIN_HEIGHT = 1e-4  # m; a clipped piece must reach this far from the mount, else it stays unclipped
# Directions of the cut lines in the (iu, iv) plane.  Steps in a turned object's imprint run at
# any angle; cuts along them separate a wall from the floor beside it in one piece each.
_CUT_ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)
_MIN_SIDE = 0.5  # each side of a cut keeps >= 0.5 sqrt(n) of the tile's n columns


def finger_height_map(finger_tsdf, cfg=None) -> np.ndarray:
    """How far the solid reaches from the mount in each column.

    finger_tsdf: [R, R, R] finger volume, [iu, iv, iw], negative inside.  Returns [R, R] float64
    metres: the w of the zero crossing above the highest solid voxel of column (iu, iv),
    interpolated linearly between that voxel and the next (the cube's far face counts as empty);
    0 for columns with no solid.  Raises VolumeError for an invalid or empty volume.
    """
    g = _geom(cfg)
    arr = check_tsdf(finger_tsdf, "finger", g)
    r = g.resolution
    solid = arr < 0
    occupied = solid.any(axis=2)
    top = r - 1 - np.argmax(solid[:, :, ::-1], axis=2)  # highest solid index per column
    above = np.concatenate([arr, np.ones((r, r, 1), np.float32)], axis=2)
    iu, iv = np.indices((r, r))
    a = arr[iu, iv, top].astype(np.float64)  # < 0
    b = above[iu, iv, top + 1].astype(np.float64)  # >= 0
    frac = np.clip(a / np.minimum(a - b, -1e-9), 0.0, 1.0)
    height = (top + 0.5 + frac) * g.voxel_size
    return np.where(occupied, height, 0.0)


class _HeightField:
    """The finger's height map, its columns, and distances from points above it to its solid.

    Columns are numbered flat, c = iu * R + iv.  Distance from a point above column c at height
    w to the height-field solid, looked up within ``_REACH_VOXELS`` columns: min over neighbours
    c' of sqrt(gap(c, c')^2 + max(w - h(c'), 0)^2), gap = lateral distance from c's centre to
    c''s footprint.
    """

    def __init__(self, height: np.ndarray, g: GeometryConfig):
        self.g = g
        self.h = height
        self.h_flat = height.ravel()
        r = height.shape[0]
        self.r = r
        vox = g.voxel_size
        iu, iv = np.indices((r, r))
        self.iu, self.iv = iu.ravel(), iv.ravel()
        rr = _REACH_VOXELS
        du, dv = np.meshgrid(np.arange(-rr, rr + 1), np.arange(-rr, rr + 1), indexing="ij")
        du, dv = du.ravel(), dv.ravel()
        gap = np.hypot(np.maximum(np.abs(du) - 0.5, 0), np.maximum(np.abs(dv) - 0.5, 0))
        keep = gap <= rr
        du, dv, gap = du[keep], dv[keep], gap[keep] * vox
        nu, nv = iu[..., None] + du, iv[..., None] + dv  # [R, R, O]
        inside = (nu >= 0) & (nu < r) & (nv >= 0) & (nv < r)
        nh = np.where(inside, height[np.clip(nu, 0, r - 1), np.clip(nv, 0, r - 1)], 0.0)
        solid = inside & (nh > 0)
        self.reach = rr * vox
        # squared lateral gaps, infinite towards columns without solid; the neighbours' heights
        self.gap2 = np.where(solid, gap**2, np.inf).reshape(r * r, -1)
        self.nh = nh.reshape(r * r, -1)
        # column centres (u, v) in metres
        c = (np.arange(r) + 0.5) * vox - g.cube_size / 2
        self.uv = np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)

    def distance(self, cols: np.ndarray, w: np.ndarray) -> np.ndarray:
        """[Q] metres from (centre of column cols[q], height w[q]) to the solid.

        Exact up to the reach; beyond it the height above the column's own solid (an upper
        bound, never below the reach), so deep errors still rank by size."""
        rise = np.maximum(w[:, None] - self.nh[cols], 0.0)
        d = np.sqrt(np.min(self.gap2[cols] + rise**2, axis=1))
        own = np.maximum(w - self.h_flat[cols], 0.0)
        return np.where(d <= self.reach, d, np.maximum(own, self.reach))


def _tile_points(field: _HeightField, members: np.ndarray):
    """Points whose hull covers the tile's solid: the footprint corners of its solid columns at
    their heights and at w = 0 (a corner shared by columns of different height takes the
    highest).  Big tiles use every s-th corner (s chosen to keep about ``_TILE_POINTS`` corners),
    each taking the highest of the corners nearest to it, so hulls and their facet counts stay
    small; the corners of the tile's bounding box are always kept.  Returns [P, 3] float64, or
    None for a tile without solid."""
    g = field.g
    h = field.h_flat[members]
    if not np.any(h > 0):
        return None
    iu, iv = field.iu[members], field.iv[members]
    i0, j0 = iu.min(), iv.min()
    sub = np.full((iu.max() - i0 + 1, iv.max() - j0 + 1), -np.inf)
    sub[iu - i0, iv - j0] = np.where(h > 0, h, -np.inf)
    hp = np.pad(sub, 1, constant_values=-np.inf)
    corner = np.maximum(np.maximum(hp[:-1, :-1], hp[1:, :-1]), np.maximum(hp[:-1, 1:], hp[1:, 1:]))
    ku, kv = np.arange(corner.shape[0]), np.arange(corner.shape[1])
    stride = int(np.ceil(np.sqrt(np.count_nonzero(corner > -np.inf) / _TILE_POINTS)))
    if stride > 1:
        ku, starts_u = _coarse_lattice(len(ku), stride)
        kv, starts_v = _coarse_lattice(len(kv), stride)
        corner = np.maximum.reduceat(corner, starts_u, axis=0)
        corner = np.maximum.reduceat(corner, starts_v, axis=1)
    ci, cj = np.nonzero(corner > -np.inf)
    u = (i0 + ku[ci]) * g.voxel_size - g.cube_size / 2
    v = (j0 + kv[cj]) * g.voxel_size - g.cube_size / 2
    top = np.stack([u, v, corner[ci, cj]], 1)
    bottom = np.stack([u, v, np.zeros_like(u)], 1)
    return np.concatenate([top, bottom])


def _coarse_lattice(n: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every stride-th of n lattice indices plus the last one, and where the bins of the fine
    indices nearest to each start (for np.maximum.reduceat)."""
    keep = np.unique(np.r_[np.arange(0, n, stride), n - 1])
    starts = np.r_[0, (keep[:-1] + keep[1:]) // 2 + 1]
    return keep, starts


def _hull_top(eq: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[Q] height of the hull's upper surface above points uv [Q, 2]; -inf where the vertical
    line misses the hull.  eq: [F, 4] ConvexHull equations (n . x + d <= 0 inside); the hull
    lies on w >= 0 with its bottom face on w = 0 (a tile's piece)."""
    nw = eq[:, 2]
    up, side = nw > 1e-9, np.abs(nw) <= 1e-9
    # each upper facet as the plane w = a + b u + c v; float32 halves the memory traffic of the
    # [Q, F] products, still micrometre-exact at these sizes
    a, b, c = (-eq[up, 3] / nw[up], -eq[up, 0] / nw[up], -eq[up, 1] / nw[up])
    u, v = uv[:, :1].astype(np.float32), uv[:, 1:].astype(np.float32)
    top = np.min(a.astype(np.float32) + u * b.astype(np.float32) + v * c.astype(np.float32),
                 axis=1).astype(np.float64)
    if side.any():  # vertical facets bound the footprint
        outside = np.any(eq[side, 3] + uv[:, :1] * eq[side, 0] + uv[:, 1:] * eq[side, 1] > 1e-12,
                         axis=1)
        top = np.where(outside, -np.inf, top)
    return top


def _fit_plane(uv: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Least-squares plane h ~ c0 + c1 u + c2 v; a tiny ridge keeps one-line tiles flat."""
    a = np.c_[np.ones(len(uv)), uv]
    gram = np.einsum("ni,nj->ij", a, a) + np.diag([0.0, 1e-9, 1e-9])
    return np.linalg.solve(gram, np.einsum("ni,n->i", a, h))


def _balanced_offset(top: np.ndarray, plane: np.ndarray, h: np.ndarray) -> float:
    """Offset o for the clip w <= plane + o at which the worst excess (top' - h) is
    ``_INTRUSION_WEIGHT`` times the worst shortfall (h - top'), top' = min(top, plane + o), over
    the tile's solid columns.

    Both are monotone in o, so bisection finds the balance; returns +inf when clipping cannot
    lower the worst error (the hull already fits: a ridge or a flat face)."""
    excess_full = float(np.max(top - h))
    if excess_full <= 1e-6:
        return np.inf
    lo = float(np.min(h - plane)) - excess_full
    hi = float(np.max(top - plane))
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        clipped = np.minimum(top, plane + mid)
        if np.max(clipped - h) > _INTRUSION_WEIGHT * np.max(h - clipped):
            hi = mid
        else:
            lo = mid
    return hi


def _clip_halfspace(points: np.ndarray, hull: ConvexHull, normal: np.ndarray,
                    offset: float) -> np.ndarray:
    """Vertices of the hull of ``points`` cut by the half-space normal . x <= offset: the hull
    vertices inside it and the points where hull edges cross its plane.  [P', 3]."""
    side = points[:, 0] * normal[0] + points[:, 1] * normal[1] + points[:, 2] * normal[2] - offset
    # each edge once: the edge opposite vertex i of facet f is shared with neighbour i of f
    tri, nbr = hull.simplices, hull.neighbors
    facet = np.arange(len(tri))
    a, b = [], []
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        own = facet < nbr[:, i]
        a.append(tri[own, j])
        b.append(tri[own, k])
    a, b = np.concatenate(a), np.concatenate(b)
    cross = (side[a] > 0) != (side[b] > 0)
    a, b = a[cross], b[cross]
    t = side[a] / (side[a] - side[b])
    inside = hull.vertices[side[hull.vertices] <= 0]
    return np.concatenate([points[inside], points[a] + t[:, None] * (points[b] - points[a])])


@dataclass
class _Tile:
    members: np.ndarray  # flat column indices c = iu * R + iv
    points: np.ndarray | None  # the piece's points, None when the tile has no solid
    error: float  # worst surface error of the piece (m): intrusion, or weighted shortfall
    hull_points: np.ndarray | None = None  # the unclipped hull's points, where clipped


def _make_tile(field: _HeightField, members: np.ndarray, cover: bool) -> _Tile:
    """The piece of one tile and its worst error.

    cover=True: the hull of the tile's columns (contains all their solid; errors are intrusion
    into the empty space where the height map is concave).  cover=False: that hull clipped by one
    plane (least-squares plane of the heights, offset to trade intrusion against shortfall,
    ``_balanced_offset``), which roughly halves the error over a bowl at the cost of shaving
    solid."""
    pts = _tile_points(field, members)
    if pts is None:
        return _Tile(members, None, 0.0)
    if len(members) == 1:
        return _Tile(members, pts, 0.0)  # one column: its piece is exact
    hull = ConvexHull(pts)
    cols = members
    if len(members) > _JUDGE_COLUMNS:
        # big tiles are judged on every other column: they get split anyway, and the
        # [columns, facets] products dominate the cost
        cols = members[(field.iu[members] % 2 == 0) & (field.iv[members] % 2 == 0)]
    uv = field.uv[cols]
    top = _hull_top(hull.equations, uv)
    h = field.h_flat[cols]
    solid = h > 0
    shortfall = 0.0
    hull_points = None
    if not cover and solid.any():
        coef = _fit_plane(uv[solid], h[solid])
        plane = coef[0] + uv[:, 0] * coef[1] + uv[:, 1] * coef[2]
        offset = _balanced_offset(top[solid], plane[solid], h[solid])
        if np.isfinite(offset):
            # w <= c0 + o + c1 u + c2 v  <=>  (-c1, -c2, 1) . x <= c0 + o
            new_pts = _clip_halfspace(pts, hull, np.array([-coef[1], -coef[2], 1.0]),
                                      coef[0] + offset)
            # a plane below the whole tile would leave a flat piece: keep the hull then
            if len(new_pts) >= 4 and new_pts[:, 2].max() > _MIN_HEIGHT:
                hull_points, pts = pts, new_pts
                top = np.minimum(top, plane + offset)
                # shortfall measured across the plane's slope, like a distance
                tilt = np.sqrt(1.0 + coef[1] ** 2 + coef[2] ** 2)
                shortfall = float(np.max(h[solid] - np.maximum(top[solid], 0.0))) / tilt
    hit = top > 0
    intrusion = float(field.distance(cols[hit], top[hit]).max()) if hit.any() else 0.0
    error = max(intrusion, _INTRUSION_WEIGHT * shortfall)
    return _Tile(members, pts, error if error > _EXACT else 0.0, hull_points)


def _rss(gram: np.ndarray, rhs: np.ndarray, sq: np.ndarray) -> np.ndarray:
    """Residual sums of squares of least-squares planes from their normal equations, batched:
    gram [n, 3, 3] (symmetric), rhs [n, 3], sq [n] -> sq - rhs . gram^-1 rhs.  Closed-form 3x3
    inverse (adjugate): thousands of tiny solves, no LAPACK call overhead."""
    a, b, c = gram[:, 0, 0], gram[:, 0, 1], gram[:, 0, 2]
    d, e, f = gram[:, 1, 1] + _RIDGE, gram[:, 1, 2], gram[:, 2, 2] + _RIDGE
    # cofactors of the symmetric matrix [[a b c] [b d e] [c e f]]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    x, y, z = rhs[:, 0], rhs[:, 1], rhs[:, 2]
    quad = (A * x * x + D * y * y + F * z * z + 2 * (B * x * y + C * x * z + E * y * z))
    return sq - quad / np.where(np.abs(det) > 1e-300, det, np.inf)


_RIDGE = 1e-6  # on the slope terms (index units): keeps one-line tiles' planes flat


def _best_cut(field: _HeightField, members: np.ndarray):
    """Split a tile's columns along the straight cut after which planes fit both halves best.

    For each direction in ``_CUT_ANGLES_DEG`` the columns are ordered along the direction's
    normal; every gap between distinct positions is a candidate cut.  Cost: the halves'
    residual sums of squares about their least-squares planes (empty columns count as height 0),
    for all cuts at once from prefix sums of the normal equations.  Pieces end up nearly planar,
    which is what a hull (clipped or not) fits; a thin high wall beside a low floor is peeled off
    in one cut.  Returns the two member arrays, or None for a single column."""
    n = len(members)
    if n < 2:
        return None
    iu = field.iu[members].astype(np.float64)
    iv = field.iv[members].astype(np.float64)
    h = field.h_flat[members]
    x = np.stack([np.ones(n), iu - iu.mean(), iv - iv.mean()], 1)  # [n, 3]
    total_gram = np.einsum("ni,nj->ij", x, x)
    total_rhs = np.einsum("ni,n->i", x, h)
    total_sq = float(np.sum(h * h))
    min_side = max(1.0, _MIN_SIDE * np.sqrt(n))
    best = None
    for angle in _CUT_ANGLES_DEG:
        t = iu * np.cos(np.radians(angle)) + iv * np.sin(np.radians(angle))
        order = np.argsort(t, kind="stable")
        ts = t[order]
        cuts = np.flatnonzero(np.diff(ts) > 1e-9) + 1  # cut before sorted position p
        # no slivers: a cut that shaves a corner column off lowers the squares a lot (an empty
        # corner counts as height 0) but not the worst error
        cuts = cuts[(cuts >= min_side) & (n - cuts >= min_side)]
        if len(cuts) == 0:
            continue
        xs, hs = x[order], h[order]
        gram = np.cumsum(xs[:, :, None] * xs[:, None, :], axis=0)[cuts - 1]
        rhs = np.cumsum(xs * hs[:, None], axis=0)[cuts - 1]
        sq = np.cumsum(hs * hs)[cuts - 1]
        cost = _rss(gram, rhs, sq) + _rss(total_gram - gram, total_rhs - rhs, total_sq - sq)
        # prefer cuts near the middle among near-equals: balanced tiles shrink errors fastest
        cost = cost + 1e-9 * (1.0 + np.abs(cost).max()) * np.abs(cuts - n / 2) / n
        j = int(np.argmin(cost))
        if best is None or cost[j] < best[0]:
            best = (cost[j], order, cuts[j])
    if best is None:
        return None
    _, order, p = best
    return np.sort(members[order[:p]]), np.sort(members[order[p:]])


def _tile_height_map(height: np.ndarray, g: GeometryConfig, max_tiles: int,
                     cover: bool) -> list[_Tile]:
    """Greedy binary space partition of the columns: split the tile with the worst error until
    max_tiles tiles hold solid or every piece is exact.  (Choosing among cuts by the halves'
    exact errors was tried: the one-step-better cut often leads to worse tilings later, at
    twice the cost.)"""
    field = _HeightField(height, g)
    occ = np.nonzero(height > 0)
    box = np.zeros_like(height, bool)
    box[occ[0].min():occ[0].max() + 1, occ[1].min():occ[1].max() + 1] = True
    heap: list = []  # max-heap on error, then size; the counter keeps ties deterministic
    done: list[_Tile] = []
    counter = 0

    def push(tile: _Tile):
        nonlocal counter
        if tile.points is None:
            return
        heapq.heappush(heap, (-tile.error, -len(tile.members), counter, tile))
        counter += 1

    push(_make_tile(field, np.flatnonzero(box.ravel()), cover))
    while heap and len(heap) + len(done) < max_tiles:
        neg_error, _, _, tile = heapq.heappop(heap)
        if -neg_error <= 0.0:
            done.append(tile)
            break
        halves = _best_cut(field, tile.members)
        if halves is None:
            done.append(tile)
            continue
        for members in halves:
            push(_make_tile(field, members, cover))
    done.extend(item[-1] for item in heap)
    # slot order by position, so similar fingers fill their slots alike
    return sorted(done, key=lambda t: int(t.members[0]))


def finger_tiles(finger_tsdf, cfg=None, *, max_pieces: int | None = None,
                 cover: bool = False) -> np.ndarray:
    """The partition of a finger's columns that ``finger_hulls`` uses.

    Returns [R, R] int: the slot of the piece that covers column (iu, iv), -1 for columns in no
    piece (outside the solid's bounding box, or in a tile without solid)."""
    g = _geom(cfg)
    height = finger_height_map(finger_tsdf, g)
    labels = np.full(height.size, -1)
    for slot, tile in enumerate(_tile_height_map(height, g, max_pieces or g.finger_hulls, cover)):
        labels[tile.members] = slot
    return labels.reshape(height.shape)


def finger_hulls(finger_tsdf, cfg=None, *, max_pieces: int | None = None,
                 max_vertices: int | None = None, cover: bool = False) -> Hulls:
    """Convex pieces of a finger from its height map, in milliseconds.

    finger_tsdf: [R, R, R] finger volume, [iu, iv, iw], negative inside (config.py frames).
    Returns Hulls [max_pieces (cfg.finger_hulls), max_vertices (cfg.hull_vertices), 3] in the
    finger's local frame.  The columns are split by straight cuts (0, 45, 90, 135 degrees) into
    at most max_pieces tiles; each piece is the convex hull of one tile's columns from the mount
    (w = 0) up to the height map.  With cover=False (default) each hull is also cut by the tile's
    best-fit plane, offset so that the piece reaches into the empty space 0.8 times as far as it
    falls short of the solid: over a concave bowl that about halves the intrusion of the plain
    hull.  cover=True keeps the plain hulls, which contain the whole (undercut-filled) solid.
    Tiles are split where the error is worst, along the cut after which planes fit both halves
    best.  Undercuts are filled (module docstring).  Raises VolumeError for an invalid or empty
    volume.
    """
    g = _geom(cfg)
    k = max_pieces or g.finger_hulls
    v = max_vertices or g.hull_vertices
    height = finger_height_map(finger_tsdf, g)
    pieces = []
    for tile in _tile_height_map(height, g, k, cover):
        try:
            pieces.append(reduce_vertices(tile.points, v))
        except DecompositionError:
            if tile.hull_points is None:
                raise
            pieces.append(reduce_vertices(tile.hull_points, v))  # a clip left a sliver
    return _pack(pieces, k, v)


# --------------------------------------------------------------------------------------------
# Objects: coacd once per object, cached on disk
# --------------------------------------------------------------------------------------------


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
        return [_hull_vertices(verts)]
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
        pieces = [_hull_vertices(verts)]
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
    hulls = [_hull_vertices(np.asarray(p, dtype=np.float64)) for p in pieces]
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
        hulls.append(_hull_vertices(np.concatenate([hulls[i], hulls[j]])))
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
    pieces = [_hull_vertices(np.asarray(p, dtype=np.float64)) for p in pieces]
    misfit = [_reduce(p, max_vertices)[1] for p in pieces]
    while len(pieces) < max_pieces and misfit and max(misfit) > tolerance:
        worst = int(np.argmax(misfit))
        piece = pieces[worst]
        centre = piece.mean(axis=0)
        axis = np.linalg.eigh(np.cov((piece - centre).T))[1][:, -1]
        hull = ConvexHull(piece)
        try:
            halves = [_hull_vertices(_clip_halfspace(piece, hull, s * axis, s * centre @ axis))
                      for s in (1.0, -1.0)]
        except DecompositionError:  # a sliver that cannot be cut: leave it
            misfit[worst] = 0.0
            continue
        pieces[worst:worst + 1] = halves
        misfit[worst:worst + 1] = [_reduce(h, max_vertices)[1] for h in halves]
    return pieces


def _layout(pieces: list[np.ndarray], k: int, v: int, g: GeometryConfig, name: str) -> Hulls:
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
    g = _geom(cfg)
    k = max_pieces or g.object_hulls
    v = max_vertices or g.hull_vertices
    return _layout(decompose_mesh(mesh, settings, name=name), k, v, g, name)


def _hull_excess(arr: np.ndarray, pts: np.ndarray, g: GeometryConfig) -> float:
    """How far (m) the hull of pts reaches into the volume's empty space, read from the TSDF at
    the voxel centres inside the hull (an empty voxel's value times the truncation is its
    distance to the surface, up to the truncation)."""
    verts, _ = _reduce(pts, _CONVEX_TEST_VERTICES)
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


def _cache_key(arr: np.ndarray, g: GeometryConfig, k: int, v: int,
               settings: CoacdSettings) -> str:
    meta = json.dumps(dict(version=_CACHE_VERSION, max_pieces=k, max_vertices=v,
                           resolution=g.resolution, cube_size=g.cube_size,
                           convex_tolerance=_CONVEX_TOLERANCE_VOXELS,
                           refine_tolerance=_REFINE_TOLERANCE_VOXELS,
                           settings=dataclasses.asdict(settings)), sort_keys=True)
    digest = hashlib.sha1(np.ascontiguousarray(arr, dtype=np.float32).tobytes())
    digest.update(meta.encode())
    return digest.hexdigest()


def _load_cached(path: Path, k: int, v: int) -> Hulls | None:
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


def _save_atomic(path: Path, hulls: Hulls) -> None:
    """Write the npz next to its destination, then rename: readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, vertices=hulls.vertices, counts=hulls.counts)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _cache_path(arr: np.ndarray, g: GeometryConfig, k: int, v: int, settings: CoacdSettings,
                cache_dir) -> Path:
    directory = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    return directory / f"{_cache_key(arr, g, k, v, settings)}.npz"


def cached_object_hulls(obj_tsdf, cfg=None, *, cache_dir=None) -> Hulls | None:
    """The cached ``object_hulls`` of a volume (default layout and settings), or None when
    they were never made here.  Raises VolumeError for an invalid volume."""
    g = _geom(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k, v = g.object_hulls, g.hull_vertices
    return _load_cached(_cache_path(arr, g, k, v, CoacdSettings(), cache_dir), k, v)


def store_object_hulls(obj_tsdf, hulls: Hulls, cfg=None, *, cache_dir=None) -> None:
    """Cache hulls that ``object_hulls(obj_tsdf, cfg, cache_dir=None)`` made elsewhere (another
    process or machine, e.g. a Ray worker), as ``object_hulls`` would have; atomic."""
    g = _geom(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k, v = g.object_hulls, g.hull_vertices
    if hulls.vertices.shape != (k, v, 3):
        raise ValueError(f"hulls of layout {hulls.vertices.shape}, expected {(k, v, 3)}")
    _save_atomic(_cache_path(arr, g, k, v, CoacdSettings(), cache_dir), hulls)


def object_hulls(obj_tsdf, cfg=None, *, cache_dir: str | os.PathLike | None | bool = None,
                 max_pieces: int | None = None, max_vertices: int | None = None,
                 settings: CoacdSettings | None = None) -> Hulls:
    """Convex pieces of an object volume, computed once and cached on disk.

    obj_tsdf: [R, R, R] object volume, negative inside.  The marching-cubes surface
    (``tsdf_to_mesh``, metres, the object's local frame) is decomposed by coacd (``mesh_hulls``)
    unless its convex hull reaches at most a voxel into the empty space: then the hull is the
    one piece (coacd would cut a convex shape along the voxel staircase, slowly).
    The result is cached as ``<sha1>.npz`` in cache_dir (default ``default_cache_dir()``; False:
    no cache, neither read nor written), keyed by the float32 volume bytes, the layout and the
    settings; writes are atomic and an unreadable file is recomputed.
    Returns Hulls [max_pieces (cfg.object_hulls), max_vertices, 3].
    Raises VolumeError for an invalid or empty volume, DecompositionError if no piece can be made.
    """
    g = _geom(cfg)
    arr = check_tsdf(obj_tsdf, "object", g)
    k = max_pieces or g.object_hulls
    v = max_vertices or g.hull_vertices
    settings = settings or CoacdSettings()
    use_cache = cache_dir is not False
    path = _cache_path(arr, g, k, v, settings, cache_dir if use_cache else None)
    if use_cache:
        cached = _load_cached(path, k, v)
        if cached is not None:
            return cached
    start = time.perf_counter()
    name = f"object {path.stem[:10]}"
    mesh = tsdf_to_mesh(arr, g, name="object")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    if _hull_excess(arr, verts, g) <= _CONVEX_TOLERANCE_VOXELS * g.voxel_size:
        # convex up to the voxels' staircase: coacd would only cut it along the stairs
        pieces = [_hull_vertices(verts)]
    else:
        pieces = decompose_mesh(mesh, settings, name=name)
    hulls = _layout(pieces, k, v, g, name)
    log.info("object hulls %s: %d pieces in %.1f s", path.stem[:10], hulls.n_pieces,
             time.perf_counter() - start)
    if use_cache:
        _save_atomic(path, hulls)
    return hulls


def _object_hulls_or_error(obj, cfg, cache_dir) -> Hulls | str:
    try:
        return object_hulls(obj, cfg, cache_dir=cache_dir)
    except (F2FError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"


def _worker_main(argv: list[str]) -> int:
    """``python -m f2f_jax.geometry.hulls VOLUMES.npy INDICES CACHE_DIR GEOMETRY_JSON ERR_DIR``:
    decompose the listed volumes into the cache; failures go to ERR_DIR/<index>.txt."""
    volumes_path, indices, cache_dir, geometry, err_dir = argv
    volumes = np.load(volumes_path, mmap_mode="r")
    g = GeometryConfig(**json.loads(geometry))
    for i in json.loads(indices):
        res = _object_hulls_or_error(np.array(volumes[i]), g, cache_dir)
        if isinstance(res, str):
            Path(err_dir, f"{i}.txt").write_text(res)
    return 0


def object_hulls_many(objects, cfg=None, *, cache_dir=None, workers: int | None = None,
                      progress: bool | None = None) -> list[Hulls | str]:
    """``object_hulls`` of many object volumes: cached ones read here, the rest decomposed by
    coacd in ``workers`` worker processes (default: one per CPU).  coacd holds the GIL and a core
    for seconds per object, so threads would not run it side by side; the workers are plain
    ``python -m`` subprocesses (not multiprocessing), which needs no ``__main__`` guard in the
    caller's script and never forks a process that runs JAX threads.

    objects: sequence of [R, R, R] volumes (duplicates are decomposed once).
    Returns one entry per object: its Hulls, or the error message of a volume that could not be
    decomposed (so one bad object does not stop a batch).
    """
    import subprocess
    import sys

    from tqdm.auto import tqdm

    g = _geom(cfg)
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
        path = directory / f"{_cache_key(arr, g, g.object_hulls, g.hull_vertices, CoacdSettings())}.npz"
        cached = _load_cached(path, g.object_hulls, g.hull_vertices)
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
                [sys.executable, "-m", "f2f_jax.geometry.hulls", str(Path(tmp) / "volumes.npy"),
                 json.dumps(list(range(w, len(todo), workers))), str(directory), geometry, tmp],
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
                    made[key] = _object_hulls_or_error(objs[first[key]], g, cache_dir)
        bar.n = len(todo)
    else:
        for key, _ in todo:
            made[key] = _object_hulls_or_error(objs[first[key]], g, cache_dir)
            bar.update(1)
    bar.close()
    return [made[k] for k in keys]


if __name__ == "__main__":
    import sys

    sys.exit(_worker_main(sys.argv[1:]))
