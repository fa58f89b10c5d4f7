"""Data: object sources (built-in, PyBullet's random_urdfs, mesh directories), splits, the
object set on disk and the grasp-result store."""

from f2f_jax.data.object_set import load_or_make_objects, object_split
from f2f_jax.data.objects import FAMILIES, HOLLOW_FAMILIES, builtin_object, builtin_objects
from f2f_jax.data.sources import (
    load_mesh,
    load_mesh_dir,
    mesh_files,
    object_source,
    pybullet_data_dir,
    pybullet_random_urdfs,
)
from f2f_jax.data.splits import load_split, make_split, save_split
from f2f_jax.data.store import GraspStore

make_object = builtin_object  # the name the first stand-in used

__all__ = [
    "FAMILIES", "GraspStore", "HOLLOW_FAMILIES", "builtin_object", "builtin_objects", "load_mesh",
    "load_mesh_dir", "load_or_make_objects", "load_split", "make_object", "make_split", "mesh_files",
    "object_source", "object_split", "pybullet_data_dir", "pybullet_random_urdfs", "save_split",
]
