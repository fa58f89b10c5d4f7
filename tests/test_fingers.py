import numpy as np
import pytest
import trimesh

from f2f_jax.config import GeometryConfig
from f2f_jax.errors import VolumeError
from f2f_jax.geometry import (
    export_finger_stl,
    feasibility_report,
    finger_from_shape,
    finger_pose,
    imprint_fingers,
    is_feasible,
    largest_component,
    mesh_to_tsdf,
    wsg50_fingers,
)

G = GeometryConfig()


def block(u0, u1, v0, v1, w0, w1):
    """Finger volume: solid voxels [u0:u1, v0:v1, w0:w1] (crisp TSDF)."""
    f = np.ones((40, 40, 40), np.float32)
    f[u0:u1, v0:v1, w0:w1] = -1
    return f


def test_sphere_imprint_fingers_are_feasible_and_cage_the_sphere(sphere_tsdf):
    left, right = imprint_fingers(sphere_tsdf)
    assert is_feasible(left) and is_feasible(right)
    # Symmetric object: both fingers alike (up to the voxelisation's half-voxel asymmetry).
    assert np.mean((left < 0) != (right < 0)) < 0.01
    # The tip plane (w = 6 cm) meets the object's mid-plane: the cavity is deepest at the centre.
    depth = (left < 0).sum(axis=2)  # solid column length along w
    assert depth[20, 20] <= 21 and depth[0, 20] == 40  # centre ray hits, edge ray misses
    # Fingers placed at closure hug the sphere: no finger voxel inside it, gap at most ~1 voxel.
    finger_world = _finger_points_world(left, "left", mount_x=-G.cube_size)
    centre = np.array([0, 0, G.cube_size / 2 + G.rest_offset])  # the sphere resting on the floor
    r = G.cube_size / 2 - G.voxel_size
    d = np.linalg.norm(finger_world - centre, axis=1)
    assert d.min() > r - 1.5 * G.voxel_size


def _finger_points_world(finger, side, mount_x):
    from f2f_jax.config import voxel_centres

    u, v, w = np.meshgrid(*voxel_centres(G), indexing="ij")
    pts = np.stack([u[finger < 0], v[finger < 0], w[finger < 0], np.ones((finger < 0).sum())], 1)
    return (finger_pose(side, mount_x) @ pts.T).T[:, :3]


def test_right_finger_is_left_finger_turned_about_z():
    L, R = finger_pose("left", -0.05), finger_pose("right", 0.05)
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    assert np.allclose(turn @ L, R)
    assert np.isclose(np.linalg.det(R[:3, :3]), 1.0)


def test_imprint_of_an_asymmetric_object_differs_per_side():
    # A wedge: steep on one side, sloped on the other.
    mesh = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [0, 1, 1]],
        [[0, 2, 1], [1, 2, 3], [0, 1, 4], [2, 5, 3], [0, 4, 5], [0, 5, 2], [1, 3, 5], [1, 5, 4]],
    )
    left, right = imprint_fingers(mesh_to_tsdf(mesh))
    assert is_feasible(left) and is_feasible(right)
    assert np.mean((left < 0) != (right < 0)) > 0.02


def test_infeasible_fingers():
    assert not is_feasible(np.ones((40, 40, 40), np.float32))  # empty
    floating = block(10, 30, 10, 30, 10, 30)  # away from the mount
    assert not is_feasible(floating)
    assert feasibility_report(floating)["touches_mount"] is False
    two = np.minimum(block(0, 15, 0, 40, 0, 20), block(25, 40, 0, 40, 0, 20))  # two pieces
    assert feasibility_report(two)["components"] == 2 and not is_feasible(two)
    stalk = block(19, 21, 19, 21, 0, 40)  # touches the mount but on 4 / 1600 of the plane
    assert not is_feasible(stalk)
    edge_only = np.minimum(block(0, 20, 0, 20, 0, 10), block(20, 40, 20, 40, 0, 10))  # meet at an edge
    assert feasibility_report(edge_only)["components"] == 2
    good = block(0, 40, 0, 40, 0, 3)
    assert is_feasible(good)
    with pytest.raises(VolumeError, match="shape"):
        is_feasible(np.ones((40, 40)))


def test_largest_component_repairs_a_two_piece_finger():
    two = np.minimum(block(0, 30, 0, 40, 0, 20), block(33, 40, 0, 5, 0, 5))
    fixed = largest_component(two)
    assert is_feasible(fixed)
    assert (fixed < 0).sum() == 30 * 40 * 20


def test_finger_cut_from_an_object():
    cone = trimesh.creation.cone(radius=0.03, height=0.06)  # apex up: small share high up
    finger = finger_from_shape(mesh_to_tsdf(cone))
    assert finger is not None and is_feasible(finger)
    # A shape that never reaches 10% of a plane in its first third cannot become a finger.
    needle = np.ones((40, 40, 40), np.float32)
    needle[18:22, 18:22, :] = -1
    assert finger_from_shape(needle) is None


def test_wsg50_fingers_are_flat_pads():
    left, right = wsg50_fingers()
    assert is_feasible(left) and np.array_equal(left, right)
    solid = left < 0
    assert solid[:, :, 0].sum() > 0.1 * 1600
    # flat face: every solid column has the same length
    lengths = solid.sum(2)[solid.any(2)]
    assert lengths.min() == lengths.max() == 20


def test_export_stl_is_watertight_millimetres(tmp_path, sphere_tsdf):
    left, _ = imprint_fingers(sphere_tsdf)
    path = export_finger_stl(left, tmp_path / "left.stl")
    mesh = trimesh.load(path)
    assert mesh.is_watertight and mesh.volume > 0
    extent = mesh.bounds[1] - mesh.bounds[0]
    assert np.allclose(extent[:2], 60, atol=1.0)  # the 6 cm face in mm
    assert 60 < extent[2] < 66  # finger depth plus the mount plate
    with pytest.raises(VolumeError, match="not feasible"):
        export_finger_stl(block(10, 30, 10, 30, 10, 30), tmp_path / "bad.stl")
    assert not (tmp_path / "bad.stl").exists()


def test_imprint_finger_does_not_reach_under_a_resting_box():
    box = mesh_to_tsdf(trimesh.creation.box((0.05, 0.05, 0.05)))
    left, right = imprint_fingers(box)
    bottom = np.nonzero((box < 0).any(axis=(0, 1)))[0][0]
    for finger in (left, right):
        assert is_feasible(finger)
        # below the box's lowest row, nothing beyond the base block (w < 3 cm)
        assert not (finger[:, :bottom, 20:] < 0).any()


def test_a_flat_finger_mesh_becomes_the_flat_pads():
    from f2f_jax.geometry.fingers import finger_from_mesh

    g = GeometryConfig()
    # a 2 cm wide, 1 cm thick bar, face at x = 0, tip at z = 8 cm: the flat pads' shape
    bar = trimesh.creation.box((0.01, 0.02, 0.08))
    bar.apply_translation([-0.005, 0.0, 0.04])
    finger = finger_from_mesh(bar, g)
    pads, _ = wsg50_fingers(g)
    solid, want = finger < 0, pads < 0
    assert feasibility_report(finger, g)["feasible"]
    assert (solid != want).mean() < 0.01  # the same voxels but at the rims
    assert not solid[:, 0].any() and solid[:, 1].any()  # the tip a voxel above the floor
    with pytest.raises(ValueError, match="no column"):
        finger_from_mesh(bar.copy().apply_translation([0, 0.1, 0]), g)  # beside the volume


def test_wsg_fmf_finger_from_the_pybullet_mesh(monkeypatch):
    pytest.importorskip("pybullet_data")
    import importlib.util

    from f2f_jax.data import sources
    from f2f_jax.errors import MissingExtraError

    g = GeometryConfig()
    left, right = sources.wsg_fmf_fingers(g)
    report = feasibility_report(left, g)
    assert report["feasible"] and np.array_equal(left, right)
    solid = left < 0
    # 30 mm wide, face reaching 3 cm from the mount, not a flat pad: its face steps and grooves
    u = np.nonzero(solid.any(axis=(1, 2)))[0]
    assert abs((u[-1] - u[0] + 1) * g.voxel_size - 0.03) <= 2 * g.voxel_size
    depth = solid.sum(axis=2)[solid.any(axis=2)] * g.voxel_size
    assert depth.max() == pytest.approx(0.03, abs=g.voxel_size) and depth.min() < 0.025
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "pybullet_data" else real(name, *a))
    with pytest.raises(MissingExtraError, match=r"\.\[pybullet\]"):
        sources.wsg_fmf_fingers(g)
