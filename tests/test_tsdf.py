import numpy as np
import pytest
import trimesh

from f2f_jax.config import GeometryConfig, voxel_centres
from f2f_jax.errors import MeshError, VolumeError
from f2f_jax.geometry import check_tsdf, mesh_to_tsdf, tsdf_to_mesh
from tests.conftest import cup_mesh


def iou(a, b):
    a, b = a < 0, b < 0
    return (a & b).sum() / (a | b).sum()


def test_sphere_matches_analytic_distance(sphere_tsdf):
    g = GeometryConfig()
    r = (g.cube_size - 2 * g.voxel_size) / 2  # normalised sphere: the cube less one voxel a side
    x, y, z = np.meshgrid(*voxel_centres(g), indexing="ij")
    ref = np.clip((np.sqrt(x**2 + y**2 + (z - g.cube_size / 2) ** 2) - r) / g.truncation, -1, 1)
    band = np.abs(ref) < 1
    err = np.abs(sphere_tsdf - ref)[band].mean()
    print(f"sphere TSDF mean abs error in the truncation band: {err:.4f}")
    assert sphere_tsdf.shape == (40, 40, 40) and sphere_tsdf.dtype == np.float32
    assert sphere_tsdf.min() >= -1 and sphere_tsdf.max() <= 1
    assert err < 0.1
    # deep inside is fully truncated, the corners are outside
    assert sphere_tsdf[20, 20, 20] == -1 and sphere_tsdf[0, 0, 0] > 0


@pytest.mark.parametrize("name", ["box", "torus", "cup"])
def test_round_trip_iou(name):
    mesh = {
        "box": lambda: trimesh.creation.box((0.04, 0.02, 0.05)),
        "torus": lambda: trimesh.creation.torus(0.02, 0.008),
        "cup": cup_mesh,
    }[name]()
    tsdf = mesh_to_tsdf(mesh)
    surface = tsdf_to_mesh(tsdf)
    assert surface.is_watertight
    back = mesh_to_tsdf(surface)
    score = iou(tsdf, back)
    print(f"{name}: round-trip IoU {score:.3f}")
    assert score > 0.9


def test_cup_keeps_its_cavity():
    tsdf = mesh_to_tsdf(cup_mesh())
    # centre column above the base is empty, the wall at the rim is solid
    assert (tsdf[20, 20, 12:38] > 0).all()
    assert (tsdf[1:3, 20, 30] < 0).any()


def test_mesh_with_holes_is_still_solid(sphere_mesh, sphere_tsdf):
    holed = trimesh.Trimesh(sphere_mesh.vertices, sphere_mesh.faces[3:], process=False)
    assert not holed.is_watertight
    assert iou(mesh_to_tsdf(holed), sphere_tsdf) > 0.95


def test_multi_body_union():
    a = trimesh.creation.box((0.02, 0.02, 0.02))
    b = trimesh.creation.box((0.02, 0.02, 0.02))
    b.apply_translation([0.03, 0, 0])
    tsdf = mesh_to_tsdf(trimesh.util.concatenate([a, b]))
    solid = tsdf < 0
    # two blocks with a gap between them along x
    assert solid[5, 20, 20] and solid[34, 20, 20] and not solid[20, 20, 20]


def test_tsdf_to_mesh_frame_is_metres(sphere_tsdf):
    m = tsdf_to_mesh(sphere_tsdf)
    lo, hi = m.bounds
    assert np.allclose(lo, [-0.0285, -0.0285, 0.0015], atol=1e-3)
    assert np.allclose(hi, [0.0285, 0.0285, 0.0585], atol=1e-3)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), [[0, 1, 2]], process=False), "NaN"),
        (lambda: trimesh.Trimesh(), "empty"),
        (lambda: trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]]), "flat"),
        (lambda: trimesh.creation.box((1000.0, 800.0, 900.0)), "exceeds"),
    ],
    ids=["nan", "empty", "sheet", "1km"],
)
def test_bad_meshes_raise_clear_errors(make, match):
    mesh = make()
    mesh.metadata["name"] = "bad.obj"
    with pytest.raises(MeshError, match=match) as info:
        mesh_to_tsdf(mesh)
    assert "bad.obj" in str(info.value)


@pytest.mark.parametrize(
    "arr, match",
    [
        (np.zeros((40, 40)), "shape"),
        (np.zeros((32, 32, 32)), "shape"),
        (np.full((40, 40, 40), np.nan), "NaN"),
        (np.ones((40, 40, 40)), "empty"),
        (-np.ones((40, 40, 40)), "inside"),
    ],
    ids=["2d", "wrong-size", "nan", "empty", "all-inside"],
)
def test_bad_volumes_raise_clear_errors(arr, match):
    with pytest.raises(VolumeError, match=match):
        check_tsdf(arr)
    with pytest.raises(VolumeError, match=match):
        tsdf_to_mesh(arr)


def test_solid_iou_per_volume():
    from f2f_jax.geometry import solid_iou

    a = np.ones((2, 4, 4, 4), np.float32)
    a[0, :2] = -1  # half the cube solid
    a[1, :1] = -1  # a quarter
    b = np.ones_like(a)
    b[:, :1] = -1  # a quarter in both
    np.testing.assert_allclose(solid_iou(a, b), [0.5, 1.0])
    assert solid_iou(a[0], a[0]) == 1.0
    assert solid_iou(np.ones((4, 4, 4)), np.ones((4, 4, 4))) == 0.0  # two empty volumes


# ------------------------------------------------------------------------- placing a mesh


def test_scale_modes_keep_or_change_the_objects_shape():
    """A 40 x 20 x 10 mm box: stretched it fills the cube (a cube), fit it keeps 4:2:1 with its
    longest side the cube's span, at its real size it is 40 x 20 x 10 mm; each says so."""
    from f2f_jax.geometry import object_volume, place_mesh

    g = GeometryConfig()
    span = g.cube_size - 2 * g.voxel_size
    box = trimesh.creation.box((40.0, 20.0, 10.0))  # millimetres
    volumes = {}
    for scale, units, size in [("stretch", None, (span, span, span)),
                               ("fit", None, (span, span / 2, span / 4)),
                               ("real", "mm", (0.040, 0.020, 0.010))]:
        placed, where = place_mesh(box, g, scale=scale, units=units)
        np.testing.assert_allclose(placed.extents, size, rtol=1e-9)
        np.testing.assert_allclose(where.size_m, size, rtol=1e-9)
        assert where.mode == scale and where.uniform == (scale != "stretch")
        assert placed.bounds[0][2] == pytest.approx(g.voxel_size)  # resting on the cube's floor
        np.testing.assert_allclose(placed.bounds.mean(0)[:2], 0.0, atol=1e-12)  # centred in x, y
        volumes[scale], got = object_volume(box, g, scale=scale, units=units)
        assert got == where and where.to_json()["object_size_mm"] == [round(s * 1e3, 3) for s in size]
    solid = {k: (v < 0).mean() for k, v in volumes.items()}
    assert solid["stretch"] > 0.8 > 0.15 > solid["fit"] > solid["real"] > 0.02
    # the default is the config's (the nets' training objects): stretch, bit for bit
    np.testing.assert_array_equal(mesh_to_tsdf(box, g), volumes["stretch"])


def test_real_size_refuses_what_does_not_fit_and_needs_units():
    from f2f_jax.geometry import place_mesh

    box = trimesh.creation.box((80.0, 20.0, 10.0))
    with pytest.raises(MeshError, match=r"80\.0 x 20\.0 x 10\.0 mm .*57\.0 mm"):
        place_mesh(box, scale="real", units="mm", name="long box")
    with pytest.raises(ValueError, match="units"):
        place_mesh(box, scale="real")
    with pytest.raises(ValueError, match="scale"):
        place_mesh(box, scale="squash")
    with pytest.raises(ValueError, match="units"):
        place_mesh(box, scale="real", units="furlong")
    # the same box in metres, at its real size, is 80 m long: refused, naming its size
    with pytest.raises(MeshError, match="80000.0 x"):
        place_mesh(trimesh.creation.box((80.0, 20.0, 10.0)), scale="real", units="m")
