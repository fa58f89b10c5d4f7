"""Finger volumes: imprint fingers, fingers cut from other shapes, feasibility, placement, export.

Finger volumes use the finger frame of config.py: ``[iu, iv, iw]`` with ``iw = 0`` on the mount
plate and ``w`` pointing at the object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from f2f_jax.config import GeometryConfig, geometry_config, voxel_centres
from f2f_jax.errors import VolumeError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry.tsdf import check_tsdf, marching_cubes_mesh

# Face-connected components only: voxels touching at an edge or a corner do not print as one part.
_CONNECTIVITY = ndimage.generate_binary_structure(3, 1)


def _components(solid: np.ndarray) -> tuple[np.ndarray, int]:
    return ndimage.label(solid, structure=_CONNECTIVITY)


def largest_component(tsdf: np.ndarray) -> np.ndarray:
    """Keep the largest face-connected solid component; other solid voxels become empty.

    tsdf: [R, R, R] float32, negative inside.  Removed voxels keep their distance magnitude with a
    positive sign (at least 1e-3), so the field stays smooth around what remains.
    """
    tsdf = np.asarray(tsdf, dtype=np.float32)
    labels, n = _components(tsdf < 0)
    if n <= 1:
        return tsdf.copy()
    sizes = np.bincount(labels.ravel())[1:]
    keep = labels == (1 + int(np.argmax(sizes)))
    drop = (tsdf < 0) & ~keep
    out = tsdf.copy()
    out[drop] = np.maximum(np.abs(out[drop]), 1e-3)
    return out


def postprocess(lefts: np.ndarray, rights: np.ndarray,
                geometry: GeometryConfig | None = None) -> np.ndarray:
    """Keep each finger's largest component, in place; return feasible [B, K] (both fingers)."""
    b, k = lefts.shape[:2]
    feasible = np.zeros((b, k), bool)
    for i in range(b):
        for j in range(k):
            lefts[i, j] = largest_component(lefts[i, j])
            rights[i, j] = largest_component(rights[i, j])
            feasible[i, j] = is_feasible(lefts[i, j], geometry) and is_feasible(rights[i, j], geometry)
    return feasible


def feasibility_report(finger_tsdf, cfg=None) -> dict:
    """Why a finger is or is not printable and mountable.

    Returns dict(feasible, components, base_fraction (best share of solid voxels among the first
    `feasible_base_planes` planes from the mount), touches_mount).
    """
    g = geometry_config(cfg)
    arr = np.asarray(finger_tsdf)
    r = g.resolution
    if arr.shape != (r, r, r):
        raise VolumeError(f"finger: expected shape ({r}, {r}, {r}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise VolumeError("finger: contains NaN/inf values")
    solid = arr < 0
    _, n = _components(solid)
    plane_share = solid[:, :, : g.feasible_base_planes].mean(axis=(0, 1))
    base_fraction = float(plane_share.max()) if plane_share.size else 0.0
    touches = bool(solid[:, :, 0].any())
    feasible = n == 1 and touches and base_fraction >= g.feasible_base_fraction
    return dict(feasible=bool(feasible), components=int(n), base_fraction=base_fraction,
                touches_mount=touches)


def is_feasible(finger_tsdf, cfg=None) -> bool:
    """A finger can be printed and mounted: one face-connected solid component that touches the
    mount plane, and solid on >= 10% of one of the first 4 planes from the mount (paper, and the
    original code's base-connection rule).  An empty volume is infeasible.
    """
    return feasibility_report(finger_tsdf, cfg)["feasible"]


def _first_surface(obj: np.ndarray, g: GeometryConfig) -> np.ndarray:
    """Sub-voxel index along axis 0 where each ray (iy, iz) coming from -x first meets the object.

    Returns [R, R] float (voxel units, in index coordinates; inf where the ray misses).  The
    crossing is interpolated between the last outside and the first inside sample.
    """
    r = g.resolution
    solid = obj < 0
    hit = solid.any(axis=0)
    k = np.argmax(solid, axis=0)  # first inside index (0 where none)
    iy, iz = np.indices((r, r))
    prev = np.clip(k - 1, 0, r - 1)
    a, b = obj[prev, iy, iz], obj[k, iy, iz]
    frac = np.where((k > 0) & (a > b), a / np.maximum(a - b, 1e-6), 0.5)
    pos = np.where(k > 0, prev + np.clip(frac, 0.0, 1.0), -0.5)
    return np.where(hit, pos, np.inf)


def _imprint_left(obj: np.ndarray, g: GeometryConfig) -> np.ndarray:
    """Left finger (at -x) from the single view of the object seen from -x.

    The view's TSDF is negated: what the view sees as free space in front of the object becomes
    finger, what lies at or behind the first surface stays empty.  The half of the view nearest
    the finger (object x < 0) maps onto w in [3, 6] cm, so the finger tip plane reaches the
    object's mid-plane at full closure; w in [0, 3) cm is the solid base (the original shifted the
    negated view by half the volume, filling with solid).
    """
    r = g.resolution
    half = r // 2
    surface = _first_surface(obj, g)  # [iy, iz], object x index
    iw = np.arange(r, dtype=np.float32)
    x_index = iw - half  # object x index seen at finger plane iw (w = x + 6 cm)
    # Projective distance along the ray, in voxels: negative (finger) in front of the surface.
    dist = x_index[None, None, :] - surface[:, :, None]  # [iy, iz, iw]
    finger = np.clip(dist / g.truncation_voxels, -1.0, 1.0)
    finger = np.where(np.isinf(surface)[:, :, None], -1.0, finger)
    # A finger cannot reach under an object that rests on the floor: rays below the object's
    # lowest voxel row see no object, but they pass under it, not beside it.
    rows = np.nonzero((obj < 0).any(axis=(0, 1)))[0]
    if len(rows):
        finger[:, : rows[0], :] = np.maximum(finger[:, : rows[0], :], 1.0)
    finger[:, :, :half] = -1.0
    # [iy, iz, iw] -> [iu, iv, iw]: u = +y, v = z for the left finger.
    return largest_component(finger.astype(np.float32))


def imprint_fingers(obj_tsdf, cfg=None) -> tuple[np.ndarray, np.ndarray]:
    """Imprint fingers of an object (paper section 3.2 and appendix B.1).

    obj_tsdf: [R, R, R] object volume.  Returns (left, right) finger volumes [R, R, R] float32.
    Each finger is the negated two-view (from -x, from +x) volume of the object, cut at the
    object's mid-plane: using only the views along the closing direction leaves no undercut, so
    the fingers can close around the object.  The right finger is computed as the left finger of
    the object turned 180 degrees about z, which is exactly its frame (config.py).
    """
    g = geometry_config(cfg)
    obj = check_tsdf(obj_tsdf, "object", g)
    left = _imprint_left(obj, g)
    right = _imprint_left(obj[::-1, ::-1, :], g)
    return left, right


def finger_from_shape(shape_tsdf, cfg=None) -> np.ndarray | None:
    """A finger cut from another shape (the paper's 'ShapeNet fingers').

    The largest component of the shape is searched from the mount side (axis 2, index 0) through
    its first third for a plane with >= 10% solid; the volume is chopped there and stretched back
    to R planes.  Returns the finger volume, or None when no such plane exists or the stretched
    finger is not feasible.
    """
    g = geometry_config(cfg)
    vol = largest_component(check_tsdf(shape_tsdf, "shape", g))
    r = g.resolution
    share = (vol < 0).mean(axis=(0, 1))
    candidates = np.nonzero(share[: int(r * g.cut_search_fraction)] >= g.feasible_base_fraction)[0]
    if len(candidates) == 0:
        return None
    cut = int(candidates[0])
    chopped = vol[:, :, cut:]
    stretched = ndimage.zoom(chopped, (1.0, 1.0, r / chopped.shape[2]), order=1, mode="nearest")
    stretched = np.clip(stretched[:, :, :r], -1.0, 1.0).astype(np.float32)
    stretched = largest_component(stretched)
    return stretched if is_feasible(stretched, g) else None


def _box_tsdf(lo: np.ndarray, hi: np.ndarray, g: GeometryConfig) -> np.ndarray:
    """Exact truncated signed distance of an axis-aligned box [lo, hi] (metres, local frame)."""
    points = np.stack(np.meshgrid(*voxel_centres(g), indexing="ij"), -1)
    return np.clip(_box_sdf(points, lo, hi) / g.truncation, -1.0, 1.0).astype(np.float32)


def _box_sdf(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Signed distance (metres) from points [..., 3] to the box [lo, hi]."""
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(points - centre) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def wsg50_fingers(cfg=None, *, width: float = 0.02, depth: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: flat fingertips like the WSG50's standard fingers, as finger volumes.

    A block ``width`` wide (u), the cube's full height (v) less a voxel, reaching ``depth`` from the
    mount (w): a flat pad parallel to the mount plate.  Returns (left, right), identical volumes.
    """
    g = geometry_config(cfg)
    h = g.cube_size / 2 - g.voxel_size
    lo = np.array([-width / 2, -h, -g.voxel_size])  # starts below w = 0: solid on the mount plane
    hi = np.array([width / 2, h, depth])
    finger = _box_tsdf(lo, hi, g)
    return finger, finger.copy()


def finger_from_mesh(mesh: trimesh.Trimesh, cfg=None, *, reach: float = 0.03) -> np.ndarray:
    """A real finger's mesh as a finger volume, seen the way the object sees it.

    mesh: one finger as mounted on a parallel-jaw gripper, in metres, in the convention of
    Schunk's WSG50 finger meshes (``WSG-FMF.stl`` in pybullet_data): the jaw closes along +x (the
    face that meets the object is the mesh's +x side), the finger's length runs along z with its
    tip at the largest z, its width along y (centred on y = 0 in our u).
    Each (u, v) column of the volume takes the mesh's first surface seen from the object (a ray
    along -x) as its height, with the tip one voxel above the cube's floor and the face's foremost
    point at w = ``reach``: like the flat pads of ``wsg50_fingers``, the two faces meet at the
    object's mid-plane when the jaws close fully.  Every column is solid from the mount (w = 0) up
    to its face (the finger stands on a spacer, as a printed finger would, and has no undercut);
    what lies above the cube's height (the mounting end) and columns whose face is more than
    ``reach`` behind the foremost point are outside the volume.
    Returns [R, R, R] float32, a projective TSDF as ``imprint_fingers`` makes.  Raises ValueError
    for a mesh that no column of the volume meets.
    """
    g = geometry_config(cfg)
    r, vox = g.resolution, g.voxel_size
    lo, hi = np.asarray(mesh.bounds, np.float64)
    if not 0 < reach <= g.cube_size:
        raise ValueError(f"reach must be in (0, {g.cube_size}] m, got {reach}")
    c = (np.arange(r) + 0.5) * vox - g.cube_size / 2
    uu, vv = np.meshgrid(c, c, indexing="ij")
    z = hi[2] - (vv + g.cube_size / 2 - vox)  # v = -h (one voxel above the floor) at the tip
    origins = np.stack([np.full(uu.size, hi[0] + 0.01), uu.ravel(), z.ravel()], 1)
    directions = np.tile([-1.0, 0.0, 0.0], (uu.size, 1))
    hits, rays, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    if len(rays) == 0:
        raise ValueError("finger mesh: no column of the finger volume meets it (check its axes)")
    face = np.full(uu.size, -np.inf)
    face[rays] = hits[:, 0]
    height = (face - hi[0] + reach).reshape(r, r)  # w of each column's face; -inf: empty column
    w = (np.arange(r) + 0.5) * vox
    tsdf = np.clip((w[None, None, :] - height[:, :, None]) / g.truncation, -1.0, 1.0)
    return largest_component(tsdf.astype(np.float32))


def finger_extent(finger_tsdf, cfg=None) -> float:
    """How far the finger reaches from its mount plane (metres): the largest w of any solid voxel,
    to its far face."""
    g = geometry_config(cfg)
    solid = np.asarray(finger_tsdf) < 0
    planes = np.nonzero(solid.any(axis=(0, 1)))[0]
    if len(planes) == 0:
        return 0.0
    return float((planes[-1] + 1) * g.voxel_size)


def finger_pose(side: str, mount_x: float, cfg=None) -> np.ndarray:
    """[4, 4] transform from a finger's local frame (u, v, w) to world.

    left:  world = (mount_x + w,  u, z0 + v)
    right: world = (mount_x - w, -u, z0 + v)
    z0 = cube_size / 2 + rest_offset: finger and object volumes share their vertical frame, so
    finger voxel row iv faces object voxel row iz = iv.
    """
    g = geometry_config(cfg)
    z0 = g.cube_size / 2 + g.rest_offset
    T = np.eye(4)
    if side == "left":
        T[:3, :3] = [[0, 0, 1], [1, 0, 0], [0, 1, 0]]
    elif side == "right":
        T[:3, :3] = [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]
    else:
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    T[:3, 3] = [mount_x, 0.0, z0]
    return T


def finger_with_mount(finger_tsdf, cfg=None) -> trimesh.Trimesh:
    """One watertight solid: the finger plus its mount plate, in metres, finger frame.

    The plate (``mount_plate_thickness``, the cube's full face less one voxel) is joined to the
    finger in volume space, so the surface is a single closed marching-cubes mesh.
    """
    g = geometry_config(cfg)
    finger = check_tsdf(finger_tsdf, "finger", g)
    if not is_feasible(finger, g):
        report = feasibility_report(finger, g)
        raise VolumeError(f"finger is not feasible, refusing to export it: {report}")
    n_plate = max(1, int(np.ceil(g.mount_plate_thickness / g.voxel_size)))
    u, v, w = voxel_centres(g)
    n_below = n_plate + 1  # one empty plane under the plate's bottom face
    w_ext = np.concatenate([-(np.arange(n_below)[::-1] + 0.5) * g.voxel_size, w])
    # Box faces between voxel centres: a sample exactly on the level set makes marching cubes
    # emit degenerate triangles.
    h = g.cube_size / 2 - g.voxel_size
    plate = _box_sdf(np.stack(np.meshgrid(u, v, w_ext, indexing="ij"), -1),
                     np.array([-h, -h, -n_plate * g.voxel_size]), np.array([h, h, 0.0]))
    plate = np.clip(plate / g.truncation, -1.0, 1.0)
    finger_ext = np.concatenate([np.ones((g.resolution,) * 2 + (n_below,), np.float32), finger], 2)
    volume = np.minimum(plate, finger_ext)  # union of solids
    origin = np.array([-g.cube_size / 2, -g.cube_size / 2, -n_below * g.voxel_size])
    return marching_cubes_mesh(volume, g.voxel_size, origin)


def export_finger_stl(finger_tsdf, path, cfg=None, *, header: str = "") -> Path:
    """Write finger plus mount plate as a watertight binary STL in millimetres (atomic write).

    header: up to 80 ASCII characters for the STL's header (what the finger was designed for);
    longer text is cut, and a header never starts with "solid" (readers would take the file for
    an ASCII STL)."""
    mesh = finger_with_mount(finger_tsdf, cfg)
    mesh.apply_scale(1000.0)
    data = bytearray(trimesh.exchange.stl.export_stl(mesh))
    text = header.encode("ascii", "replace")[:80]
    if text.lower().startswith(b"solid"):
        text = (b"f2f_jax " + text)[:80]
    data[:80] = text.ljust(80, b" ")
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(bytes(data))
    return path


# The imprint candidates of the pool: (origin, voxels the object is grown by before imprinting).
# Grown, its imprint leaves a voxel of play (looser); shrunk, it presses a voxel sooner (tighter).
IMPRINT_VARIANTS: tuple[tuple[str, float], ...] = (
    ("imprint", 0.0), ("imprint, 1 voxel looser", 1.0), ("imprint, 1 voxel tighter", -1.0))


def imprint_candidates(objects: np.ndarray, geometry: GeometryConfig | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The imprint pairs of ``IMPRINT_VARIANTS``: objects [B, R, R, R] -> lefts, rights
    [B, V, R, R, R] float32 and made [B, V] bool.

    A variant grows the object by ``voxels`` before imprinting (its TSDF, in units of the
    truncation distance, lowered by voxels x voxel size / truncation).  Where that leaves no
    volume to imprint (a box that fills the cube, grown by a voxel, has no voxel outside; a thin
    wall, shrunk by one, may vanish), the variant is not made: its fingers are empty volumes and
    ``made`` is False there, so the pool leaves it out.  The plain imprint (0 voxels) is made for
    every object that ``check_tsdf`` accepts."""
    g = geometry_config(geometry)
    step = g.voxel_size / g.truncation
    objects = np.asarray(objects, np.float32)
    b, v, r = len(objects), len(IMPRINT_VARIANTS), g.resolution
    lefts = np.ones((b, v, r, r, r), np.float32)
    rights = np.ones((b, v, r, r, r), np.float32)
    made = np.zeros((b, v), bool)
    for i, obj in enumerate(objects):
        for j, (_, voxels) in enumerate(IMPRINT_VARIANTS):
            grown = np.clip(obj - voxels * step, -1.0, 1.0).astype(np.float32)
            solid = grown < 0
            if voxels != 0 and (solid.all() or not solid.any()):
                continue  # nothing left outside (or inside) to imprint
            lefts[i, j], rights[i, j] = imprint_fingers(grown, g)
            made[i, j] = True
    return lefts, rights, made
