"""MJX collisions for many convex pieces: one collision function for all piece pairs.

Stock MJX compiles a separate convex-convex function for every pair of distinct meshes (8 object
x 32 finger pieces = 256 functions: tens of minutes to compile).  Here every piece's convex data
is padded to one size (``ConvexSizes``) and the mesh-mesh pairs form a single group whose
collider gathers each pair's data by geom, so one vmapped function serves them all; MJX's
``max_geom_pairs`` broad phase keeps only the closest pairs each step.  The fingers' pairs with
each other are a second such group, with a cap of their own, and
the floor's pairs with every piece a third; ``max_contact_points`` keeps the solver's problem at
the deepest 96 contacts.  This relies on MJX internals of mujoco-mjx 3.17 (pinned):
``collision_driver._geom_groups`` and ``_COLLISION_FUNC``.

Convex data is computed here, not by MJX: ``mjx.put_model`` derives it with trimesh, about 0.5 s
per model; ``convex_data`` takes ~1 ms per piece from the hull's vertices.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import jax
import jax.numpy as jp
import mujoco
import numpy as np
from scipy.spatial import ConvexHull

from f2f_jax.sim.scene import FINGER_BIT

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from mujoco.mjx._src import collision_convex, collision_driver
    from mujoco.mjx._src import math as mjx_math
    from mujoco.mjx._src.collision_types import ConvexInfo, FunctionKey, GeomInfo
    from mujoco.mjx._src.types import ConvexMesh, GeomType

# Model fields that differ between candidates of one layout (found by comparing models of very
# different triples); everything else is shared with the template.
MAX_POLYGON = 12  # vertices kept per merged coplanar face (MJX allows 20)
# Mesh-mesh pairs kept per step by MJX's broad phase (closest bounding spheres first).  A finger
# pressing an object touches it with a few pieces; 16 keeps every pair that can touch in the
# grasps we looked at while bounding the narrow phase's cost.
MAX_GEOM_PAIRS = 16
# Contacts the solver sees per step, the deepest first.  The fingers' pairs with each other
# (16 more pairs, 64 contact slots) would otherwise grow the constraint problem by two thirds;
# 96 is over twice the 17-40 contacts a held grasp has active (plain MuJoCo, RESULTS.md).
MAX_CONTACT_POINTS = 96
# data_ids of the merged collision groups: every object-finger (and object-object) mesh pair,
# every finger-finger mesh pair (its own group, so its broad-phase cap does not crowd out the
# pairs that hold the object), and every plane-mesh pair (the floor: no broad phase)
_MERGED = (-1, -1)
_MERGED_FINGERS = (-2, -2)


# --------------------------------------------------------------------------------------------
# Convex data of one piece, padded to fixed sizes
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ConvexSizes:
    """Padded sizes of every piece's convex data: vertices, faces, face polygon, edges."""

    vertices: int
    faces: int
    polygon: int
    edges: int

    @classmethod
    def for_vertices(cls, v: int) -> "ConvexSizes":
        # Euler: a convex polyhedron of v vertices has at most 2v - 4 faces and 3v - 6 edges.
        return cls(vertices=v, faces=2 * v - 4, polygon=MAX_POLYGON, edges=3 * v - 6)


def _order_polygon(points: np.ndarray, idx: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Vertex indices of a planar convex polygon, counter-clockwise about ``normal``."""
    p = points[idx]
    c = p.mean(0)
    a = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(normal, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    ang = np.arctan2((p - c) @ b, (p - c) @ a)
    return idx[np.argsort(ang)]


def convex_data(vertices: np.ndarray, sizes: ConvexSizes) -> ConvexMesh:
    """MJX convex-mesh data of the hull of ``vertices`` ([n, 3], the mesh's own frame).

    Coplanar hull triangles are merged into polygons (as MJX does); faces, polygon vertices and
    edges are padded by repeating the last entry, which adds no new separating axis.
    Returns numpy arrays: vert [V, 3], face [F, P, 3], face_normal [F, 3], edge [E, 2],
    edge_face_normal [E, 2, 3].
    """
    pts = np.asarray(vertices, np.float64)
    hull = ConvexHull(pts)
    keep = hull.vertices
    remap = -np.ones(len(pts), np.int64)
    remap[keep] = np.arange(len(keep))
    vert = pts[keep]
    # group triangles by plane
    eq = hull.equations
    key = np.round(eq / 1e-6).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    faces, normals = [], []
    for gi in range(group.max() + 1):
        tris = hull.simplices[group.ravel() == gi]
        idx = np.unique(remap[tris.ravel()])
        n = eq[group.ravel() == gi][0, :3]
        poly = _order_polygon(vert, idx, n)
        if len(poly) > sizes.polygon:
            poly = poly[:: len(poly) // sizes.polygon + 1]
        faces.append(poly)
        normals.append(n / np.linalg.norm(n))
    if len(vert) > sizes.vertices or len(faces) > sizes.faces:
        raise ValueError(f"hull of {len(vert)} vertices / {len(faces)} faces exceeds {sizes}")
    # edges: polygon sides shared by two faces
    edge_map: dict[tuple[int, int], list[int]] = {}
    for fi, poly in enumerate(faces):
        for a, b in zip(poly, np.roll(poly, -1)):
            if a != b:
                edge_map.setdefault((min(a, b), max(a, b)), []).append(fi)
    edges = [(k, v[:2]) for k, v in edge_map.items() if len(v) >= 2]
    edge = np.array([k for k, _ in edges], np.int64)
    edge_n = np.array([[normals[v[0]], normals[v[1]]] for _, v in edges])
    face = np.stack([np.pad(p, (0, sizes.polygon - len(p)), mode="edge") for p in faces])
    pad = lambda x, n: np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)])  # noqa: E731
    vert_p = pad(vert, sizes.vertices)
    return ConvexMesh(
        vert=vert_p.astype(np.float32),
        face=pad(vert[face], sizes.faces).astype(np.float32),
        face_normal=pad(np.array(normals), sizes.faces).astype(np.float32),
        edge=pad(edge, sizes.edges).astype(np.int32),
        edge_face_normal=pad(edge_n, sizes.edges).astype(np.float32),
    )


def model_convex(m: mujoco.MjModel, sizes: ConvexSizes) -> list[ConvexMesh]:
    """convex_data of every mesh of a compiled model, in mesh order."""
    out = []
    for i in range(m.nmesh):
        adr, num = m.mesh_vertadr[i], m.mesh_vertnum[i]
        out.append(convex_data(m.mesh_vert[adr: adr + num], sizes))
    return out


# --------------------------------------------------------------------------------------------
# One collision group for every mesh-mesh pair
# --------------------------------------------------------------------------------------------
def _merged_groups(m):
    groups = _STOCK_GEOM_GROUPS(m)
    merged: dict = {}
    finger = (np.asarray(m.geom_contype) & FINGER_BIT) != 0  # object pieces set no contype
    for key, pairs in groups.items():
        if key.types == (GeomType.MESH, GeomType.MESH):
            for pair in pairs:
                ids = _MERGED_FINGERS if finger[pair[0]] and finger[pair[1]] else _MERGED
                merged.setdefault(FunctionKey(key.types, ids, key.condim), []).append(pair)
            continue
        if key.types == (GeomType.PLANE, GeomType.MESH):
            key = FunctionKey(key.types, _MERGED, key.condim)
        merged.setdefault(key, []).extend(pairs)
    return merged


def _convex_info(m, d, g):
    """ConvexInfo of geoms ``g`` [P], each with its own mesh's padded convex data."""
    stacked = jax.tree_util.tree_map(lambda *x: jp.stack(x), *m._impl.mesh_convex)
    c = jax.tree_util.tree_map(lambda x: x[jp.asarray(m.geom_dataid)[g]], stacked)
    return ConvexInfo(d.geom_xpos[g], d.geom_xmat[g], m.geom_size[g], c.vert, c.face,
                      c.face_normal, c.edge, c.edge_face_normal)


def _mesh_mesh(m, d, key, geom):
    """Contacts of many mesh-mesh pairs at once; each pair's convex data gathered by geom."""
    if key.data_ids not in (_MERGED, _MERGED_FINGERS):
        return _STOCK_CONVEX(m, d, key, geom)

    def pair(c1, c2):
        dist, pos, n = collision_convex._convex_convex(c1, c2)
        return dist, pos, jax.vmap(mjx_math.make_frame)(n)

    g1, g2 = geom.T
    dist, pos, frame = jax.vmap(pair)(_convex_info(m, d, g1), _convex_info(m, d, g2))
    return dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3)


def _plane_mesh(m, d, key, geom):
    """Contacts of the floor with many mesh geoms at once (one group, not one per mesh)."""
    if key.data_ids != _MERGED:
        return _STOCK_PLANE_MESH(m, d, key, geom)
    g1, g2 = geom.T
    plane = GeomInfo(d.geom_xpos[g1], d.geom_xmat[g1], m.geom_size[g1])
    dist, pos, frame = jax.vmap(_PLANE_CONVEX)(plane, _convex_info(m, d, g2))
    return dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3)


_mesh_mesh.ncon = 4
_plane_mesh.ncon = 4
_STOCK_GEOM_GROUPS = collision_driver._geom_groups
_STOCK_CONVEX = collision_driver._COLLISION_FUNC[(GeomType.MESH, GeomType.MESH)]
_STOCK_PLANE_MESH = collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.MESH)]
# The stock entry wraps MJX's plane-convex function for one shared mesh; the function itself is
# the wrapper's closure (mujoco-mjx 3.17), vmapped above over per-geom convex data.
_PLANE_CONVEX = next(c.cell_contents for c in _STOCK_PLANE_MESH.__closure__
                     if getattr(c.cell_contents, "__name__", "") == "plane_convex")
assert _STOCK_PLANE_MESH.ncon == _plane_mesh.ncon


class merged_mesh_collisions:
    """Context manager: MJX groups all mesh-mesh pairs into one collision function while
    models are put and programs traced (the grouping is read at trace time only)."""

    def __enter__(self):
        collision_driver._geom_groups = _merged_groups
        collision_driver._COLLISION_FUNC[(GeomType.MESH, GeomType.MESH)] = _mesh_mesh
        collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.MESH)] = _plane_mesh
        return self

    def __exit__(self, *exc):
        collision_driver._geom_groups = _STOCK_GEOM_GROUPS
        collision_driver._COLLISION_FUNC[(GeomType.MESH, GeomType.MESH)] = _STOCK_CONVEX
        collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.MESH)] = _STOCK_PLANE_MESH
        return False
