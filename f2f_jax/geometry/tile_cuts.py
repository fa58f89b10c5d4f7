"""Where ``finger_tiling`` cuts a tile: the straight cut after which planes fit both halves best.

Kept apart from the tiling loop; every array here is a function of the height map's columns
(c = iu * R + iv, numbered flat) and of one tile's members among them, sorted by c.
"""

from __future__ import annotations

import functools

import numpy as np

# Directions of the cut lines in the (iu, iv) plane.  Steps in a turned object's imprint run at
# any angle; cuts along them separate a wall from the floor beside it in one piece each.
CUT_ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)
_CUT_COS = np.cos(np.radians(CUT_ANGLES_DEG))[:, None]
_CUT_SIN = np.sin(np.radians(CUT_ANGLES_DEG))[:, None]
_MIN_SIDE = 0.5  # each side of a cut keeps >= 0.5 sqrt(n) of the tile's n columns
_RIDGE = 1e-6  # on the slope terms (index units): keeps one-line tiles' planes flat
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the gram's upper triangle


@functools.lru_cache(maxsize=8)
def _direction_orders(r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For an R x R map: column indices as floats (iu, iv), each column's position along every
    direction's normal t [directions, R^2], and all columns sorted by (t, c) per direction.

    A tile's members sorted by c and then stably by t are these orders with the other columns
    left out, so a tile never sorts."""
    iu, iv = (a.ravel().astype(np.float64) for a in np.indices((r, r)))
    t = _CUT_COS * iu + _CUT_SIN * iv
    order = np.argsort(t, axis=1, kind="stable")
    for a in (iu, iv, t, order):
        a.setflags(write=False)
    return iu, iv, t, order


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
    """Per column, the terms whose sums are the normal equations of a plane fit: x [3, ...]
    (1, u, v), h [...] -> [10, ...]: the gram's upper triangle x0x0 x0x1 x0x2 x1x1 x1x2 x2x2,
    then x0h x1h x2h, then h h."""
    terms = np.empty((10,) + x.shape[1:])
    for k, (i, j) in enumerate(_PAIRS):
        np.multiply(x[i], x[j], out=terms[k])
    np.multiply(x, h, out=terms[6:9])
    np.multiply(h, h, out=terms[9])
    return terms


def best_cut(h_flat: np.ndarray, r: int, members: np.ndarray):
    """Split a tile's columns along the straight cut after which planes fit both halves best.

    h_flat: [R^2] the height map; members: the tile's columns, sorted.  For each direction in
    ``CUT_ANGLES_DEG`` the columns are ordered along the direction's normal; every gap between
    distinct positions is a candidate cut.  Cost: the halves' residual sums of squares about their
    least-squares planes (empty columns count as height 0), for all cuts at once from prefix sums
    of the normal equations.  Pieces end up nearly planar, which is what a hull (clipped or not)
    fits; a thin high wall beside a low floor is peeled off in one cut.  Returns the two member
    arrays (sorted), or None for a single column."""
    n = len(members)
    if n < 2:
        return None
    fu, fv, t_all, order_all = _direction_orders(r)
    inside = np.zeros(r * r, bool)
    inside[members] = True
    # every direction at once: the members along its normal (the first direction, iu, keeps
    # their own order), their positions, and the normal equations in that order
    ordered = order_all[inside[order_all]].reshape(len(order_all), n)  # [directions, n]
    ts = np.take_along_axis(t_all, ordered, axis=1)
    iu, iv, h = fu[members], fv[members], h_flat[members]
    mu, mv = iu.mean(), iv.mean()
    x = np.stack([np.ones(n), iu - mu, iv - mv], 1)  # [n, 3]
    total = np.concatenate([np.einsum("ni,nj->ij", x, x).ravel()[[0, 1, 2, 4, 5, 8]],
                            np.einsum("ni,n->i", x, h), [np.sum(h * h)]])
    min_side = max(1.0, _MIN_SIDE * np.sqrt(n))
    # a cut before sorted position q + 1 wherever the position steps; no slivers: a cut that
    # shaves a corner column off lowers the squares a lot (an empty corner counts as height 0)
    # but not the worst error
    q = np.arange(1, n)
    ok = (np.diff(ts, axis=1) > 1e-9) & (q >= min_side) & (n - q >= min_side)
    direction, q = np.nonzero(ok)
    if len(q) == 0:
        return None
    xo = np.empty((3,) + ordered.shape)
    xo[0] = 1.0
    np.subtract(fu[ordered], mu, out=xo[1])
    np.subtract(fv[ordered], mv, out=xo[2])
    terms = _normal_terms(xo, h_flat[ordered])  # [10, directions, n]
    # prefix sums down each order (of the counts: exact, so without summing)
    before = np.empty((10, 2, len(q)))
    before[0, 0] = q + 1
    before[1:, 0] = np.cumsum(terms[1:], axis=2)[:, direction, q]
    np.subtract(total[:, None], before[:, 0], out=before[:, 1])  # after the cut
    rss = _rss(before)
    cost = rss[0] + rss[1]
    cuts = q + 1
    # prefer cuts near the middle among near-equals: balanced tiles shrink errors fastest
    first = np.ones(len(q), bool)
    first[1:] = direction[1:] != direction[:-1]
    starts = np.flatnonzero(first)
    scale = np.maximum.reduceat(np.abs(cost), starts)[np.cumsum(first) - 1]
    cost = cost + 1e-9 * (1.0 + scale) * np.abs(cuts - n / 2) / n
    j = int(np.argmin(cost))  # the first minimum: earlier directions win ties
    line, p = ordered[direction[j]], cuts[j]
    return np.sort(line[:p]), np.sort(line[p:])
