"""Meshes <-> truncated signed distance volumes.

``mesh_to_tsdf`` places a mesh in the shape cube (``place_mesh``: stretched per axis to fill it,
as the original Fit2Form did; scaled uniformly to fit it; or kept at its real size), voxelises its
surface on a grid three times finer than the volume, fills the enclosed interior and takes
Euclidean distance transforms on both sides of the surface.  Working on occupancy rather than on
the triangle soup's orientation makes non-watertight, multi-body and badly oriented meshes usable:
whatever a closed surface (up to holes of about a fine voxel, 0.5 mm) encloses is solid.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from scipy import ndimage
from skimage import measure

from f2f_jax.config import SCALES, UNITS, GeometryConfig
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


@dataclasses.dataclass(frozen=True)
class Placement:
    """How a mesh was placed in the shape cube, so a design can say what its fingers fit.

    mode: "stretch" (each axis scaled to fill the cube: the paper's convention, the object's shape
        changes), "fit" (one factor for all axes, the largest extent fills the cube: the shape is
        kept, its size is not) or "real" (the mesh's own size, read in ``units``).
    factor: design-cube metres per mesh unit along x, y, z (three equal values unless stretched).
    extent: the mesh's size along x, y, z in its own units; units: those units ("m", "mm", ...),
        or None where they were never needed (stretch, fit).
    The placed object is ``(vertex - anchor) * factor`` shifted onto the cube's floor, centred in
    x and y; a finger printed from the design fits the object scaled by ``factor`` (in metres).
    """

    mode: str
    factor: tuple[float, float, float]
    extent: tuple[float, float, float]
    units: str | None = None

    @property
    def size_m(self) -> tuple[float, float, float]:
        """The placed object's size in the design cube, metres."""
        return tuple(float(e * f) for e, f in zip(self.extent, self.factor))

    @property
    def uniform(self) -> bool:
        """One factor for every axis: the object's shape is kept."""
        return self.factor[0] == self.factor[1] == self.factor[2]

    def describe(self) -> str:
        """One line for a log or a picture: what the fingers fit."""
        size = " x ".join(f"{s * 1e3:.1f}" for s in self.size_m)
        if self.mode == "real":
            return f"object at its real size ({size} mm; mesh read in {self.units})"
        if self.mode == "fit":
            return (f"object scaled uniformly by {self.factor[0]:.4g} m per mesh unit to fit the "
                    f"design cube ({size} mm): the fingers fit the object at that size")
        return (f"object stretched per axis to fill the design cube (factors "
                f"{', '.join(f'{f:.4g}' for f in self.factor)} m per mesh unit): the fingers fit "
                "that stretched shape, not the mesh")

    def short(self) -> str:
        """A few words for an STL header: the mode and the placed size (mm)."""
        size = "x".join(f"{s * 1e3:.1f}" for s in self.size_m)
        if self.mode == "real":
            return f"real size {size} mm"
        if self.mode == "fit":
            return f"fit x{self.factor[0]:.5g} m/unit, {size} mm"
        return f"stretched per axis to {size} mm"

    def to_json(self) -> dict:
        return dict(mode=self.mode, factor_m_per_unit=[float(f) for f in self.factor],
                    mesh_extent=[float(e) for e in self.extent], units=self.units,
                    object_size_mm=[round(s * 1e3, 3) for s in self.size_m],
                    uniform=self.uniform)


def check_placement(scale: str | None, units: str | None) -> None:
    """Raise ValueError for a scale mode or units that ``place_mesh`` does not know (None: unset)."""
    if scale is not None and scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; choose one of {', '.join(SCALES)}")
    if units is not None and units not in UNITS:
        raise ValueError(f"unknown units {units!r}; choose one of {', '.join(UNITS)}")


def place_mesh(mesh: trimesh.Trimesh, cfg: GeometryConfig | None = None, *, scale: str | None = None,
               units: str | None = None, name: str | None = None) -> tuple[trimesh.Trimesh, Placement]:
    """Put a mesh into the volume's local frame: returns (the placed mesh, its ``Placement``).

    scale: "stretch" (each axis to fill the cube less one voxel on every side: x, y in
    [-3 cm + v, 3 cm - v], z in [v, 6 cm - v] for voxel v = 1.5 mm, so every face, a box's
    included, is a zero crossing of the volume), "fit" (one factor, the largest extent filling the
    same span, the others centred in x and y and resting on the cube's floor at z = v) or "real"
    (the mesh's size in ``units``, placed as "fit" places it; refused when it does not fit the
    span); None: ``cfg.object_scale``.  units: "m", "cm", "mm" or "in"; needed by "real" only.
    Raises MeshError for empty, non-finite, flat, absurdly large meshes and for a real-size object
    bigger than the cube, ValueError for an unknown scale or units.
    """
    cfg = cfg or GeometryConfig()
    scale = cfg.object_scale if scale is None else scale
    label = _label(mesh, name)
    check_placement(scale, units)
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
    if scale != "real" and extent.max() > _MAX_EXTENT:
        raise MeshError(f"{label}: largest extent {extent.max():.4g} exceeds {_MAX_EXTENT:g} units; "
                        "objects are expected in metres or millimetres")
    if extent.max() <= 1e-9 or extent.min() < _MIN_ASPECT * extent.max():
        raise MeshError(f"{label}: the mesh is flat (extents {np.round(extent, 6).tolist()}); "
                        "a graspable object needs thickness on all three axes")
    v = cfg.voxel_size
    span = cfg.cube_size - 2 * v
    meta = dict(mesh.metadata)
    if scale == "stretch":
        lo_box = np.array([-cfg.cube_size / 2 + v, -cfg.cube_size / 2 + v, v])
        out = (verts - lo) / extent * span + lo_box
        placement = Placement("stretch", tuple(float(span / e) for e in extent),
                              tuple(float(e) for e in extent))
        return trimesh.Trimesh(out, faces.copy(), process=False, metadata=meta), placement
    if scale == "fit":
        factor = span / extent.max()
    else:
        if units is None:
            raise ValueError(f"{label}: scale='real' needs the mesh's units (one of "
                             f"{', '.join(UNITS)}): its largest extent is {extent.max():.4g} units")
        factor = UNITS[units]
        size = extent * factor
        if size.max() > span * (1 + 1e-9):
            dims = " x ".join(f"{s * 1e3:.1f}" for s in size)
            raise MeshError(f"{label}: at its real size the object is {dims} mm (x, y, z, read in "
                            f"{units}); the fingers' design cube holds at most {span * 1e3:.1f} mm "
                            "along each axis. Check the units, or scale it to fit (scale='fit', "
                            "f2f-design --scale fit): the fingers then fit the scaled object")
    anchor = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    out = (verts - anchor) * factor + np.array([0.0, 0.0, v])
    placement = Placement(scale, (float(factor),) * 3, tuple(float(e) for e in extent),
                          units if scale == "real" else None)
    return trimesh.Trimesh(out, faces.copy(), process=False, metadata=meta), placement


def normalize_mesh(mesh: trimesh.Trimesh, cfg: GeometryConfig | None = None, *,
                   scale: str | None = None, units: str | None = None,
                   name: str | None = None) -> trimesh.Trimesh:
    """The mesh placed in the volume's local frame (``place_mesh`` without its ``Placement``)."""
    return place_mesh(mesh, cfg, scale=scale, units=units, name=name)[0]


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
                 scale: str | None = None, units: str | None = None,
                 name: str | None = None) -> np.ndarray:
    """Shape volume of a mesh.

    mesh: any triangle mesh, placed in the cube by ``place_mesh`` (scale: "stretch", "fit" or
    "real" with ``units``; None: ``cfg.object_scale``).
    Returns tsdf: [R, R, R] float32 in [-1, 1], negative inside, truncated at cfg.truncation.
    Raises MeshError naming the mesh when it cannot become a volume.
    """
    return object_volume(mesh, cfg, scale=scale, units=units, name=name)[0]


def object_volume(mesh: trimesh.Trimesh, cfg: GeometryConfig | None = None, *,
                  scale: str | None = None, units: str | None = None,
                  name: str | None = None) -> tuple[np.ndarray, Placement]:
    """``mesh_to_tsdf`` and the ``Placement`` that says how the mesh was scaled into the cube."""
    cfg = cfg or GeometryConfig()
    label = _label(mesh, name)
    norm, placement = place_mesh(mesh, cfg, scale=scale, units=units, name=label)
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
                        f"{cfg.voxel_size * 1e3:.1f} mm resolution ({placement.describe()})")
    return tsdf, placement


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
