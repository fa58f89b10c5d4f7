"""Meshes <-> truncated signed distance volumes.

``mesh_to_tsdf`` stretches a mesh per axis to fill the shape cube (as the original Fit2Form did),
voxelises its surface on a grid three times finer than the volume, fills the enclosed interior and
takes Euclidean distance transforms on both sides of the surface.  Working on occupancy rather than
on the triangle soup's orientation makes non-watertight, multi-body and badly oriented meshes
usable: whatever a closed surface (up to holes of about a fine voxel, 0.5 mm) encloses is solid.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage
from skimage import measure

from f2f_jax.config import GeometryConfig
from f2f_jax.errors import MeshError, VolumeError

_SUPERSAMPLE = 3  # fine voxels per volume voxel along each axis (odd: coarse centres are fine centres)
_MAX_EXTENT = 500.0  # mesh units; bigger than any object in metres or millimetres
_MIN_ASPECT = 0.01  # thinnest / thickest extent; flatter meshes would be stretched 100x


def _label(mesh: trimesh.Trimesh, name: str | None) -> str:
    return name or mesh.metadata.get("name") or mesh.metadata.get("file_name") or "<mesh>"


def check_tsdf(tsdf, name: str = "tsdf", cfg: GeometryConfig | None = None) -> np.ndarray:
    """Validate one shape volume and return it as float32.

    tsdf: [R, R, R] array (R = cfg.resolution, 40), finite, values in [-1, 1], negative inside.
    Raises VolumeError for a wrong shape, NaN/inf, a volume with no solid voxel (empty) or with
    no empty voxel (all inside).
    """
    cfg = cfg or GeometryConfig()
    r = cfg.resolution
    arr = np.asarray(tsdf)
    if arr.shape != (r, r, r):
        raise VolumeError(f"{name}: expected shape ({r}, {r}, {r}), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise VolumeError(f"{name}: expected a real-valued array, got dtype {arr.dtype}")
    arr = arr.astype(np.float32, copy=False)
    if not np.all(np.isfinite(arr)):
        raise VolumeError(f"{name}: contains {int(np.sum(~np.isfinite(arr)))} NaN/inf values")
    solid = arr < 0
    if not solid.any():
        raise VolumeError(f"{name}: empty volume (no voxel is negative/inside)")
    if solid.all():
        raise VolumeError(f"{name}: every voxel is inside; the shape has no surface in the cube")
    return arr


def normalize_mesh(mesh: trimesh.Trimesh, cfg: GeometryConfig | None = None, *,
                   name: str | None = None) -> trimesh.Trimesh:
    """Stretch a mesh per axis into the volume's local frame.

    The mesh spans the cube less one voxel on every side (x, y in [-3 cm + v, 3 cm - v], z in
    [v, 6 cm - v] for voxel v = 1.5 mm), so every face, a box's included, is a zero crossing of
    the volume.  Raises MeshError for empty, non-finite, flat or absurdly large meshes.
    """
    cfg = cfg or GeometryConfig()
    label = _label(mesh, name)
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{label}: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(verts) == 0 or len(faces) == 0:
        raise MeshError(f"{label}: the mesh is empty ({len(verts)} vertices, {len(faces)} faces)")
    if not np.all(np.isfinite(verts)):
        raise MeshError(f"{label}: {int(np.sum(~np.isfinite(verts).all(1)))} vertices are NaN/inf")
    used = verts[np.unique(faces)]
    lo, hi = used.min(0), used.max(0)
    extent = hi - lo
    if extent.max() > _MAX_EXTENT:
        raise MeshError(f"{label}: largest extent {extent.max():.4g} exceeds {_MAX_EXTENT:g} units; "
                        "objects are expected in metres or millimetres")
    if extent.max() <= 1e-9 or extent.min() < _MIN_ASPECT * extent.max():
        raise MeshError(f"{label}: the mesh is flat (extents {np.round(extent, 6).tolist()}); "
                        "a graspable object needs thickness on all three axes")
    v = cfg.voxel_size
    lo_box = np.array([-cfg.cube_size / 2 + v, -cfg.cube_size / 2 + v, v])
    span = cfg.cube_size - 2 * v
    out = (verts - lo) / extent * span + lo_box
    return trimesh.Trimesh(out, faces.copy(), process=False, metadata=dict(mesh.metadata))


def _triangle_points(vertices: np.ndarray, faces: np.ndarray, step: float) -> np.ndarray:
    """Points on every triangle, no two neighbours further apart than ``step``.

    Each triangle gets a barycentric grid of n subdivisions, n = ceil(longest edge / step);
    triangles are grouped by n so the work stays vectorised.
    """
    tri = vertices[faces]  # [F, 3, 3]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    ns = np.maximum(1, np.ceil(edges / step).astype(np.int64))
    out = [tri.reshape(-1, 3)]
    for n in np.unique(ns):
        if n == 1:
            continue
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        bary = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], 1) / n  # [P, 3]
        group = tri[ns == n]  # [G, 3, 3]
        out.append(np.einsum("pk,gkd->gpd", bary, group).reshape(-1, 3))
    return np.concatenate(out)


def _surface_voxels(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, pitch: float,
                    n: int) -> np.ndarray:
    """Boolean [n, n, n] grid marking cells that a triangle passes through (sampled at pitch/2)."""
    pts = _triangle_points(vertices, faces, pitch / 2)
    idx = np.clip(np.floor((pts - origin) / pitch).astype(np.int64), 0, n - 1)
    grid = np.zeros((n, n, n), dtype=bool)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return grid


_CLOSE_ITERATIONS = 4  # bridges holes up to ~2 x 4 fine voxels (4 mm at the default size)


def _fill(surface: np.ndarray) -> np.ndarray:
    """Solid = the surface plus what it encloses.

    A mesh with holes encloses nothing; then the surface is closed morphologically first (on a
    padded grid, so the cube's border does not erode it), which bridges holes of a few mm.
    """
    solid = ndimage.binary_fill_holes(surface)
    if solid.sum() > 1.05 * surface.sum():
        return solid
    k = _CLOSE_ITERATIONS + 1
    padded = np.pad(surface, k)
    closed = ndimage.binary_closing(padded, structure=np.ones((3, 3, 3), bool),
                                    iterations=_CLOSE_ITERATIONS)
    return ndimage.binary_fill_holes(closed)[k:-k, k:-k, k:-k] | surface


def mesh_to_tsdf(mesh: trimesh.Trimesh, cfg: GeometryConfig | None = None, *,
                 name: str | None = None) -> np.ndarray:
    """Shape volume of a mesh.

    mesh: any triangle mesh (any units; stretched per axis to fill the cube, see normalize_mesh).
    Returns tsdf: [R, R, R] float32 in [-1, 1], negative inside, truncated at cfg.truncation.
    Raises MeshError naming the mesh when it cannot become a volume.
    """
    cfg = cfg or GeometryConfig()
    label = _label(mesh, name)
    norm = normalize_mesh(mesh, cfg, name=label)
    s = _SUPERSAMPLE
    n = cfg.resolution * s
    pitch = cfg.voxel_size / s
    origin = np.array([-cfg.cube_size / 2, -cfg.cube_size / 2, 0.0])
    surface = _surface_voxels(np.asarray(norm.vertices), np.asarray(norm.faces), origin, pitch, n)
    solid = _fill(surface)
    # Distances between fine voxel centres; the surface lies half a fine voxel from each side.
    outside = ndimage.distance_transform_edt(~solid) - 0.5
    inside = ndimage.distance_transform_edt(solid) - 0.5
    sdf = np.where(solid, -inside, outside) * pitch
    centre = s // 2
    coarse = sdf[centre::s, centre::s, centre::s]
    tsdf = np.clip(coarse / cfg.truncation, -1.0, 1.0).astype(np.float32)
    if not (tsdf < 0).any():
        raise MeshError(f"{label}: no voxel came out inside; the mesh encloses no volume at "
                        f"{cfg.voxel_size * 1e3:.1f} mm resolution")
    return tsdf


def tsdf_to_mesh(tsdf, cfg: GeometryConfig | None = None, *, name: str = "tsdf") -> trimesh.Trimesh:
    """Watertight surface of a shape volume by marching cubes.

    tsdf: [R, R, R], negative inside.  Returns a trimesh.Trimesh with vertices in metres in the
    volume's local frame (config.py).  The volume is padded with empty voxels so the surface is
    closed where the shape touches the cube's faces.
    """
    cfg = cfg or GeometryConfig()
    arr = check_tsdf(tsdf, name, cfg)
    origin = np.array([-cfg.cube_size / 2, -cfg.cube_size / 2, 0.0])
    return marching_cubes_mesh(arr, cfg.voxel_size, origin)


def marching_cubes_mesh(volume: np.ndarray, voxel_size: float, origin: np.ndarray) -> trimesh.Trimesh:
    """Closed zero-level surface of a signed volume of any shape [A, B, C].

    volume[i, j, k] is sampled at origin + (i + 0.5, j + 0.5, k + 0.5) * voxel_size; the volume is
    padded with empty voxels so the surface closes where the solid touches the border.
    """
    padded = np.pad(volume, 1, constant_values=1.0)
    verts, faces, _, _ = measure.marching_cubes(padded, level=0.0, spacing=(voxel_size,) * 3)
    # padded index p is volume index p - 1, whose centre is at (p - 1 + 0.5) * voxel + origin
    mesh = trimesh.Trimesh(verts + origin - 0.5 * voxel_size, faces[:, ::-1], process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def solid(tsdf) -> np.ndarray:
    """Boolean occupancy (tsdf < 0)."""
    return np.asarray(tsdf) < 0


def solid_iou(a, b) -> np.ndarray:
    """IoU of the solid voxels of volumes a and b, [..., R, R, R] each: [...] float64 (two empty
    volumes count as 0)."""
    sa, sb = solid(a), solid(b)
    inter = (sa & sb).sum(axis=(-3, -2, -1))
    return inter / np.maximum((sa | sb).sum(axis=(-3, -2, -1)), 1)
