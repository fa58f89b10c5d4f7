"""The fast paths of finger pieces: the same arrays as the plain computations they replace."""

import numpy as np
from scipy.spatial import ConvexHull

from f2f_jax.geometry import tile_cuts
from f2f_jax.geometry.hulls import QuickHull


def test_quick_hull_is_scipys_convex_hull_to_the_bit():
    """Pieces are made with QuickHull; they stay the pieces ConvexHull gives, on grid points with
    many coplanar ones (a tile's corners at their heights and on the mount) as on random ones."""
    rng = np.random.default_rng(5)
    u, v = np.meshgrid(np.arange(7.0), np.arange(5.0), indexing="ij")
    top = np.c_[u.ravel(), v.ravel(), np.round(rng.uniform(1, 3, u.size), 1)]
    grid = np.concatenate([top, top * [1, 1, 0]])
    for pts in (grid, rng.random((60, 3))):
        quick, full = QuickHull(pts), ConvexHull(pts)
        for name in ("simplices", "neighbors", "equations", "vertices"):
            assert np.array_equal(getattr(quick, name), getattr(full, name)), name


def test_cut_orders_are_each_tiles_stable_sort():
    """best_cut reads a tile's columns along each direction from one sort of the whole map."""
    r = 12
    _, _, t, order = tile_cuts._direction_orders(r)
    rng = np.random.default_rng(2)
    for _ in range(20):
        members = np.flatnonzero(rng.random(r * r) < rng.uniform(0.05, 0.9))
        inside = np.zeros(r * r, bool)
        inside[members] = True
        ordered = order[inside[order]].reshape(len(order), -1)
        expected = members[np.argsort(t[:, members], axis=1, kind="stable")]
        assert np.array_equal(ordered, expected)
