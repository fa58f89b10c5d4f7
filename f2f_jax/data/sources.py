"""Where object meshes come from: the built-in procedural set, PyBullet's ``random_urdfs`` or a
directory of mesh files (ShapeNet, YCB, your own scans).

Every loader returns ``trimesh.Trimesh`` objects with ``metadata["name"]`` set to a stable,
unique name ("builtin/0007_cup", "pybullet/000", "<dir name>/<relative path>") that splits and
the grasp store use as keys.
"""

from __future__ import annotations

import importlib.util
import logging
import warnings
from pathlib import Path

import numpy as np
import trimesh

from f2f_jax.data.objects import builtin_objects
from f2f_jax.errors import MeshError, MissingExtraError
from f2f_jax.geometry.fingers import finger_from_mesh

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")
PYBULLET_HINT = 'pip install -e ".[pybullet]"'


def load_mesh(path, *, name: str | None = None) -> trimesh.Trimesh:
    """Read one mesh file (.obj, .stl, .ply, .glb, .gltf, .off) as a single Trimesh.

    A scene (several bodies, e.g. a glTF or an .obj with groups) is flattened into one mesh with
    each body's transform applied.  Raises FileNotFoundError for a missing file and MeshError,
    naming the file, for one that cannot be read, holds no triangles or has NaN/inf vertices.
    ``metadata["name"]`` is ``name`` or the file's stem; ``metadata["file_name"]`` its path.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        loaded = trimesh.load(path, force=None, process=False)
    except Exception as exc:  # trimesh raises many kinds (ValueError, KeyError, IndexError, ...)
        raise MeshError(f"{path}: cannot read as a mesh ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        bodies = [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
        bodies = [b for b in bodies if len(b.faces)]
        if not bodies:
            raise MeshError(f"{path}: the file holds no triangles")
        mesh = trimesh.util.concatenate(bodies) if len(bodies) > 1 else bodies[0]
    elif isinstance(loaded, trimesh.Trimesh):
        mesh = loaded
    else:
        raise MeshError(f"{path}: holds a {type(loaded).__name__}, not a triangle mesh")
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise MeshError(f"{path}: the mesh is empty ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces)")
    bad = int(np.sum(~np.isfinite(np.asarray(mesh.vertices)).all(axis=1)))
    if bad:
        raise MeshError(f"{path}: {bad} of {len(mesh.vertices)} vertices are NaN/inf")
    # Rebuild from geometry alone: drops textures and materials (big, unused) and merges the
    # duplicate vertices of STL triangle soups, so closed surfaces come out watertight.
    mesh = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    mesh.metadata["name"] = name or path.stem
    mesh.metadata["file_name"] = str(path)
    return mesh


def mesh_files(directory, *, recursive: bool = True) -> list[Path]:
    """Sorted mesh files (by suffix, case-insensitive) in a directory.

    Raises FileNotFoundError when the directory does not exist or is not a directory.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"mesh directory not found: {directory}")
    pattern = "**/*" if recursive else "*"
    return sorted(p for p in directory.glob(pattern) if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


def _names_for(files: list[Path], root: Path, prefix: str) -> list[str]:
    """'<prefix>/<relative path without suffix>', keeping the suffix where two files would clash."""
    stems = [p.relative_to(root).with_suffix("").as_posix() for p in files]
    counts = {s: stems.count(s) for s in stems}
    return [f"{prefix}/{s if counts[s] == 1 else p.relative_to(root).as_posix()}"
            for s, p in zip(stems, files)]


def _load_files(files: list[Path], names: list[str], *, limit: int | None = None
                ) -> tuple[list[trimesh.Trimesh], list[tuple[Path, str]]]:
    """Load files in order (stopping at ``limit`` meshes); returns meshes and (path, error)."""
    meshes, failed = [], []
    for path, name in zip(files, names):
        if limit is not None and len(meshes) >= limit:
            break
        try:
            meshes.append(load_mesh(path, name=name))
        except MeshError as exc:
            failed.append((path, str(exc)))
    return meshes, failed


def load_mesh_dir(directory, *, recursive: bool = True) -> list[trimesh.Trimesh]:
    """Every readable mesh file in a directory, sorted by path.

    Names are "<directory name>/<relative path without suffix>".  Unreadable files are skipped
    with one ``warnings.warn`` listing them.  Raises FileNotFoundError for a missing directory
    and MeshError when it holds no mesh files or none of them can be read.
    """
    directory = Path(directory)
    files = mesh_files(directory, recursive=recursive)
    if not files:
        raise MeshError(f"{directory}: no mesh files ({', '.join(MESH_SUFFIXES)}) "
                        f"{'under' if recursive else 'in'} this directory")
    names = _names_for(files, directory, directory.resolve().name or "meshes")
    meshes, failed = _load_files(files, names)
    if failed:
        listing = "; ".join(msg for _, msg in failed)
        if not meshes:
            raise MeshError(f"{directory}: none of its {len(files)} mesh files could be read: {listing}")
        warnings.warn(f"{directory}: skipped {len(failed)} of {len(files)} unreadable mesh files: {listing}",
                      stacklevel=2)
    return meshes


def pybullet_data_dir(what: str = "the 'pybullet' object source") -> Path:
    """The installed ``pybullet_data`` package directory (ships with the optional pybullet extra);
    MissingExtraError (an ImportError) naming ``what`` needs it and the install command."""
    spec = importlib.util.find_spec("pybullet_data")
    if spec is None or not spec.submodule_search_locations:
        raise MissingExtraError(f"{what} needs the pybullet package, which ships pybullet_data: "
                                f"{PYBULLET_HINT}")
    return Path(list(spec.submodule_search_locations)[0])


def wsg_fmf_mesh() -> trimesh.Trimesh:
    """Schunk's standard WSG50 finger (WSG-FMF), the mesh pybullet_data ships (zlib licence), in
    metres in the mesh's own frame (closing along +x, tip at the largest z)."""
    path = pybullet_data_dir("the WSG-FMF finger") / "gripper" / "meshes" / "WSG-FMF.stl"
    mesh = load_mesh(path, name="WSG-FMF")
    mesh.apply_scale(1e-3)  # the file is in millimetres
    return mesh


def wsg_fmf_fingers(cfg=None) -> tuple[np.ndarray, np.ndarray]:
    """The paper's WSG50 baseline: the standard WSG-FMF fingers as (left, right) finger volumes
    (``geometry.finger_from_mesh``: face toward the object, tip down, faces meeting at the
    object's mid-plane at full closure).  Raises MissingExtraError without the pybullet extra."""
    finger = finger_from_mesh(wsg_fmf_mesh(), cfg)
    return finger, finger.copy()


def _pybullet_files() -> list[Path]:
    root = pybullet_data_dir() / "random_urdfs"
    files = sorted(root.glob("*/*.obj"))
    if not files:
        raise MeshError(f"{root}: no random_urdfs/*/*.obj meshes in this pybullet_data install")
    return files


def pybullet_random_urdfs(n: int | None = None, seed: int = 0) -> list[trimesh.Trimesh]:
    """The ``random_urdfs`` meshes that PyBullet ships (~1,000 procedural rock-like shapes).

    n: None for all of them, else a subset of n chosen at random by ``seed`` (returned in name
    order).  Names are "pybullet/<folder>" ("pybullet/000").  Meshes that cannot be used (one of
    them has NaN vertices) are skipped and logged; a random subset is topped up from the rest.
    Raises ImportError naming the pybullet extra when pybullet_data is not installed.
    """
    files = _pybullet_files()
    names = [f"pybullet/{p.parent.name}" for p in files]
    order = np.arange(len(files))
    if n is not None:
        order = np.random.default_rng(seed).permutation(len(files))
    meshes, failed = _load_files([files[i] for i in order], [names[i] for i in order], limit=n)
    for path, msg in failed:
        log.warning("skipping pybullet mesh: %s", msg)
    return sorted(meshes, key=lambda m: m.metadata["name"])


def object_source(spec: str, n: int | None = None, seed: int = 0) -> list[trimesh.Trimesh]:
    """Meshes from a named source.

    spec: "builtin" (procedural, n required), "pybullet" (PyBullet's random_urdfs) or a directory
    of mesh files.  n: how many (for pybullet and directories a seeded random subset; None = all).
    """
    if n is not None and n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    if spec == "builtin":
        if n is None:
            raise ValueError("the builtin source generates objects: give n")
        return builtin_objects(n, seed)
    if spec == "pybullet":
        return pybullet_random_urdfs(n, seed)
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f"object source {spec!r} is neither 'builtin', 'pybullet' nor an "
                                "existing directory")
    meshes = load_mesh_dir(path)
    if n is not None and n < len(meshes):
        keep = np.sort(np.random.default_rng(seed).choice(len(meshes), n, replace=False))
        meshes = [meshes[i] for i in keep]
    return meshes
