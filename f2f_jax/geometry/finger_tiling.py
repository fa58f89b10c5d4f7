"""Finger hulls over tiles of the height map.

Fingers are new every training cycle (thousands), so they get a method that costs tens of
milliseconds (``finger_hulls``).  A finger is mounted on the plane ``w = 0`` and the object
meets it from ``+w``, so the surface that matters is the height map ``h(u, v)``: how far the
solid reaches from the mount in each column.  The columns are split by straight cuts into
tiles, each tile's piece is the convex hull of its columns from ``w = 0`` up to ``h``, cut by
the tile's best-fit plane.  A hull over-covers where the map is concave inside its tile (a
bowl's hull fills the bowl); the plane trades that intrusion for a smaller shortfall, and tiles
are split where the worse of the two is largest.  Simplification: solid hanging over a hollow
that faces the mount (an undercut) is filled down to the mount; imprint fingers have none.
"""

from __future__ import annotations

import functools
import hashlib
import heapq
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from f2f_jax.config import GeometryConfig, geometry_config
from f2f_jax.errors import DecompositionError
from f2f_jax.geometry.hulls import (
    Hulls,
    QuickHull,
    clip_halfspace,
    pack_pieces,
    reduce_hull,
    reduce_vertices,
)
from f2f_jax.geometry.tile_cuts import best_cut
from f2f_jax.geometry.tsdf import check_tsdf

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
_max, _min = np.maximum.reduce, np.minimum.reduce  # np.max and np.min, without their wrappers
_REMEMBERED = 256  # distinct fingers whose pieces ``remembered_finger_hulls`` keeps (~7 KB each)


def finger_height_map(finger_tsdf, cfg=None) -> np.ndarray:
    """How far the solid reaches from the mount in each column.

    finger_tsdf: [R, R, R] finger volume, [iu, iv, iw], negative inside.  Returns [R, R] float64
    metres: the w of the zero crossing above the highest solid voxel of column (iu, iv),
    interpolated linearly between that voxel and the next (the cube's far face counts as empty);
    0 for columns with no solid.  Raises VolumeError for an invalid or empty volume.
    """
    g = geometry_config(cfg)
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
        lay = _layout(r, g.voxel_size, g.cube_size)
        self.iu, self.iv, self.even, self.uv, self.corners = (
            lay.iu, lay.iv, lay.even, lay.uv, lay.corners)
        self.reach = _REACH_VOXELS * g.voxel_size
        # the neighbours' heights (0 off the map) and squared lateral gaps to them, infinite
        # towards columns without solid: [R^2, offsets]
        padded = np.zeros((r + 2 * _REACH_VOXELS,) * 2)
        padded[_REACH_VOXELS:-_REACH_VOXELS, _REACH_VOXELS:-_REACH_VOXELS] = height
        self.nh = padded.ravel()[lay.neighbours]
        self.gap2 = np.where(self.nh > 0, lay.gap2, np.inf)

    def distance(self, cols: np.ndarray, w: np.ndarray) -> np.ndarray:
        """[Q] metres from (centre of column cols[q], height w[q]) to the solid.

        Exact up to the reach; beyond it the height above the column's own solid (an upper
        bound, never below the reach), so deep errors still rank by size."""
        rise = w[:, None] - self.nh[cols]
        np.maximum(rise, 0.0, out=rise)
        rise *= rise
        rise += self.gap2[cols]
        d = np.sqrt(_min(rise, axis=1))
        own = np.maximum(w - self.h_flat[cols], 0.0)
        return np.where(d <= self.reach, d, np.maximum(own, self.reach))


@dataclass(frozen=True)
class _Layout:
    """What every height map of one resolution and voxel shares (``_layout``)."""

    iu: np.ndarray  # [R^2] column rows and columns
    iv: np.ndarray
    even: np.ndarray  # [R^2] bool: both even (the columns big tiles are judged on)
    uv: np.ndarray  # [R^2, 2] column centres (u, v), metres
    corners: np.ndarray  # [R + 1] footprint corner coordinates, metres
    neighbours: np.ndarray  # [R^2, O] flat index of each column's neighbours in the padded map
    gap2: np.ndarray  # [O] squared lateral gap to each neighbour (m^2)


@functools.lru_cache(maxsize=8)
def _layout(r: int, vox: float, cube: float) -> _Layout:
    iu, iv = np.indices((r, r))
    rr = _REACH_VOXELS
    du, dv = np.meshgrid(np.arange(-rr, rr + 1), np.arange(-rr, rr + 1), indexing="ij")
    du, dv = du.ravel(), dv.ravel()
    gap = np.hypot(np.maximum(np.abs(du) - 0.5, 0), np.maximum(np.abs(dv) - 0.5, 0))
    keep = gap <= rr
    du, dv, gap = du[keep], dv[keep], gap[keep] * vox
    neighbours = ((iu[..., None] + du + rr) * (r + 2 * rr) + iv[..., None] + dv + rr)
    c = (np.arange(r) + 0.5) * vox - cube / 2
    lay = _Layout(iu.ravel(), iv.ravel(), ((iu % 2 == 0) & (iv % 2 == 0)).ravel(),
                  np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2),
                  np.arange(r + 1) * vox - cube / 2, neighbours.reshape(r * r, -1), gap**2)
    for a in vars(lay).values():
        a.setflags(write=False)
    return lay


def _tile_points(field: _HeightField, members: np.ndarray):
    """Points whose hull covers the tile's solid: the footprint corners of its solid columns at
    their heights and at w = 0 (a corner shared by columns of different height takes the
    highest).  Big tiles use every s-th corner (s chosen to keep about ``_TILE_POINTS`` corners),
    each taking the highest of the corners nearest to it, so hulls and their facet counts stay
    small; the corners of the tile's bounding box are always kept.  members: sorted.  Returns
    [P, 3] float64, or None for a tile without solid."""
    h = field.h_flat[members]
    solid = h > 0
    if not solid.any():
        return None
    iu, iv = field.iu[members], field.iv[members]
    i0, j0 = int(iu[0]), int(_min(iv))  # members are sorted, so by iu first
    hp = np.full((int(iu[-1]) - i0 + 3, int(_max(iv)) - j0 + 3), -np.inf)
    hp[iu - (i0 - 1), iv - (j0 - 1)] = np.where(solid, h, -np.inf)
    rows = np.maximum(hp[:-1], hp[1:])
    corner = np.maximum(rows[:, :-1], rows[:, 1:])
    real = corner > -np.inf
    stride = math.ceil(math.sqrt(np.count_nonzero(real) / _TILE_POINTS))
    if stride > 1:
        ku, starts_u = _coarse_lattice(corner.shape[0], stride)
        kv, starts_v = _coarse_lattice(corner.shape[1], stride)
        corner = np.maximum.reduceat(corner, starts_u, axis=0)
        corner = np.maximum.reduceat(corner, starts_v, axis=1)
        real = corner > -np.inf
        ci, cj = np.nonzero(real)
        ci, cj = ku[ci], kv[cj]
    else:
        ci, cj = np.nonzero(real)
    m = len(ci)
    out = np.empty((2, m, 3))
    out[:, :, 0] = field.corners[i0 + ci]
    out[:, :, 1] = field.corners[j0 + cj]
    out[0, :, 2] = corner[real]
    out[1, :, 2] = 0.0
    return out.reshape(2 * m, 3)


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
    up = nw > 1e-9
    e, n = eq[up], nw[up]
    # each upper facet as the plane w = a + b u + c v; float32 halves the memory traffic of the
    # [Q, F] products, still micrometre-exact at these sizes
    a, b, c = ((-e[:, k] / n).astype(np.float32) for k in (3, 0, 1))
    uv32 = uv.astype(np.float32)
    plane = uv32[:, :1] * b
    plane += a
    plane += uv32[:, 1:] * c
    top = _min(plane, axis=1).astype(np.float64)
    side = np.abs(nw) <= 1e-9
    if len(e) < len(eq) and side.any():  # vertical facets bound the footprint
        s = eq[side]
        outside = np.any(s[:, 3] + uv[:, :1] * s[:, 0] + uv[:, 1:] * s[:, 1] > 1e-12, axis=1)
        top[outside] = -np.inf
    return top


def _fit_plane(uv: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Least-squares plane h ~ c0 + c1 u + c2 v; a tiny ridge keeps one-line tiles flat."""
    a = np.empty((len(uv), 3))
    a[:, 0] = 1.0
    a[:, 1:] = uv
    gram = np.einsum("ni,nj->ij", a, a)
    gram += _PLANE_RIDGE
    return _solve(gram, np.einsum("ni,n->i", a, h))


_PLANE_RIDGE = np.diag([0.0, 1e-9, 1e-9])
# np.linalg.solve's kernel for one right-hand side, without its per-call checks (the ridge keeps
# the gram positive definite)
_solve1 = getattr(getattr(np.linalg, "_umath_linalg", None), "solve1", None)


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.solve(a, b) if _solve1 is None else _solve1(a, b, signature="dd->d")


def _balanced_offset(top: np.ndarray, plane: np.ndarray, h: np.ndarray) -> float:
    """Offset o for the clip w <= plane + o at which the worst excess (top' - h) is
    ``_INTRUSION_WEIGHT`` times the worst shortfall (h - top'), top' = min(top, plane + o), over
    the tile's solid columns.

    Both are monotone in o, so bisection finds the balance; returns +inf when clipping cannot
    lower the worst error (the hull already fits: a ridge or a flat face)."""
    excess_full = float(_max(top - h))
    if excess_full <= 1e-6:
        return np.inf
    lo = float(_min(h - plane)) - excess_full
    hi = float(_max(top - plane))
    excess = np.empty_like(top)
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        np.add(plane, mid, out=excess)
        np.minimum(top, excess, out=excess)
        excess -= h  # its negation is the shortfall
        if _max(excess) > _INTRUSION_WEIGHT * -_min(excess):
            hi = mid
        else:
            lo = mid
    return hi


@dataclass
class _Tile:
    members: np.ndarray  # flat column indices c = iu * R + iv
    points: np.ndarray | None  # the piece's points, None when the tile has no solid
    error: float  # worst surface error of the piece (m): intrusion, or weighted shortfall
    hull_points: np.ndarray | None = None  # the unclipped hull's points, where clipped
    hull: QuickHull | None = None  # the hull of the unclipped points, where made

    def vertices(self, max_vertices: int) -> np.ndarray:
        """The piece's vertices (``reduce_vertices`` of its points), the unclipped hull's when a
        clip left a sliver."""
        if self.hull is not None and self.hull_points is None:
            return reduce_hull(self.points[self.hull.vertices], max_vertices)[0]
        try:
            return reduce_vertices(self.points, max_vertices)
        except DecompositionError:
            if self.hull_points is None:
                raise
            return reduce_hull(self.hull_points[self.hull.vertices], max_vertices)[0]


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
    hull = QuickHull(pts)
    cols = members
    if len(members) > _JUDGE_COLUMNS:
        # big tiles are judged on every other column: they get split anyway, and the
        # [columns, facets] products dominate the cost
        cols = members[field.even[members]]
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
        if math.isfinite(offset):
            # w <= c0 + o + c1 u + c2 v  <=>  (-c1, -c2, 1) . x <= c0 + o
            new_pts = clip_halfspace(pts, hull, np.array([-coef[1], -coef[2], 1.0]),
                                      coef[0] + offset)
            # a plane below the whole tile would leave a flat piece: keep the hull then
            if len(new_pts) >= 4 and _max(new_pts[:, 2]) > _MIN_HEIGHT:
                hull_points, pts = pts, new_pts
                top = np.minimum(top, plane + offset)
                # shortfall measured across the plane's slope, like a distance
                tilt = np.sqrt(1.0 + coef[1] ** 2 + coef[2] ** 2)
                shortfall = float(_max(h[solid] - np.maximum(top[solid], 0.0))) / tilt
    hit = top > 0
    intrusion = float(_max(field.distance(cols[hit], top[hit]))) if hit.any() else 0.0
    error = max(intrusion, _INTRUSION_WEIGHT * shortfall)
    return _Tile(members, pts, error if error > _EXACT else 0.0, hull_points, hull)


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
        halves = best_cut(field.h_flat, field.r, tile.members)
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
    g = geometry_config(cfg)
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
    finger's local frame: at most max_pieces tiles cut at 0, 45, 90 or 135 degrees, each the hull
    of its columns from the mount (w = 0) up to the height map.  cover=False (default) also cuts
    each hull by the tile's best-fit plane, offset so that it reaches into the empty space 0.8
    times as far as it falls short of the solid (over a bowl, about half the plain hull's
    intrusion); cover=True keeps the plain hulls, which contain the whole (undercut-filled) solid.
    Tiles are split where the error is worst, along the cut after which planes fit both halves
    best.  Raises VolumeError for an invalid or empty volume."""
    g = geometry_config(cfg)
    k = max_pieces or g.finger_hulls
    v = max_vertices or g.hull_vertices
    height = finger_height_map(finger_tsdf, g)
    return pack_pieces([tile.vertices(v) for tile in _tile_height_map(height, g, k, cover)], k, v)


_memo: OrderedDict[tuple, Hulls] = OrderedDict()
_memo_lock = threading.Lock()


def remembered_finger_hulls(finger_tsdf, cfg=None) -> Hulls:
    """``finger_hulls(finger_tsdf, cfg)`` with its default settings, made once per distinct
    finger volume and geometry and kept for the last ``_REMEMBERED`` of them: batches repeat
    fingers (the WSG50 pads beside every object, imprints scored under several settings), whose
    pieces cost 30-90 ms each.  The arrays are shared between callers and made read-only.
    Thread-safe; two threads that miss on the same finger at once both compute it."""
    g = geometry_config(cfg)
    arr = np.ascontiguousarray(finger_tsdf)
    key = (hashlib.blake2b(arr.view(np.uint8).reshape(-1), digest_size=16).digest(),
           arr.dtype.str, arr.shape, g)
    with _memo_lock:
        hit = _memo.get(key)
        if hit is not None:
            _memo.move_to_end(key)
            return hit
    hulls = finger_hulls(arr, g)
    hulls.vertices.setflags(write=False)
    hulls.counts.setflags(write=False)
    with _memo_lock:
        _memo[key] = hulls
        while len(_memo) > _REMEMBERED:
            _memo.popitem(last=False)
    return hulls
