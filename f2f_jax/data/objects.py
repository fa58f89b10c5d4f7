"""A seeded procedural set of graspable objects, so a run needs no download.

Every object is an implicit signed distance function (negative inside) built from primitives with
min / max (union, intersection, difference), sampled on a grid and meshed by marching cubes, so
hollows (cups, bowls, trays, tubes) and holes (mug handles, nuts) come for free and every mesh is
a closed surface.

Shapes are designed in dimensionless "design units" inside a box of half extents up to ~1, posed
(sometimes laid on a side, always turned about z), then scaled so the largest extent is
``OBJECT_SIZE`` (6 cm, the shape cube).  ``mesh_to_tsdf`` later stretches each axis to fill the
cube; since every axis then grows by at least ``(cube - 2 voxels) / largest extent`` (0.95), a
part that is ``MIN_THICKNESS`` thick here stays thicker than 4 mm in the volume (2.7 voxels), so
cup walls, handles and legs survive voxelisation.

Object ``i`` of a seed depends only on ``(seed, i)``: ``builtin_objects(10)[:5]`` equals
``builtin_objects(5)``.  Families are dealt in shuffled rounds, so any ``len(FAMILIES)``
consecutive objects starting at a multiple of it hold every family once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh
from skimage import measure

OBJECT_SIZE = 0.06  # m, largest extent of a built-in object (the shape cube's side)
MIN_THICKNESS = 0.0045  # m, thinnest wall / rod / plate at OBJECT_SIZE (4.3 mm after normalising)
_GRID_CELLS = 56  # marching-cubes cells along the largest axis (about 1.1 mm at 6 cm)
_SIDE_POSE_P = 0.3  # share of objects laid on a side before turning about z
_MARGIN = 0.08  # design units around the posed bounding box (smooth unions bulge a little)

Sdf = Callable[[np.ndarray], np.ndarray]  # points [N, 3] (design units) -> signed distance [N]


# ----------------------------------------------------------------------------------------------
# Signed distance primitives.  Points are [N, 3]; results [N], negative inside.  Some are exact,
# some (ellipsoid, frustum) only bound the distance; marching cubes needs just the zero level.
# ----------------------------------------------------------------------------------------------
def _length(v, axis=-1):
    # sqrt of a sum, not np.linalg.norm: about 5x faster on [N, 3] arrays
    return np.sqrt(np.sum(v * v, axis=axis))


def _dot(p, v):
    """p [N, 3] . v [3] without BLAS, whose threads stall on a busy 2-core machine."""
    return p[:, 0] * v[0] + p[:, 1] * v[1] + p[:, 2] * v[2]


def _sphere(p, centre, r):
    return _length(p - centre, axis=-1) - r


def _ellipsoid(p, centre, radii):
    radii = np.asarray(radii, float)
    return (_length((p - centre) / radii, axis=-1) - 1.0) * radii.min()


def _box(p, lo, hi, rounding=0.0):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 - rounding
    q = np.abs(p - centre) - half
    return _length(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - rounding


def _cylinder(p, centre, r, z_lo, z_hi, axis=2):
    """Solid cylinder of radius r around the line through ``centre`` along ``axis``, spanning
    [z_lo, z_hi] along that axis (absolute coordinates)."""
    others = [a for a in range(3) if a != axis]
    radial = _length(p[:, others] - np.asarray(centre, float)[others], axis=-1) - r
    mid, half = (z_lo + z_hi) / 2, (z_hi - z_lo) / 2
    along = np.abs(p[:, axis] - mid) - half
    d = np.stack([radial, along], -1)
    return _length(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(-1), 0.0)


def _frustum(p, r_lo, r_hi, z_lo, z_hi):
    """Truncated cone around z: radius r_lo at z_lo to r_hi at z_hi."""
    slope = (r_hi - r_lo) / (z_hi - z_lo)
    r_at = r_lo + slope * (np.clip(p[:, 2], z_lo, z_hi) - z_lo)
    side = (_length(p[:, :2], axis=-1) - r_at) / np.sqrt(1 + slope**2)
    along = np.abs(p[:, 2] - (z_lo + z_hi) / 2) - (z_hi - z_lo) / 2
    return np.maximum(side, along)


def _capsule(p, a, b, r):
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(_dot(p - a, ab) / float(ab @ ab), 0.0, 1.0)
    return _length(p - (a + t[:, None] * ab), axis=-1) - r


def _torus(p, centre, major, minor, axis=2):
    """Torus around ``axis`` through ``centre``."""
    q = p - np.asarray(centre, float)
    others = [a for a in range(3) if a != axis]
    ring = _length(q[:, others], axis=-1) - major
    return np.sqrt(ring**2 + q[:, axis] ** 2) - minor


def _hex_prism(p, apothem, z_lo, z_hi):
    angles = np.deg2rad([0.0, 60.0, 120.0])
    side = np.maximum.reduce([np.abs(p[:, 0] * np.cos(t) + p[:, 1] * np.sin(t)) for t in angles]) - apothem
    along = np.abs(p[:, 2] - (z_lo + z_hi) / 2) - (z_hi - z_lo) / 2
    return np.maximum(side, along)


def _union(*ds):
    return np.minimum.reduce(ds)


def _intersect(*ds):
    return np.maximum.reduce(ds)


def _subtract(a, b):
    return np.maximum(a, -b)


def _smooth_union(a, b, k):
    """Union with a fillet of about k design units (polynomial smooth minimum)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


# ----------------------------------------------------------------------------------------------
# Families.  Each takes (rng, wall) and returns a _Design whose bounding box is centred on the
# origin with half extents ``half``; ``wall(half)`` is the thinnest part allowed for that box in
# this pose, in design units, and ``thin`` is the thinnest part actually built.
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Design:
    sdf: Sdf
    half: tuple[float, float, float]
    thin: float


def _box_family(rng, wall):
    a, b, c = rng.uniform(0.35, 1.0, 3)
    rounding = rng.uniform(0.0, 0.4) * min(a, b, c)
    lo, hi = -np.array([a, b, c]), np.array([a, b, c])
    return _Design(lambda p: _box(p, lo, hi, rounding), (a, b, c), 2 * min(a, b, c))


def _cylinder_family(rng, wall):
    r, h = rng.uniform(0.3, 0.9), rng.uniform(0.25, 1.0)
    if rng.random() < 0.5:  # upright can
        return _Design(lambda p: _cylinder(p, (0, 0, 0), r, -h, h, 2), (r, r, h), 2 * min(r, h))
    return _Design(lambda p: _cylinder(p, (0, 0, 0), r, -h, h, 0), (h, r, r), 2 * min(r, h))


def _ellipsoid_family(rng, wall):
    radii = rng.uniform(0.4, 1.0, 3)
    return _Design(lambda p: _ellipsoid(p, 0.0, radii), tuple(radii), 2 * radii.min())


def _capsule_family(rng, wall):
    length, r = rng.uniform(0.3, 0.8), rng.uniform(0.25, 0.6)
    a, b = np.array([-length, 0, 0]), np.array([length, 0, 0])
    return _Design(lambda p: _capsule(p, a, b, r), (length + r, r, r), 2 * r)


def _torus_family(rng, wall):
    outer = rng.uniform(0.55, 1.0)
    minor = rng.uniform(0.15, 0.35) * outer
    axis = 1 if rng.random() < 0.5 else 2  # a standing ring or one lying flat
    half = [outer, outer, outer]
    half[axis] = minor
    minor = max(minor, 0.55 * wall(tuple(half)))
    half[axis] = minor
    major = outer - minor
    return _Design(lambda p: _torus(p, 0.0, major, minor, axis=axis), tuple(half), 2 * minor)


def _profile_thickness(rng, wall, half, fraction_hi):
    w = wall(half)
    return max(w, rng.uniform(w, max(w, fraction_hi)))


def _l_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    t1 = _profile_thickness(rng, wall, (a, b, c), 0.7 * c)
    t2 = _profile_thickness(rng, wall, (a, b, c), 0.7 * a)

    def sdf(p):
        foot = _box(p, (-a, -b, -c), (a, b, -c + t1))
        post = _box(p, (a - t2, -b, -c), (a, b, c))
        return _union(foot, post)

    return _Design(sdf, (a, b, c), min(t1, t2, 2 * b))


def _t_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    t1 = _profile_thickness(rng, wall, (a, b, c), 0.6 * c)
    t2 = _profile_thickness(rng, wall, (a, b, c), 0.6 * a)

    def sdf(p):
        bar = _box(p, (-a, -b, c - t1), (a, b, c))
        stem = _box(p, (-t2 / 2, -b, -c), (t2 / 2, b, c))
        return _union(bar, stem)

    return _Design(sdf, (a, b, c), min(t1, t2, 2 * b))


def _u_family(rng, wall):
    a, b, c = rng.uniform(0.6, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    w = wall((a, b, c))
    t1 = max(w, rng.uniform(w, 0.5 * c))
    t2 = max(w, rng.uniform(w, 0.35 * a))  # leaves a gap of at least 0.6 a between the arms

    def sdf(p):
        base = _box(p, (-a, -b, -c), (a, b, -c + t1))
        arms = _union(_box(p, (-a, -b, -c), (-a + t2, b, c)), _box(p, (a - t2, -b, -c), (a, b, c)))
        return _union(base, arms)

    return _Design(sdf, (a, b, c), min(t1, t2, 2 * b))


def _cup_family(rng, wall):
    r, c = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    w = wall((r, r, c))
    t = max(w, rng.uniform(0.1, 0.2) * r)
    base = max(w, rng.uniform(0.1, 0.25) * c)

    def sdf(p):
        outer = _cylinder(p, (0, 0, 0), r, -c, c)
        cavity = _cylinder(p, (0, 0, 0), r - t, -c + base, c + 1.0)
        return _subtract(outer, cavity)

    return _Design(sdf, (r, r, c), min(t, base))


def _mug_family(rng, wall):
    a = rng.uniform(0.75, 1.0)  # half extent along x, body plus handle
    r = rng.uniform(0.6, 0.72) * a
    xb = -a + r  # body axis
    b = r
    # The handle's tube radius must be known before c; bound c by 1 for the wall rule.
    w0 = wall((a, b, 1.0))
    tube = max(0.55 * w0, rng.uniform(0.1, 0.15))
    centre = xb + 0.9 * r
    major = a - centre - tube
    c = rng.uniform(max(0.5, major + tube + 0.05), 1.0)
    w = wall((a, b, c))
    t = max(w, rng.uniform(0.1, 0.18) * r)
    base = max(w, rng.uniform(0.1, 0.2) * c)
    handle_z = rng.uniform(-0.15, 0.15) * (c - major - tube)

    def sdf(p):
        body = _subtract(_cylinder(p, (xb, 0, 0), r, -c, c),
                         _cylinder(p, (xb, 0, 0), r - t, -c + base, c + 1.0))
        ring = _torus(p, (centre, 0, handle_z), major, tube, axis=1)
        # keep the handle outside the cavity: only the part beyond the middle of the wall
        handle = np.maximum(ring, (xb + r - t / 2) - p[:, 0])
        return _union(body, handle)

    return _Design(sdf, (a, b, c), min(t, base, 2 * tube))


def _bent_family(rng, wall):
    n_seg = int(rng.integers(2, 4))
    pts = [np.zeros(3)]
    heading = 0.0
    for k in range(n_seg):
        if k:
            heading += np.deg2rad(rng.uniform(45, 120)) * rng.choice([-1, 1])
        step = rng.uniform(0.8, 1.4)
        pts.append(pts[-1] + step * np.array([np.cos(heading), 0.0, np.sin(heading)]))
    pts = np.array(pts)
    pts -= (pts.min(0) + pts.max(0)) / 2
    radius = rng.uniform(0.15, 0.3)
    scale = (2.0 - 2 * radius) / max(np.ptp(pts, 0).max(), 1e-6)
    pts *= scale
    half0 = np.ptp(pts, 0) / 2 + radius
    radius = max(radius, 0.55 * wall(tuple(half0)))
    half = np.ptp(pts, 0) / 2 + radius

    def sdf(p):
        return _union(*[_capsule(p, pts[k], pts[k + 1], radius) for k in range(len(pts) - 1)])

    return _Design(sdf, tuple(half), 2 * radius)


def _dumbbell_family(rng, wall):
    end = rng.uniform(0.3, 0.6)
    length = rng.uniform(0.4, 1.0 - end)  # end < 0.6, so the range is never empty
    half = (length + end, end, end)
    rod = max(0.55 * wall(half), rng.uniform(0.3, 0.6) * end)
    kind = rng.choice(["sphere", "cube", "disc"])
    ends = np.array([[-length, 0, 0], [length, 0, 0]])

    def end_sdf(p, c):
        if kind == "sphere":
            return _sphere(p, c, end)
        if kind == "cube":
            return _box(p, c - end, c + end, 0.1 * end)
        return _cylinder(p, c, end, c[0] - 0.5 * end, c[0] + 0.5 * end, axis=0)

    def sdf(p):
        return _union(end_sdf(p, ends[0]), end_sdf(p, ends[1]), _capsule(p, ends[0], ends[1], rod))

    return _Design(sdf, half, 2 * rod)


def _wedge_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0, 3)
    low = max(wall((a, b, c)), rng.uniform(0.0, 0.8) * c)  # height of the thin end
    # plane through (-a, c) and (a, -c + low) in the xz plane; keep what lies under it
    normal = np.array([2 * c - low, 0.0, 2 * a])
    normal /= _length(normal)
    offset = normal @ np.array([-a, 0.0, c])

    def sdf(p):
        return _intersect(_box(p, (-a, -b, -c), (a, b, c)), _dot(p, normal) - offset)

    return _Design(sdf, (a, b, c), min(low, 2 * b))


def _frustum_family(rng, wall):
    r_lo, c = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    r_hi = max(0.55 * wall((r_lo, r_lo, c)), rng.uniform(0.15, 0.9) * r_lo)
    if rng.random() < 0.3:
        r_lo, r_hi = r_hi, r_lo  # standing on its narrow end
    r = max(r_lo, r_hi)
    return _Design(lambda p: _frustum(p, r_lo, r_hi, -c, c), (r, r, c), 2 * min(r_lo, r_hi, c))


def _bowl_family(rng, wall):
    radius = rng.uniform(0.7, 1.0)
    rim = rng.uniform(-0.25, 0.35) * radius  # rim height above the sphere's centre
    c = (radius + rim) / 2  # half height: the bowl spans [-radius, rim] around the centre
    rim_r = np.sqrt(radius**2 - min(rim, 0.0) ** 2)
    half = (rim_r, rim_r, c)
    t = max(wall(half), rng.uniform(0.1, 0.2) * radius)
    centre = np.array([0.0, 0.0, c - rim])  # puts the bottom at -c and the rim at +c

    def sdf(p):
        shell = _subtract(_sphere(p, centre, radius), _sphere(p, centre, radius - t))
        return np.maximum(shell, p[:, 2] - c)

    return _Design(sdf, half, t)


def _cross_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0), rng.uniform(0.2, 0.6)
    w = wall((a, b, c))
    c = max(c, 0.55 * w)
    w = wall((a, b, c))
    t1, t2 = (max(w, rng.uniform(0.25, 0.5) * s) for s in (b, a))
    shift = rng.uniform(-0.4, 0.4) * (a - t2 / 2)  # a cross or a plus, not always symmetric

    def sdf(p):
        return _union(_box(p, (-a, -t1 / 2, -c), (a, t1 / 2, c)),
                      _box(p, (shift - t2 / 2, -b, -c), (shift + t2 / 2, b, c)))

    return _Design(sdf, (a, b, c), min(t1, t2, 2 * c))


def _bottle_family(rng, wall):
    r, c = rng.uniform(0.35, 0.7), rng.uniform(0.8, 1.0)
    neck_len = rng.uniform(0.25, 0.5) * c
    neck = max(0.55 * wall((r, r, c)), rng.uniform(0.35, 0.6) * r)
    shoulder = rng.uniform(0.05, 0.2)

    def sdf(p):
        body = _cylinder(p, (0, 0, 0), r, -c, c - neck_len)
        top = _cylinder(p, (0, 0, 0), neck, -c, c)
        return _smooth_union(body, top, shoulder)

    return _Design(sdf, (r, r, c), 2 * neck)


def _tray_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.8)
    w = wall((a, b, c))
    t = max(w, rng.uniform(0.08, 0.15) * min(a, b))
    base = max(w, rng.uniform(0.15, 0.35) * c)

    def sdf(p):
        return _subtract(_box(p, (-a, -b, -c), (a, b, c)),
                         _box(p, (-a + t, -b + t, -c + base), (a - t, b - t, c + 1.0)))

    return _Design(sdf, (a, b, c), min(t, base))


def _spool_family(rng, wall):
    radius, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)
    w = wall((radius, radius, c))
    disc = max(w, rng.uniform(0.12, 0.3) * c)
    axle = max(0.55 * w, rng.uniform(0.3, 0.6) * radius)

    def sdf(p):
        return _union(_cylinder(p, (0, 0, 0), radius, -c, -c + disc),
                      _cylinder(p, (0, 0, 0), radius, c - disc, c),
                      _cylinder(p, (0, 0, 0), axle, -c, c))

    return _Design(sdf, (radius, radius, c), min(disc, 2 * axle))


def _nut_family(rng, wall):
    apothem, c = rng.uniform(0.6, 0.9), rng.uniform(0.25, 0.8)
    circum = apothem / np.cos(np.pi / 6)
    half = (circum, apothem, c)
    w = wall(half)
    hole = rng.uniform(0.3, 0.6) * apothem
    hole = min(hole, apothem - w)

    def sdf(p):
        return _subtract(_hex_prism(p, apothem, -c, c), _cylinder(p, (0, 0, 0), hole, -c - 1, c + 1))

    return _Design(sdf, half, min(apothem - hole, 2 * c))


def _stool_family(rng, wall):
    a, b, c = rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0), rng.uniform(0.5, 1.0)
    w = wall((a, b, c))
    top = max(w, rng.uniform(0.15, 0.35) * c)
    leg = max(0.55 * w, rng.uniform(0.1, 0.2) * min(a, b))
    corners = [(sx * (a - leg), sy * (b - leg), 0.0) for sx in (-1, 1) for sy in (-1, 1)]

    def sdf(p):
        legs = [_cylinder(p, k, leg, -c, c - top / 2) for k in corners]
        return _union(_box(p, (-a, -b, c - top), (a, b, c)), *legs)

    return _Design(sdf, (a, b, c), min(top, 2 * leg))


def _tube_family(rng, wall):
    r, h = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    w = wall((h, r, r))
    t = max(w, rng.uniform(0.12, 0.3) * r)

    def sdf(p):  # a pipe section lying along x: a ring seen from the side, open both ends
        return _subtract(_cylinder(p, (0, 0, 0), r, -h, h, 0),
                         _cylinder(p, (0, 0, 0), r - t, -h - 1, h + 1, 0))

    return _Design(sdf, (h, r, r), t)


def _blob_family(rng, wall):
    n = int(rng.integers(3, 6))
    radii = rng.uniform(0.3, 0.55, n)
    centres = [np.zeros(3)]
    for k in range(1, n):  # each ball overlaps an earlier one, so the blob is one piece
        j = int(rng.integers(k))
        direction = rng.normal(size=3)
        direction /= _length(direction)
        reach = rng.uniform(0.3, 0.8) * (radii[j] + radii[k])
        centres.append(centres[j] + reach * direction)
    centres = np.array(centres)
    lo, hi = np.min(centres - radii[:, None], 0), np.max(centres + radii[:, None], 0)
    scale = 2.0 / (hi - lo).max()  # fit the largest extent to 2 design units
    centres = (centres - (lo + hi) / 2) * scale
    radii = radii * scale
    k = rng.uniform(0.1, 0.25)
    half = (hi - lo) * scale / 2

    def sdf(p):
        d = _sphere(p, centres[0], radii[0])
        for c, r in zip(centres[1:], radii[1:]):
            d = _smooth_union(d, _sphere(p, c, r), k)
        return d

    return _Design(sdf, tuple(half), 2 * radii.min())


_FAMILY_BUILDERS = {
    "box": _box_family,
    "cylinder": _cylinder_family,
    "ellipsoid": _ellipsoid_family,
    "capsule": _capsule_family,
    "torus": _torus_family,
    "lshape": _l_family,
    "tshape": _t_family,
    "ushape": _u_family,
    "cup": _cup_family,
    "mug": _mug_family,
    "bent": _bent_family,
    "dumbbell": _dumbbell_family,
    "wedge": _wedge_family,
    "frustum": _frustum_family,
    "bowl": _bowl_family,
    "cross": _cross_family,
    "bottle": _bottle_family,
    "tray": _tray_family,
    "spool": _spool_family,
    "nut": _nut_family,
    "stool": _stool_family,
    "tube": _tube_family,
    "blob": _blob_family,
}
FAMILIES: tuple[str, ...] = tuple(_FAMILY_BUILDERS)
HOLLOW_FAMILIES: tuple[str, ...] = ("cup", "mug", "bowl", "tray", "tube")


# ----------------------------------------------------------------------------------------------
# Posing, meshing, the public generator
# ----------------------------------------------------------------------------------------------
def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_SIDE_ROTATIONS = {
    "upright": np.eye(3),
    "on_x": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # 90 degrees about x
    "on_y": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # 90 degrees about y
    "upside_down": np.diag([1.0, -1.0, -1.0]),
}


def _posed_half(rotation: np.ndarray, half) -> np.ndarray:
    """Half extents [3] of the axis-aligned box around a rotated box of half extents ``half``."""
    return np.abs(rotation) @ np.asarray(half, float)


def _family_of(index: int, seed: int) -> str:
    n = len(FAMILIES)
    order = np.random.default_rng(np.random.SeedSequence([seed, 0xF2F, index // n])).permutation(n)
    return FAMILIES[order[index % n]]


def _mesh_design(sdf: Sdf, rotation: np.ndarray, half, cells: int = _GRID_CELLS) -> trimesh.Trimesh:
    """Marching cubes of a posed design.

    sdf: design-frame signed distance; rotation: [3, 3] design -> world; half: [3] half extents
    of the posed (world) bounding box.  The grid spans [-half - margin, half + margin] in world
    coordinates with cubic cells, ``cells`` along the largest axis.
    """
    lo = -np.asarray(half, float) - _MARGIN
    hi = np.asarray(half, float) + _MARGIN
    h = (hi - lo).max() / cells
    counts = np.ceil((hi - lo) / h).astype(int) + 3
    lo = (lo + hi) / 2 - (counts - 1) * h / 2
    x, y, z = (lo[k] + h * np.arange(counts[k]) for k in range(3))
    # design point d = R^T w for world grid point w = (x, y, z), by broadcasting (no BLAS)
    design_points = (x[:, None, None, None] * rotation[0] + y[None, :, None, None] * rotation[1]
                     + z[None, None, :, None] * rotation[2]).reshape(-1, 3)
    values = sdf(design_points).reshape(*counts)
    border = min(values[[0, -1]].min(), values[:, [0, -1]].min(), values[:, :, [0, -1]].min())
    if border <= 0:  # a design that leaves its declared box is a bug in its family
        raise RuntimeError("procedural shape reaches the border of its sampling grid")
    verts, faces, _, _ = measure.marching_cubes(values, level=0.0, spacing=(h, h, h))
    verts = verts + lo
    tri = verts[faces]
    signed_volume = np.sum(tri[:, 0] * np.cross(tri[:, 1], tri[:, 2])) / 6.0
    if signed_volume < 0:  # outward normals, positive volume
        faces = faces[:, ::-1]
    return trimesh.Trimesh(verts, faces, process=True)


def builtin_object(index: int, seed: int = 0) -> trimesh.Trimesh:
    """Object ``index`` of the built-in set for ``seed`` (see ``builtin_objects``)."""
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    family = _family_of(index, seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    side = "upright"
    if rng.random() < _SIDE_POSE_P:
        side = str(rng.choice(list(_SIDE_ROTATIONS)[1:]))
    yaw = float(rng.uniform(0.0, 2 * np.pi))
    rotation = _rot_z(yaw) @ _SIDE_ROTATIONS[side]  # design -> world

    def wall(half) -> float:
        # Thinnest part (design units) that is MIN_THICKNESS once the posed object is scaled to
        # OBJECT_SIZE: the posed box bounds the largest extent, so this is conservative.
        return 1.02 * MIN_THICKNESS / OBJECT_SIZE * 2 * _posed_half(rotation, half).max()

    design = _FAMILY_BUILDERS[family](rng, wall)
    mesh = _mesh_design(design.sdf, rotation, _posed_half(rotation, design.half))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    scale = OBJECT_SIZE / (hi - lo).max()
    mesh.apply_scale(scale)
    mesh.metadata.update({
        "name": f"builtin/{index:04d}_{family}",
        "family": family,
        "seed": int(seed),
        "index": int(index),
        "pose": side,
        "yaw": yaw,
        "min_thickness_m": float(design.thin * scale),
    })
    return mesh


def builtin_objects(n: int, seed: int = 0) -> list[trimesh.Trimesh]:
    """A seeded procedural set of ``n`` varied, graspable objects.

    Families (``FAMILIES``): boxes, cylinders, ellipsoids, capsules, tori, L/T/U profiles, cups,
    mugs with handles, bent rods, dumbbells, wedges, frusta, bowls, crosses, bottles, trays,
    spools, hex nuts, stools, pipe sections and smooth blobs, each with random proportions, laid
    on a side for ~30% of objects and turned about z at random.

    Returns n closed trimesh.Trimesh in metres: largest extent 6 cm, resting on z = 0, centred in
    x and y.  ``metadata`` holds ``name`` ("builtin/0007_cup"), ``family``, ``pose``, ``yaw`` and
    ``min_thickness_m`` (thinnest designed wall/rod/plate, >= 4.5 mm).  Object i depends only on
    (seed, i).
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    return [builtin_object(i, seed) for i in range(n)]
