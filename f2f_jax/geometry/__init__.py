"""Shapes as volumes: TSDFs, fingers, convex pieces.  numpy/trimesh/scikit-image/coacd, no JAX."""

from f2f_jax.geometry.coacd_pieces import object_hulls
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.fingers import (
    export_finger_stl,
    feasibility_report,
    finger_extent,
    finger_from_shape,
    finger_pose,
    finger_with_mount,
    imprint_fingers,
    is_feasible,
    largest_component,
    postprocess,
    wsg50_fingers,
)
from f2f_jax.geometry.hulls import Hulls, hull_fit, stack_hulls
from f2f_jax.geometry.tsdf import (
    SCALES,
    UNITS,
    Placement,
    check_placement,
    check_tsdf,
    mesh_to_tsdf,
    normalize_mesh,
    object_volume,
    place_mesh,
    solid,
    solid_iou,
    tsdf_to_mesh,
)

__all__ = [
    "Hulls", "finger_hulls", "hull_fit", "object_hulls", "stack_hulls",
    "check_placement", "check_tsdf", "export_finger_stl", "feasibility_report", "finger_extent", "finger_from_shape",
    "finger_pose", "finger_with_mount", "imprint_fingers", "is_feasible", "largest_component", "postprocess",
    "mesh_to_tsdf", "normalize_mesh", "object_volume", "place_mesh", "Placement", "SCALES", "UNITS", "solid", "solid_iou", "tsdf_to_mesh", "wsg50_fingers",
]
