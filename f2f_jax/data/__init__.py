"""Objects: their sources (built-in procedural families, PyBullet's random_urdfs, mesh directories),
splits and the object set on disk.  The bottom layer beside ``geometry``: no simulator, no JAX.
The grasp results live above the simulator, in ``f2f_jax.dataset``."""

from f2f_jax.data.families import FAMILIES, HOLLOW_FAMILIES
from f2f_jax.data.object_set import (
    held_out_objects,
    load_or_make_builtin_range,
    load_or_make_objects,
    object_split,
    run_objects,
)
from f2f_jax.data.objects import builtin_object, builtin_objects
from f2f_jax.data.sources import (
    load_mesh,
    load_mesh_dir,
    mesh_files,
    object_source,
    pybullet_data_dir,
    pybullet_random_urdfs,
)
from f2f_jax.data.splits import load_split, make_split, save_split

__all__ = [
    "FAMILIES", "held_out_objects", "HOLLOW_FAMILIES", "builtin_object", "builtin_objects", "load_mesh",
    "load_mesh_dir", "load_or_make_builtin_range", "load_or_make_objects", "load_split", "make_split",
    "mesh_files", "object_source", "object_split", "pybullet_data_dir", "pybullet_random_urdfs",
    "run_objects", "save_split",
]
