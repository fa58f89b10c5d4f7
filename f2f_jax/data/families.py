"""The built-in object families: seeded builders of implicit shapes (``FAMILY_BUILDERS``).

Each builder takes ``(rng, wall)`` and returns a ``FamilyShape`` whose bounding box is centred on
the origin with half extents ``half``; ``wall(half)`` is the thinnest part allowed for that box
in this pose, in design units, and ``thin`` is the thinnest part actually built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from f2f_jax.data.sdf import (
    Sdf,
    box,
    capsule,
    cylinder,
    dot,
    ellipsoid,
    frustum,
    hex_prism,
    intersect,
    length,
    smooth_union,
    sphere,
    subtract,
    torus,
    union,
)


@dataclass(frozen=True)
class FamilyShape:
    """An implicit shape and its box: sdf, half extents (design units), thinnest part built."""

    sdf: Sdf
    half: tuple[float, float, float]
    thin: float


def _box_family(rng, wall):
    a, b, c = rng.uniform(0.35, 1.0, 3)
    rounding = rng.uniform(0.0, 0.4) * min(a, b, c)
    lo, hi = -np.array([a, b, c]), np.array([a, b, c])
    return FamilyShape(lambda p: box(p, lo, hi, rounding), (a, b, c), 2 * min(a, b, c))


def _cylinder_family(rng, wall):
    r, h = rng.uniform(0.3, 0.9), rng.uniform(0.25, 1.0)
    if rng.random() < 0.5:  # upright can
        return FamilyShape(lambda p: cylinder(p, (0, 0, 0), r, -h, h, 2), (r, r, h), 2 * min(r, h))
    return FamilyShape(lambda p: cylinder(p, (0, 0, 0), r, -h, h, 0), (h, r, r), 2 * min(r, h))


def _ellipsoid_family(rng, wall):
    radii = rng.uniform(0.4, 1.0, 3)
    return FamilyShape(lambda p: ellipsoid(p, 0.0, radii), tuple(radii), 2 * radii.min())


def _capsule_family(rng, wall):
    length, r = rng.uniform(0.3, 0.8), rng.uniform(0.25, 0.6)
    a, b = np.array([-length, 0, 0]), np.array([length, 0, 0])
    return FamilyShape(lambda p: capsule(p, a, b, r), (length + r, r, r), 2 * r)


def _torus_family(rng, wall):
    outer = rng.uniform(0.55, 1.0)
    minor = rng.uniform(0.15, 0.35) * outer
    axis = 1 if rng.random() < 0.5 else 2  # a standing ring or one lying flat
    half = [outer, outer, outer]
    half[axis] = minor
    minor = max(minor, 0.55 * wall(tuple(half)))
    half[axis] = minor
    major = outer - minor
    return FamilyShape(lambda p: torus(p, 0.0, major, minor, axis=axis), tuple(half), 2 * minor)


def _profile_thickness(rng, wall, half, fraction_hi):
    w = wall(half)
    return max(w, rng.uniform(w, max(w, fraction_hi)))


def _l_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    t1 = _profile_thickness(rng, wall, (a, b, c), 0.7 * c)
    t2 = _profile_thickness(rng, wall, (a, b, c), 0.7 * a)

    def sdf(p):
        foot = box(p, (-a, -b, -c), (a, b, -c + t1))
        post = box(p, (a - t2, -b, -c), (a, b, c))
        return union(foot, post)

    return FamilyShape(sdf, (a, b, c), min(t1, t2, 2 * b))


def _t_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    t1 = _profile_thickness(rng, wall, (a, b, c), 0.6 * c)
    t2 = _profile_thickness(rng, wall, (a, b, c), 0.6 * a)

    def sdf(p):
        bar = box(p, (-a, -b, c - t1), (a, b, c))
        stem = box(p, (-t2 / 2, -b, -c), (t2 / 2, b, c))
        return union(bar, stem)

    return FamilyShape(sdf, (a, b, c), min(t1, t2, 2 * b))


def _u_family(rng, wall):
    a, b, c = rng.uniform(0.6, 1.0), rng.uniform(0.25, 0.9), rng.uniform(0.5, 1.0)
    w = wall((a, b, c))
    t1 = max(w, rng.uniform(w, 0.5 * c))
    t2 = max(w, rng.uniform(w, 0.35 * a))  # leaves a gap of at least 0.6 a between the arms

    def sdf(p):
        base = box(p, (-a, -b, -c), (a, b, -c + t1))
        arms = union(box(p, (-a, -b, -c), (-a + t2, b, c)), box(p, (a - t2, -b, -c), (a, b, c)))
        return union(base, arms)

    return FamilyShape(sdf, (a, b, c), min(t1, t2, 2 * b))


def _cup_family(rng, wall):
    r, c = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    w = wall((r, r, c))
    t = max(w, rng.uniform(0.1, 0.2) * r)
    base = max(w, rng.uniform(0.1, 0.25) * c)

    def sdf(p):
        outer = cylinder(p, (0, 0, 0), r, -c, c)
        cavity = cylinder(p, (0, 0, 0), r - t, -c + base, c + 1.0)
        return subtract(outer, cavity)

    return FamilyShape(sdf, (r, r, c), min(t, base))


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
        body = subtract(cylinder(p, (xb, 0, 0), r, -c, c),
                         cylinder(p, (xb, 0, 0), r - t, -c + base, c + 1.0))
        ring = torus(p, (centre, 0, handle_z), major, tube, axis=1)
        # keep the handle outside the cavity: only the part beyond the middle of the wall
        handle = np.maximum(ring, (xb + r - t / 2) - p[:, 0])
        return union(body, handle)

    return FamilyShape(sdf, (a, b, c), min(t, base, 2 * tube))


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
        return union(*[capsule(p, pts[k], pts[k + 1], radius) for k in range(len(pts) - 1)])

    return FamilyShape(sdf, tuple(half), 2 * radius)


def _dumbbell_family(rng, wall):
    end = rng.uniform(0.3, 0.6)
    length = rng.uniform(0.4, 1.0 - end)  # end < 0.6, so the range is never empty
    half = (length + end, end, end)
    rod = max(0.55 * wall(half), rng.uniform(0.3, 0.6) * end)
    kind = rng.choice(["sphere", "cube", "disc"])
    ends = np.array([[-length, 0, 0], [length, 0, 0]])

    def end_sdf(p, c):
        if kind == "sphere":
            return sphere(p, c, end)
        if kind == "cube":
            return box(p, c - end, c + end, 0.1 * end)
        return cylinder(p, c, end, c[0] - 0.5 * end, c[0] + 0.5 * end, axis=0)

    def sdf(p):
        return union(end_sdf(p, ends[0]), end_sdf(p, ends[1]), capsule(p, ends[0], ends[1], rod))

    return FamilyShape(sdf, half, 2 * rod)


def _wedge_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0, 3)
    low = max(wall((a, b, c)), rng.uniform(0.0, 0.8) * c)  # height of the thin end
    # plane through (-a, c) and (a, -c + low) in the xz plane; keep what lies under it
    normal = np.array([2 * c - low, 0.0, 2 * a])
    normal /= length(normal)
    offset = normal @ np.array([-a, 0.0, c])

    def sdf(p):
        return intersect(box(p, (-a, -b, -c), (a, b, c)), dot(p, normal) - offset)

    return FamilyShape(sdf, (a, b, c), min(low, 2 * b))


def _frustum_family(rng, wall):
    r_lo, c = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    r_hi = max(0.55 * wall((r_lo, r_lo, c)), rng.uniform(0.15, 0.9) * r_lo)
    if rng.random() < 0.3:
        r_lo, r_hi = r_hi, r_lo  # standing on its narrow end
    r = max(r_lo, r_hi)
    return FamilyShape(lambda p: frustum(p, r_lo, r_hi, -c, c), (r, r, c), 2 * min(r_lo, r_hi, c))


def _bowl_family(rng, wall):
    radius = rng.uniform(0.7, 1.0)
    rim = rng.uniform(-0.25, 0.35) * radius  # rim height above the sphere's centre
    c = (radius + rim) / 2  # half height: the bowl spans [-radius, rim] around the centre
    rim_r = np.sqrt(radius**2 - min(rim, 0.0) ** 2)
    half = (rim_r, rim_r, c)
    t = max(wall(half), rng.uniform(0.1, 0.2) * radius)
    centre = np.array([0.0, 0.0, c - rim])  # puts the bottom at -c and the rim at +c

    def sdf(p):
        shell = subtract(sphere(p, centre, radius), sphere(p, centre, radius - t))
        return np.maximum(shell, p[:, 2] - c)

    return FamilyShape(sdf, half, t)


def _cross_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0), rng.uniform(0.2, 0.6)
    w = wall((a, b, c))
    c = max(c, 0.55 * w)
    w = wall((a, b, c))
    t1, t2 = (max(w, rng.uniform(0.25, 0.5) * s) for s in (b, a))
    shift = rng.uniform(-0.4, 0.4) * (a - t2 / 2)  # a cross or a plus, not always symmetric

    def sdf(p):
        return union(box(p, (-a, -t1 / 2, -c), (a, t1 / 2, c)),
                      box(p, (shift - t2 / 2, -b, -c), (shift + t2 / 2, b, c)))

    return FamilyShape(sdf, (a, b, c), min(t1, t2, 2 * c))


def _bottle_family(rng, wall):
    r, c = rng.uniform(0.35, 0.7), rng.uniform(0.8, 1.0)
    neck_len = rng.uniform(0.25, 0.5) * c
    neck = max(0.55 * wall((r, r, c)), rng.uniform(0.35, 0.6) * r)
    shoulder = rng.uniform(0.05, 0.2)

    def sdf(p):
        body = cylinder(p, (0, 0, 0), r, -c, c - neck_len)
        top = cylinder(p, (0, 0, 0), neck, -c, c)
        return smooth_union(body, top, shoulder)

    return FamilyShape(sdf, (r, r, c), 2 * neck)


def _tray_family(rng, wall):
    a, b, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.8)
    w = wall((a, b, c))
    t = max(w, rng.uniform(0.08, 0.15) * min(a, b))
    base = max(w, rng.uniform(0.15, 0.35) * c)

    def sdf(p):
        return subtract(box(p, (-a, -b, -c), (a, b, c)),
                         box(p, (-a + t, -b + t, -c + base), (a - t, b - t, c + 1.0)))

    return FamilyShape(sdf, (a, b, c), min(t, base))


def _spool_family(rng, wall):
    radius, c = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)
    w = wall((radius, radius, c))
    disc = max(w, rng.uniform(0.12, 0.3) * c)
    axle = max(0.55 * w, rng.uniform(0.3, 0.6) * radius)

    def sdf(p):
        return union(cylinder(p, (0, 0, 0), radius, -c, -c + disc),
                      cylinder(p, (0, 0, 0), radius, c - disc, c),
                      cylinder(p, (0, 0, 0), axle, -c, c))

    return FamilyShape(sdf, (radius, radius, c), min(disc, 2 * axle))


def _nut_family(rng, wall):
    apothem, c = rng.uniform(0.6, 0.9), rng.uniform(0.25, 0.8)
    circum = apothem / np.cos(np.pi / 6)
    half = (circum, apothem, c)
    w = wall(half)
    hole = rng.uniform(0.3, 0.6) * apothem
    hole = min(hole, apothem - w)

    def sdf(p):
        return subtract(hex_prism(p, apothem, -c, c), cylinder(p, (0, 0, 0), hole, -c - 1, c + 1))

    return FamilyShape(sdf, half, min(apothem - hole, 2 * c))


def _stool_family(rng, wall):
    a, b, c = rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0), rng.uniform(0.5, 1.0)
    w = wall((a, b, c))
    top = max(w, rng.uniform(0.15, 0.35) * c)
    leg = max(0.55 * w, rng.uniform(0.1, 0.2) * min(a, b))
    corners = [(sx * (a - leg), sy * (b - leg), 0.0) for sx in (-1, 1) for sy in (-1, 1)]

    def sdf(p):
        legs = [cylinder(p, k, leg, -c, c - top / 2) for k in corners]
        return union(box(p, (-a, -b, c - top), (a, b, c)), *legs)

    return FamilyShape(sdf, (a, b, c), min(top, 2 * leg))


def _tube_family(rng, wall):
    r, h = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    w = wall((h, r, r))
    t = max(w, rng.uniform(0.12, 0.3) * r)

    def sdf(p):  # a pipe section lying along x: a ring seen from the side, open both ends
        return subtract(cylinder(p, (0, 0, 0), r, -h, h, 0),
                         cylinder(p, (0, 0, 0), r - t, -h - 1, h + 1, 0))

    return FamilyShape(sdf, (h, r, r), t)


def _blob_family(rng, wall):
    n = int(rng.integers(3, 6))
    radii = rng.uniform(0.3, 0.55, n)
    centres = [np.zeros(3)]
    for k in range(1, n):  # each ball overlaps an earlier one, so the blob is one piece
        j = int(rng.integers(k))
        direction = rng.normal(size=3)
        direction /= length(direction)
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
        d = sphere(p, centres[0], radii[0])
        for c, r in zip(centres[1:], radii[1:]):
            d = smooth_union(d, sphere(p, c, r), k)
        return d

    return FamilyShape(sdf, tuple(half), 2 * radii.min())


FAMILY_BUILDERS = {
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
FAMILIES: tuple[str, ...] = tuple(FAMILY_BUILDERS)
HOLLOW_FAMILIES: tuple[str, ...] = ("cup", "mug", "bowl", "tray", "tube")
