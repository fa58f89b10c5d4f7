"""Convex pieces as fixed-size arrays: the collision geometry's container and its measures.

Every shape enters the simulator as a :class:`Hulls`: ``[K, V, 3]`` vertices (metres, the volume's
local frame, config.py) and ``[K]`` vertex counts.  K and V are fixed per layout, so many shapes
stack into one array that a batched simulator maps over (``stack_hulls``).

Pieces are made in two ways, because fingers and objects differ in how often they are made:
``finger_hulls`` (tiles of a finger's height map, tens of milliseconds: thousands per cycle) and
``object_hulls`` (coacd once per object, cached on disk; ``hull_pool`` runs it in worker
processes).  ``hull_fit`` measures any shape's hulls against its volume: IoU, how far the hulls
reach into the shape's empty space (intrusion) and how deep solid is left outside them
(shortfall).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.config import geometry_config
from f2f_jax.errors import DecompositionError
from f2f_jax.geometry.tsdf import check_tsdf

log = logging.getLogger(__name__)

_POINT_CHUNK = 4_000_000  # point-facet pairs per block in points_in_hulls (32 MB of float64)

try:  # the qhull run inside scipy's ConvexHull, without the area and volume pass it adds
    from scipy.spatial._qhull import _Qhull
except ImportError:  # pragma: no cover - another scipy layout: ConvexHull itself
    _Qhull = None


class QuickHull:
    """The parts of ``scipy.spatial.ConvexHull(points)`` that pieces use: simplices, neighbors,
    equations and vertices, from the same qhull run (options "Qt"), so the same arrays to the bit,
    about 20% sooner (no area and volume).  Raises QhullError as ConvexHull does."""

    __slots__ = ("_vertices", "equations", "neighbors", "simplices")

    def __init__(self, points: np.ndarray):
        if _Qhull is None:
            hull = ConvexHull(points)
            self.simplices, self.neighbors, self.equations = (hull.simplices, hull.neighbors,
                                                              hull.equations)
        else:
            qhull = _Qhull(b"i", np.ascontiguousarray(points, dtype=np.double), b"",
                           required_options=b"Qt")
            try:
                self.simplices, self.neighbors, self.equations = qhull.get_simplex_facet_array()[:3]
            finally:
                qhull.close()
        self._vertices = None

    @property
    def vertices(self) -> np.ndarray:
        """Indices of the hull's vertices, in input order (as ConvexHull.vertices)."""
        if self._vertices is None:
            self._vertices = np.unique(self.simplices)
        return self._vertices


def _check_quick_hull() -> None:
    """Fall back to ConvexHull when the private qhull class does not behave as expected."""
    global _Qhull
    if _Qhull is None:
        return
    pts = np.random.default_rng(0).random((40, 3))
    try:
        quick, full = QuickHull(pts), ConvexHull(pts)
        same = all(np.array_equal(getattr(quick, k), getattr(full, k))
                   for k in ("simplices", "neighbors", "equations", "vertices"))
    except Exception:  # noqa: BLE001 - any failure of the private API means: do not use it
        same = False
    if not same:
        _Qhull = None


_check_quick_hull()

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
    return reduce_with_error(points, max_vertices)[0]


def reduce_with_error(points, max_vertices: int) -> tuple[np.ndarray, float]:
    """reduce_vertices and how far (m) the dropped vertices lie outside the reduced hull."""
    if max_vertices < 4:
        raise ValueError(f"max_vertices must be >= 4 (a tetrahedron), got {max_vertices}")
    return reduce_hull(convex_vertices(np.asarray(points, dtype=np.float64)), max_vertices)


def reduce_hull(verts: np.ndarray, max_vertices: int) -> tuple[np.ndarray, float]:
    """reduce_with_error for points that are all hull vertices already (convex_vertices')."""
    if len(verts) <= max_vertices:
        return verts, 0.0
    chosen = np.zeros(len(verts), bool)
    chosen[_spanning_tetrahedron(verts)] = True
    while True:
        eq = QuickHull(verts[chosen]).equations
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


def convex_vertices(pts: np.ndarray) -> np.ndarray:
    if len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise DecompositionError(f"a convex piece needs >= 4 finite points, got {len(pts)}")
    try:
        hull = QuickHull(pts)
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
    return pack_pieces([reduce_vertices(p, max_vertices) for p in pieces], max_pieces, max_vertices)


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


def pack_pieces(pieces: list[np.ndarray], max_pieces: int, max_vertices: int) -> Hulls:
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
    g = geometry_config(cfg)
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


def clip_halfspace(points: np.ndarray, hull: ConvexHull, normal: np.ndarray,
                   offset: float) -> np.ndarray:
    """Vertices of the hull of ``points`` cut by the half-space normal . x <= offset: the hull
    vertices inside it and the points where hull edges cross its plane.  [P', 3]."""
    side = points[:, 0] * normal[0] + points[:, 1] * normal[1] + points[:, 2] * normal[2] - offset
    # each edge once: the edge opposite vertex i of facet f is shared with neighbour i of f
    tri, nbr = hull.simplices, hull.neighbors
    own = (np.arange(len(tri))[:, None] < nbr).T  # [3, F]: edges by i, then by facet
    a, b = tri[:, [1, 2, 0]].T[own], tri[:, [2, 0, 1]].T[own]
    pos = side > 0
    cross = pos[a] != pos[b]
    a, b = a[cross], b[cross]
    sa = side[a]
    t = sa / (sa - side[b])
    inside = hull.vertices[side[hull.vertices] <= 0]
    pa = points[a]
    return np.concatenate([points[inside], pa + t[:, None] * (points[b] - pa)])
