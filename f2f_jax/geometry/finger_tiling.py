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

import hashlib
import heapq
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from f2f_jax.config import GeometryConfig, geometry_config
from f2f_jax.errors import DecompositionError
from f2f_jax.geometry.hulls import Hulls, clip_halfspace, pack_pieces, reduce_vertices
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
# Directions of the cut lines in the (iu, iv) plane.  Steps in a turned object's imprint run at
# any angle; cuts along them separate a wall from the floor beside it in one piece each.
_CUT_ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)
_CUT_COS = np.cos(np.radians(_CUT_ANGLES_DEG))[:, None]
_CUT_SIN = np.sin(np.radians(_CUT_ANGLES_DEG))[:, None]
_MIN_SIDE = 0.5  # each side of a cut keeps >= 0.5 sqrt(n) of the tile's n columns
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
            new_pts = clip_halfspace(pts, hull, np.array([-coef[1], -coef[2], 1.0]),
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


def _rss(sums: np.ndarray) -> np.ndarray:
    """Residual sums of squares of least-squares planes from their normal equations, batched:
    sums [10, ...] as ``_normal_terms`` lays them out -> sq - rhs . gram^-1 rhs.  Closed-form
    3x3 inverse (adjugate): thousands of tiny solves, no LAPACK call overhead."""
    a, b, c, d, e, f = sums[:6]
    d, f = d + _RIDGE, f + _RIDGE
    # cofactors of the symmetric matrix [[a b c] [b d e] [c e f]]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    x, y, z, sq = sums[6:]
    quad = (A * x * x + D * y * y + F * z * z + 2 * (B * x * y + C * x * z + E * y * z))
    return sq - quad / np.where(np.abs(det) > 1e-300, det, np.inf)


def _normal_terms(x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Per column, the terms whose sums are the normal equations of a plane fit: x [3, n]
    (1, u, v), h [n] -> [10, n]: the gram's upper triangle x0x0 x0x1 x0x2 x1x1 x1x2 x2x2, then
    x0h x1h x2h, then h h."""
    terms = np.empty((10, x.shape[1]))
    for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        np.multiply(x[i], x[j], out=terms[k])
    np.multiply(x, h, out=terms[6:9])
    np.multiply(h, h, out=terms[9])
    return terms


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
    gram = np.einsum("ni,nj->ij", x, x)
    rhs = np.einsum("ni,n->i", x, h)
    total = np.array([gram[0, 0], gram[0, 1], gram[0, 2], gram[1, 1], gram[1, 2], gram[2, 2],
                      rhs[0], rhs[1], rhs[2], np.sum(h * h)])
    terms = _normal_terms(x.T, h)
    min_side = max(1.0, _MIN_SIDE * np.sqrt(n))
    # every direction at once: positions along its normal, the columns in that order, and the
    # normal equations' prefix sums down that order
    t = _CUT_COS * iu + _CUT_SIN * iv  # [directions, n]
    orders = np.argsort(t, axis=1, kind="stable")
    ts = np.take_along_axis(t, orders, axis=1)
    # a cut before sorted position q + 1 wherever the position steps; no slivers: a cut that
    # shaves a corner column off lowers the squares a lot (an empty corner counts as height 0)
    # but not the worst error
    q = np.arange(1, n)
    ok = (np.diff(ts, axis=1) > 1e-9) & (q >= min_side) & (n - q >= min_side)
    direction, q = np.nonzero(ok)
    if len(q) == 0:
        return None
    prefix = np.cumsum(terms[:, orders], axis=2)  # [10, directions, n]
    before = prefix[:, direction, q]  # [10, cuts]
    cost = _rss(before) + _rss(total[:, None] - before)
    cuts = q + 1
    # prefer cuts near the middle among near-equals: balanced tiles shrink errors fastest
    first = np.ones(len(q), bool)
    first[1:] = direction[1:] != direction[:-1]
    starts = np.flatnonzero(first)
    scale = np.maximum.reduceat(np.abs(cost), starts)[np.cumsum(first) - 1]
    cost = cost + 1e-9 * (1.0 + scale) * np.abs(cuts - n / 2) / n
    j = int(np.argmin(cost))  # the first minimum: earlier directions win ties
    order, p = orders[direction[j]], cuts[j]
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
    pieces = []
    for tile in _tile_height_map(height, g, k, cover):
        try:
            pieces.append(reduce_vertices(tile.points, v))
        except DecompositionError:
            if tile.hull_points is None:
                raise
            pieces.append(reduce_vertices(tile.hull_points, v))  # a clip left a sliver
    return pack_pieces(pieces, k, v)


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
