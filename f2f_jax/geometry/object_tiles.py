"""Object volumes -> convex pieces in milliseconds: hulls over tiles of the two-sided depth map.

coacd (``coacd_pieces.object_hulls``) costs 13-30 s per non-convex object: fine for a fixed set cached on
disk, not for thousands of training objects or a user's new mesh at design time.  The fingers
close along world x, and a finger is itself a height map along x (``finger_tiling.finger_hulls``), so
what a finger can touch of an object is, line by line along x, where the object begins
(``x_min``) and where it ends (``x_max``).  This module tiles that two-sided depth map over the
(y, z) plane, as the fingers' height maps are tiled over theirs: a tile's piece is the convex
hull of its columns from ``x_min`` to ``x_max``; the tile whose piece misfits most is cut in
two (straight across y or z, at the position after which the worse half fits best) until K
pieces or every piece is within half a voxel of the map.

What this leaves out, by design: hollows enclosed along x (a cup's inside, a tray's well, the
gap between the arms of a U that opens along y) are filled, since no finger closing along x
reaches them; they shift the centre of mass a little (the mass stays ``SimConfig.object_mass``).
When the object is turned for the robustness trials (up to 30 degrees) a filled hollow can be
met at a slant: ``benchmarks/sim_agreement.py`` measures what that costs against coacd.
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.errors import DecompositionError
from f2f_jax.geometry.hulls import (
    Hulls,
    convex_vertices,
    geometry_config,
    pack_pieces,
    reduce_with_error,
)
from f2f_jax.geometry.tsdf import check_tsdf

_TOLERANCE_VOXELS = 0.5  # a piece within this of the depth map is not cut further
_CUT_POSITIONS = 4  # candidate cut positions per axis, spread over the tile
_JUDGE_STRIDE = 3  # misfits are judged on every third column along each axis


def depth_map(obj_tsdf, cfg=None) -> tuple[np.ndarray, np.ndarray]:
    """Where an object begins and ends along x on each line of voxel centres (iy, iz).

    Returns (x_min, x_max): [R, R] float64 metres in the object's frame, the zero crossings
    before the first and after the last solid voxel of each line (linear between voxel
    centres; the cube's faces count as empty); NaN on lines without solid.
    """
    g = geometry_config(cfg)
    arr = check_tsdf(obj_tsdf, "object", g).astype(np.float64)
    r = g.resolution
    solid = arr < 0
    occupied = solid.any(axis=0)
    first = np.argmax(solid, axis=0)  # [R, R] index along x
    last = r - 1 - np.argmax(solid[::-1], axis=0)
    padded = np.concatenate([np.ones((1, r, r)), arr, np.ones((1, r, r))], axis=0)
    iy, iz = np.indices((r, r))
    inside_lo, outside_lo = padded[first + 1, iy, iz], padded[first, iy, iz]
    inside_hi, outside_hi = padded[last + 1, iy, iz], padded[last + 2, iy, iz]
    frac_lo = np.clip(inside_lo / np.minimum(inside_lo - outside_lo, -1e-9), 0.0, 1.0)
    frac_hi = np.clip(inside_hi / np.minimum(inside_hi - outside_hi, -1e-9), 0.0, 1.0)
    x0 = -g.cube_size / 2
    x_min = x0 + (first + 0.5 - frac_lo) * g.voxel_size
    x_max = x0 + (last + 0.5 + frac_hi) * g.voxel_size
    return np.where(occupied, x_min, np.nan), np.where(occupied, x_max, np.nan)


class _Map:
    """The depth map, its tiles' hull points and the misfit of a tile's hull."""

    def __init__(self, x_min: np.ndarray, x_max: np.ndarray, g):
        self.x_min, self.x_max = x_min, x_max
        edges = np.arange(x_min.shape[0] + 1) * g.voxel_size
        self.corner_y, self.corner_z = edges - g.cube_size / 2, edges
        centres = (np.arange(x_min.shape[0]) + 0.5) * g.voxel_size
        self.line_y, self.line_z = centres - g.cube_size / 2, centres

    def points(self, box, stride: int = 1) -> np.ndarray | None:
        """Hull points of tile box = (y0, y1, z0, z1) (columns [y0, y1) x [z0, z1)): the corners
        of its solid columns at x_min and x_max; every stride-th corner (plus the last) when
        judging candidate cuts.  None for a tile without solid."""
        y0, y1, z0, z1 = box
        ci = np.unique(np.r_[np.arange(y0, y1 + 1, stride), y1])
        cj = np.unique(np.r_[np.arange(z0, z1 + 1, stride), z1])
        lo = self._corners(self.x_min, box, np.inf, ci, cj, np.minimum)
        hi = self._corners(self.x_max, box, -np.inf, ci, cj, np.maximum)
        ii, jj = np.nonzero(np.isfinite(lo))
        if len(ii) == 0:
            return None
        y, z = self.corner_y[ci[ii]], self.corner_z[cj[jj]]
        return np.concatenate([np.stack([lo[ii, jj], y, z], 1), np.stack([hi[ii, jj], y, z], 1)])

    @staticmethod
    def _corners(src, box, fill, ci, cj, op):
        """Depths at a tile's footprint corners, sampled at corner rows ci and columns cj: a
        corner shared by several of the tile's solid columns takes the outermost of their depths
        (op: np.minimum for x_min, np.maximum for x_max); columns outside the tile do not count."""
        y0, y1, z0, z1 = box
        own = np.where(np.isfinite(src[y0:y1, z0:z1]), src[y0:y1, z0:z1], fill)
        own = np.pad(own, 1, constant_values=fill)
        block = op(op(own[:-1, :-1], own[1:, :-1]), op(own[:-1, 1:], own[1:, 1:]))
        return block[np.ix_(ci - y0, cj - z0)]

    def misfit(self, box, pts: np.ndarray, stride: int = 1) -> float:
        """Worst misfit (m) of the hull of pts over the tile's lines (every stride-th): how far
        it reaches beyond the object, falls short of it, or covers a line the object misses."""
        try:
            eq = ConvexHull(pts).equations
        except (QhullError, ValueError):
            return np.inf
        y0, y1, z0, z1 = box
        yy, zz = np.meshgrid(self.line_y[y0:y1:stride], self.line_z[z0:z1:stride], indexing="ij")
        lo = self.x_min[y0:y1:stride, z0:z1:stride].ravel()
        hi = self.x_max[y0:y1:stride, z0:z1:stride].ravel()
        lines = np.stack([np.ones(yy.size), yy.ravel(), zz.ravel()])  # [3, L]
        nx = eq[:, 0]
        # facet f bounds x on a line at (y, z): n_x x <= -(d + n_y y + n_z z); as one matrix
        # product per side, x <= a . (1, y, z) (n_x > 0) or x >= a . (1, y, z) (n_x < 0)
        coef = -eq[:, [3, 1, 2]]
        up, down = nx > 1e-12, nx < -1e-12
        upper = (coef[up] / nx[up, None] @ lines).min(0) if up.any() else np.full(yy.size, np.inf)
        lower = ((coef[down] / nx[down, None] @ lines).max(0) if down.any()
                 else np.full(yy.size, -np.inf))
        side = ~(up | down)  # facets parallel to x bound the tile's footprint
        inside = np.all(coef[side] @ lines >= 0, axis=0) if side.any() else True
        hit = inside & (lower <= upper)
        solid = np.isfinite(lo)
        err = np.zeros(len(lo))
        both = hit & solid
        err[both] = np.maximum(np.abs(lo[both] - lower[both]), np.abs(upper[both] - hi[both]))
        err[solid & ~hit] = hi[solid & ~hit] - lo[solid & ~hit]  # a line the hull misses
        empty = hit & ~solid
        err[empty] = upper[empty] - lower[empty]
        return float(err.max()) if len(err) else 0.0


def _shrink(m: _Map, box):
    """The tile cut down to the bounding box of its solid columns, or None without solid."""
    y0, y1, z0, z1 = box
    ii, jj = np.nonzero(np.isfinite(m.x_min[y0:y1, z0:z1]))
    if len(ii) == 0:
        return None
    return y0 + int(ii.min()), y0 + int(ii.max()) + 1, z0 + int(jj.min()), z0 + int(jj.max()) + 1


def _cuts(box):
    """Candidate cuts of a tile: up to _CUT_POSITIONS across y and as many across z."""
    y0, y1, z0, z1 = box
    out = []
    for lo, hi, axis in ((y0, y1, 0), (z0, z1, 1)):
        if hi - lo < 2:
            continue
        for c in np.unique(np.linspace(lo + 1, hi - 1, _CUT_POSITIONS).round().astype(int)):
            out.append(((y0, c, z0, z1), (c, y1, z0, z1)) if axis == 0
                       else ((y0, y1, z0, c), (y0, y1, c, z1)))
    return out


def _judge(m: _Map, box) -> float:
    box = _shrink(m, box)
    if box is None:
        return 0.0
    pts = m.points(box, _JUDGE_STRIDE)
    return 0.0 if pts is None else m.misfit(box, pts, _JUDGE_STRIDE)


def tile_object_hulls(obj_tsdf, cfg=None, *, max_pieces: int | None = None,
                      max_vertices: int | None = None) -> Hulls:
    """Convex pieces of an object volume over tiles of its depth map along x (module docstring).

    obj_tsdf: [R, R, R] object volume, negative inside.  Returns Hulls [max_pieces
    (cfg.object_hulls), max_vertices (cfg.hull_vertices), 3], metres, the object's local frame.
    Raises VolumeError for an invalid or empty volume, DecompositionError when no piece spans
    a volume.
    """
    g = geometry_config(cfg)
    k = max_pieces or g.object_hulls
    v = max_vertices or g.hull_vertices
    m = _Map(*depth_map(obj_tsdf, g), g)
    tolerance = _TOLERANCE_VOXELS * g.voxel_size
    heap: list = []
    done: list = []

    def push(box):
        box = _shrink(m, box)
        if box is not None:
            heapq.heappush(heap, (-_judge(m, box), box))

    push((0, m.x_min.shape[0], 0, m.x_min.shape[1]))
    while heap and len(heap) + len(done) < k:
        neg_err, box = heapq.heappop(heap)
        cuts = _cuts(box)
        if -neg_err <= tolerance or not cuts:
            done.append(box)
            if -neg_err <= tolerance:
                break
            continue
        a, b = min(cuts, key=lambda ab: max(_judge(m, ab[0]), _judge(m, ab[1])))
        push(a)
        push(b)
    done.extend(box for _, box in heap)
    pieces = []
    for box in sorted(done):  # slot order by position
        try:
            # every other corner: on 3 mm chords a 3 cm radius sags by 0.04 mm
            pieces.append(reduce_with_error(convex_vertices(m.points(box, 2)), v)[0])
        except DecompositionError:
            continue  # a tile one column thin and flat: no volume
    if not pieces:
        raise DecompositionError("object: no tile of its depth map spans a volume")
    return pack_pieces(pieces, k, v)
