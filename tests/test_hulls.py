"""Convex pieces for simulation: fixed layout, fit to the shape, object cache, failure paths."""

import dataclasses
import os
import time
import warnings

import numpy as np
import pytest
import trimesh
from scipy.optimize import nnls
from scipy.spatial import ConvexHull

from f2f_jax.config import GeometryConfig, voxel_centres
from f2f_jax.errors import DecompositionError, VolumeError
from f2f_jax.geometry import (
    coacd_pieces,
    finger_pose,
    finger_tiling,
    imprint_fingers,
    mesh_to_tsdf,
    wsg50_fingers,
)
from f2f_jax.geometry.coacd_pieces import (
    CoacdSettings,
    decompose_mesh,
    mesh_hulls,
    object_hulls,
    reduce_pieces,
)
from f2f_jax.geometry.finger_tiling import finger_height_map, finger_hulls
from f2f_jax.geometry.hulls import (
    Hulls,
    hull_fit,
    hulls_to_mesh,
    pad_hulls,
    reduce_vertices,
    stack_hulls,
)

G = GeometryConfig()
K, V = G.finger_hulls, G.hull_vertices
# Cheap coacd settings: the cache and fallback logic do not depend on decomposition quality.
FAST = CoacdSettings(mcts_iterations=10, mcts_nodes=5, mcts_max_depth=1, resolution=300)


def analytic_tsdf(sdf) -> np.ndarray:
    """Volume from a signed distance function of (u, v, w) in metres, negative inside."""
    u, v, w = np.meshgrid(*voxel_centres(G), indexing="ij")
    return np.clip(sdf(u, v, w) / G.truncation, -1.0, 1.0).astype(np.float32)


def l_shape_mesh() -> trimesh.Trimesh:
    """A non-convex object: coacd has to cut it."""
    bar = trimesh.creation.box((3, 1, 1))
    post = trimesh.creation.box((1, 1, 3), transform=trimesh.transformations.translation_matrix(
        (-1, 0, 1.5)))
    return trimesh.util.concatenate([bar, post])


@pytest.fixture(scope="module")
def dome_finger():
    """A sphere finger: a 25 mm half ball standing on the mount."""
    return analytic_tsdf(lambda u, v, w: np.sqrt(u**2 + v**2 + w**2) - 0.025)


@pytest.fixture(scope="module")
def sphere_imprints():
    return imprint_fingers(mesh_to_tsdf(trimesh.creation.icosphere()))


@pytest.fixture(scope="module")
def l_shape_tsdf():
    return mesh_to_tsdf(l_shape_mesh())


@pytest.fixture(scope="module")
def fingers(dome_finger, sphere_imprints):
    rng = np.random.default_rng(3)
    # a rough random finger: columns of random heights, some empty
    heights = rng.integers(0, 40, size=(40, 40))
    rough = np.where(np.arange(40)[None, None, :] < heights[:, :, None], -1.0, 1.0)
    return {"dome": dome_finger, "box": wsg50_fingers()[0], "imprint": sphere_imprints[0],
            "rough": rough.astype(np.float32)}


# ---------------------------------------------------------------- layout


def test_every_finger_gets_the_same_padded_layout(fingers):
    made = []
    for name, finger in fingers.items():
        h = finger_hulls(finger)
        assert h.vertices.shape == (K, V, 3) and h.vertices.dtype == np.float32, name
        assert h.counts.shape == (K,) and h.counts.dtype == np.int32, name
        real = h.counts > 0
        assert np.all(h.counts[real] >= 4) and np.all(h.counts <= V), name
        assert np.array_equal(h.valid, real) and h.n_pieces == real.sum() >= 1
        for k, n in enumerate(h.counts):
            if n:  # padding rows repeat vertex 0
                assert np.all(h.vertices[k, n:] == h.vertices[k, 0]), (name, k)
            else:
                assert np.all(h.vertices[k] == 0), (name, k)
        assert [len(p) for p in h.pieces()] == [n for n in h.counts if n]
        made.append(h)
    verts, counts = stack_hulls(made)
    assert verts.shape == (len(made), K, V, 3) and counts.shape == (len(made), K)
    assert np.array_equal(counts[1], made[1].counts)


def test_pad_hulls_packs_any_piece_list_into_one_shape():
    rng = np.random.default_rng(0)
    shapes = set()
    for n in (1, 3, 8):
        pieces = [rng.normal(size=(int(rng.integers(4, 80)), 3)) for _ in range(n)]
        h = pad_hulls(pieces, 8, 16)
        shapes.add((h.vertices.shape, h.counts.shape))
        assert h.n_pieces == n and np.all(h.counts[:n] <= 16)
    assert shapes == {((8, 16, 3), (8,))}
    with pytest.raises(DecompositionError, match="do not fit"):
        pad_hulls([rng.normal(size=(10, 3))] * 9, 8, 16)


def test_stack_hulls_refuses_mixed_layouts(fingers):
    a = finger_hulls(fingers["box"])
    b = finger_hulls(fingers["box"], max_pieces=8)
    with pytest.raises(ValueError, match="layout"):
        stack_hulls([a, b])


def test_hulls_rejects_inconsistent_counts():
    with pytest.raises(ValueError):
        Hulls(np.zeros((2, 8, 3), np.float32), np.array([3, 0], np.int32))


def test_reduce_vertices_keeps_a_subset_that_spans_most_of_the_hull():
    pts = np.asarray(trimesh.creation.icosphere(subdivisions=3).vertices)  # 642 points
    out = reduce_vertices(pts, 32)
    assert 4 <= len(out) <= 32
    assert all(np.any(np.all(pts == p, axis=1)) for p in out)  # chosen from the input
    ratio = ConvexHull(out).volume / ConvexHull(pts).volume
    assert 0.75 < ratio <= 1.0
    with pytest.raises(DecompositionError):
        reduce_vertices(np.c_[pts[:, :2], np.zeros(len(pts))], 32)  # flat
    with pytest.raises(ValueError):
        reduce_vertices(pts, 3)


# ---------------------------------------------------------------- fingers


def test_height_map_reads_the_solid_extent_from_the_mount():
    f = np.ones((40, 40, 40), np.float32)
    f[5, 5, :10] = -1.0  # solid from the mount to plane 9
    f[6, 6, 20:30] = -1.0  # floating block: an undercut, filled down to the mount
    h = finger_height_map(f)
    # crisp -1/+1 values cross zero midway between voxel centres
    assert h[5, 5] == pytest.approx(10 * G.voxel_size)
    assert h[6, 6] == pytest.approx(30 * G.voxel_size)
    assert h[0, 0] == 0.0 and np.count_nonzero(h) == 2


@pytest.mark.parametrize("name", ["dome", "box", "imprint"])
def test_finger_hulls_cover_the_finger(fingers, name):
    fit = hull_fit(fingers[name], finger_hulls(fingers[name]))
    assert fit["iou"] > 0.85, fit
    assert fit["coverage"] > 0.9, fit


def test_flat_finger_is_fitted_to_the_voxel(fingers):
    fit = hull_fit(fingers["box"], finger_hulls(fingers["box"]))
    assert fit["max_intrusion_m"] <= G.voxel_size and fit["max_shortfall_m"] <= G.voxel_size, fit


def _max_depth_in_sphere(h: Hulls, side: str) -> float:
    """Deepest point of any piece inside the sphere the finger was imprinted from, at closure.

    The object is the icosphere stretched to the cube less a voxel (radius 28.5 mm, centred in
    the cube); at closure the finger's tip plane w = 6 cm lies on the object's mid-plane x = 0,
    so the mount is at x = -/+ 6 cm.  A convex piece reaches deepest into a ball at its point
    nearest the centre: min |sum_i l_i p_i - c| over l >= 0, sum l = 1 (NNLS, the sum enforced
    by a heavily weighted row)."""
    pose = finger_pose(side, -G.cube_size if side == "left" else G.cube_size, G)
    centre = np.array([0.0, 0.0, pose[2, 3]])  # height of the finger cube's centre
    radius = G.cube_size / 2 - G.voxel_size
    deepest = 0.0
    for piece in h.pieces():
        world = piece.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        weights, _ = nnls(np.vstack([world.T, 1e3 * np.ones(len(world))]), np.r_[centre, 1e3])
        deepest = max(deepest, radius - np.linalg.norm(weights @ world - centre))
    return deepest


@pytest.mark.parametrize("side", ["left", "right"])
def test_sphere_imprint_hulls_hardly_enter_the_sphere(sphere_imprints, side):
    finger = sphere_imprints[0 if side == "left" else 1]
    h = finger_hulls(finger)
    assert _max_depth_in_sphere(h, side) <= 0.003
    assert hull_fit(finger, h)["coverage"] > 0.95  # not by leaving the cavity's walls out


def test_cover_mode_contains_the_solid_and_intrudes_more(sphere_imprints):
    finger = sphere_imprints[0]
    cover = finger_hulls(finger, cover=True)
    balanced = finger_hulls(finger)
    fit_cover, fit_balanced = hull_fit(finger, cover), hull_fit(finger, balanced)
    assert fit_cover["coverage"] > 0.99
    assert fit_cover["max_intrusion_m"] > fit_balanced["max_intrusion_m"]
    assert _max_depth_in_sphere(cover, "left") > _max_depth_in_sphere(balanced, "left")


def test_more_pieces_fit_better(sphere_imprints):
    finger = sphere_imprints[0]
    few = hull_fit(finger, finger_hulls(finger, max_pieces=4))
    many = hull_fit(finger, finger_hulls(finger, max_pieces=32))
    assert many["max_intrusion_m"] < few["max_intrusion_m"] and many["iou"] > few["iou"]


def test_finger_tiles_partition_the_solid_columns(fingers):
    finger = fingers["rough"]
    labels = finger_tiling.finger_tiles(finger)
    solid = finger_height_map(finger) > 0
    assert labels.shape == (40, 40)
    assert np.all(labels[solid] >= 0) and labels.max() < K  # every solid column in one piece
    h = finger_hulls(finger)
    assert h.n_pieces == len(np.unique(labels[labels >= 0]))


@pytest.mark.parametrize("bad", ["empty", "nan", "shape"])
def test_invalid_volumes_raise(bad, tmp_path):
    vol = {"empty": np.ones((40, 40, 40), np.float32),
           "nan": np.full((40, 40, 40), np.nan, np.float32),
           "shape": -np.ones((40, 40, 39), np.float32)}[bad]
    with pytest.raises(VolumeError):
        finger_hulls(vol)
    with pytest.raises(VolumeError):
        object_hulls(vol, cache_dir=tmp_path)


# ---------------------------------------------------------------- fit metric, rendering


def test_hull_fit_sees_a_bad_fit(fingers):
    finger = fingers["dome"]
    h = G.cube_size / 2
    box = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (0.0, G.cube_size)])
    whole_cube = pad_hulls([box], 1, 8)
    bad, good = hull_fit(finger, whole_cube), hull_fit(finger, finger_hulls(finger))
    assert bad["iou"] < 0.5 and bad["max_intrusion_m"] > 0.02
    assert good["iou"] > bad["iou"] + 0.3 and good["max_intrusion_m"] < 0.005


def test_hulls_to_mesh_is_the_union_of_pieces(fingers):
    h = finger_hulls(fingers["dome"])
    mesh = hulls_to_mesh(h)
    assert mesh.volume == pytest.approx(sum(ConvexHull(p).volume for p in h.pieces()), rel=1e-4)
    lo, hi = mesh.bounds
    assert np.all(lo >= [-0.03 - 1e-9, -0.03 - 1e-9, -1e-9]) and np.all(hi <= [0.03, 0.03, 0.06])


# ---------------------------------------------------------------- objects


def test_convex_object_skips_coacd_and_fits_tightly(sphere_tsdf, tmp_path, monkeypatch):
    import coacd

    def refuse(*args, **kwargs):
        raise AssertionError("coacd must not run for a convex object")

    monkeypatch.setattr(coacd, "run_coacd", refuse)
    h = object_hulls(sphere_tsdf, cache_dir=tmp_path)
    assert h.vertices.shape == (G.object_hulls, V, 3)
    fit = hull_fit(sphere_tsdf, h)
    # free slots were spent on detail: one 32-vertex hull of a ball fits to ~0.82 IoU only
    assert fit["iou"] > 0.95 and fit["max_intrusion_m"] < G.voxel_size, fit


def test_object_cache_hit_is_identical_and_fast(l_shape_tsdf, tmp_path):
    t0 = time.perf_counter()
    first = object_hulls(l_shape_tsdf, cache_dir=tmp_path, settings=FAST)
    t1 = time.perf_counter()
    again = object_hulls(l_shape_tsdf, cache_dir=tmp_path, settings=FAST)
    t2 = time.perf_counter()
    assert np.array_equal(first.vertices, again.vertices)
    assert np.array_equal(first.counts, again.counts)
    assert (t2 - t1) * 10 < (t1 - t0)
    files = os.listdir(tmp_path)
    assert len(files) == 1 and files[0].endswith(".npz")  # and no temp file left behind
    fit = hull_fit(l_shape_tsdf, first)
    assert first.n_pieces >= 2 and fit["iou"] > 0.85, fit


def test_corrupt_cache_file_is_recomputed(l_shape_tsdf, tmp_path):
    first = object_hulls(l_shape_tsdf, cache_dir=tmp_path, settings=FAST)
    (path,) = tmp_path.iterdir()
    path.write_bytes(b"not a zip file")
    with pytest.warns(RuntimeWarning, match="unusable"):
        again = object_hulls(l_shape_tsdf, cache_dir=tmp_path, settings=FAST)
    assert np.array_equal(first.vertices, again.vertices)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the rewritten file loads cleanly
        third = object_hulls(l_shape_tsdf, cache_dir=tmp_path, settings=FAST)
    assert np.array_equal(first.vertices, third.vertices)


def test_cache_key_and_location(l_shape_tsdf, sphere_tsdf, tmp_path, monkeypatch):
    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path))
    assert coacd_pieces.default_cache_dir() == tmp_path / "hulls"
    object_hulls(sphere_tsdf)
    object_hulls(sphere_tsdf, settings=CoacdSettings(threshold=0.1))  # other settings, new entry
    object_hulls(sphere_tsdf, max_pieces=4)  # other layout, new entry
    object_hulls(sphere_tsdf)  # hit
    assert len(list((tmp_path / "hulls").glob("*.npz"))) == 3


def test_coacd_failure_falls_back_to_one_hull(monkeypatch):
    import coacd

    mesh = l_shape_mesh()

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(coacd, "run_coacd", broken)
    with pytest.warns(RuntimeWarning, match="coacd failed"):
        pieces = decompose_mesh(mesh, FAST)
    assert len(pieces) == 1
    assert ConvexHull(pieces[0]).volume == pytest.approx(mesh.convex_hull.volume)
    monkeypatch.setattr(coacd, "run_coacd", lambda *a, **k: [])
    with pytest.warns(RuntimeWarning, match="no pieces"):
        h = mesh_hulls(mesh, settings=FAST, max_pieces=2)
    assert h.n_pieces >= 1
    flat = trimesh.Trimesh(np.c_[np.random.default_rng(0).random((10, 2)), np.zeros(10)],
                           [[0, 1, 2], [3, 4, 5], [6, 7, 8]], process=False)
    monkeypatch.setattr(coacd, "run_coacd", broken)
    with pytest.warns(RuntimeWarning), pytest.raises(DecompositionError):
        decompose_mesh(flat, FAST)


def test_reduce_pieces_merges_touching_pieces_and_drops_specks():
    def cube(lo, size=1.0):
        return np.array([[x, y, z] for x in (0, size) for y in (0, size) for z in (0, size)],
                        float) + lo

    pieces = [cube([0, 0, 0]), cube([1, 0, 0]), cube([5, 5, 5]), cube([9, 9, 9], 0.01)]
    out, report = reduce_pieces(pieces, 2)
    assert len(out) == 2
    assert report == dict(pieces_in=4, merged=1, dropped=1, added_volume=pytest.approx(0, abs=1e-9),
                          dropped_volume=pytest.approx(1e-6))
    assert sorted(round(ConvexHull(p).volume, 6) for p in out) == [1.0, 2.0]
    same, report = reduce_pieces(pieces, 4)
    assert len(same) == 4 and report["merged"] == report["dropped"] == 0


def test_noise_volume_does_not_hang_in_coacd(tmp_path):
    noise = np.random.default_rng(0).uniform(-1, 1, (40, 40, 40)).astype(np.float32)
    with pytest.warns(RuntimeWarning, match="faces"):
        h = object_hulls(noise, cache_dir=tmp_path)
    assert h.n_pieces >= 1


def test_many_objects_in_worker_processes_match_one_by_one(sphere_tsdf, tmp_path):
    """object_hulls_many: uncached volumes decomposed by two worker processes give the hulls
    object_hulls gives; a duplicate is done once; a bad volume is an error string, not a crash."""
    from f2f_jax.geometry.hull_pool import object_hulls_many

    r = G.resolution
    box = np.ones((r, r, r), np.float32)
    box[12:28, 10:30, 1:25] = -1.0  # a convex box: no coacd, so this stays fast
    empty = np.ones((r, r, r), np.float32)
    got = object_hulls_many([sphere_tsdf, box, sphere_tsdf, empty], cache_dir=tmp_path / "a",
                            workers=2, progress=False)
    assert isinstance(got[3], str) and "empty" in got[3]
    assert got[0] is got[2]
    for vol, h in ((sphere_tsdf, got[0]), (box, got[1])):
        ref = object_hulls(vol, cache_dir=tmp_path / "b")
        assert np.array_equal(ref.vertices, h.vertices) and np.array_equal(ref.counts, h.counts)
    assert len(list((tmp_path / "a").glob("*.npz"))) == 2  # both written to the cache by workers


def test_many_objects_made_with_other_coacd_settings_are_cached_under_those(tmp_path):
    """object_hulls_many(settings=...): the workers get the settings (another coacd seed, as
    ``sim_retest.py --perturb pieces`` asks for) and cache under their key, not the default's."""
    from f2f_jax.geometry.coacd_pieces import CoacdSettings, cache_path
    from f2f_jax.geometry.hull_pool import object_hulls_many

    r = G.resolution
    boxes = []
    for lo in (8, 12):
        box = np.ones((r, r, r), np.float32)
        box[lo:28, 10:30, 1:25] = -1.0  # convex: one hull, no coacd run, so this stays fast
        boxes.append(box)
    other = CoacdSettings(seed=CoacdSettings().seed + 1)
    got = object_hulls_many(boxes, cache_dir=tmp_path, workers=2, progress=False, settings=other)
    for box, h in zip(boxes, got):
        assert not isinstance(h, str)
        assert cache_path(box, G, G.object_hulls, G.hull_vertices, other, tmp_path).exists()
        assert not cache_path(box, G, G.object_hulls, G.hull_vertices, CoacdSettings(), tmp_path).exists()


def test_with_max_vertices_keeps_slots_and_shrinks_each_piece_inside_itself():
    from f2f_jax.geometry.hulls import Hulls, pad_hulls, points_in_hulls, with_max_vertices

    rng = np.random.default_rng(3)
    ball = rng.normal(size=(200, 3))
    ball /= np.linalg.norm(ball, axis=1, keepdims=True)
    pieces = [0.01 * ball, 0.01 * ball + [0.03, 0, 0]]
    full = pad_hulls(pieces, 4, 32)
    full = Hulls(full.vertices[[0, 2, 1, 3]], full.counts[[0, 2, 1, 3]])  # a gap in slot 1
    coarse = with_max_vertices(full, 8)
    assert coarse.vertices.shape == (4, 8, 3)
    assert coarse.counts.tolist() == [8, 0, 8, 0]
    # every coarse vertex lies inside the piece it came from
    assert points_in_hulls(full, coarse.vertices[0, :8], tol=1e-7).all()
    assert points_in_hulls(full, coarse.vertices[2, :8], tol=1e-7).all()
    with pytest.raises(ValueError, match="max_vertices"):
        with_max_vertices(full, 3)


def test_remembered_finger_hulls_are_made_once_per_volume_equal_and_read_only(sphere_tsdf, monkeypatch):
    from f2f_jax import config as f2f_config

    cfg = f2f_config.default()
    left, _ = imprint_fingers(sphere_tsdf, cfg)
    made = []
    real = finger_tiling.finger_hulls
    monkeypatch.setattr(finger_tiling, "_memo", type(finger_tiling._memo)())
    monkeypatch.setattr(finger_tiling, "finger_hulls",
                        lambda *a, **k: made.append(1) or real(*a, **k))
    first = finger_tiling.remembered_finger_hulls(left, cfg)
    again = finger_tiling.remembered_finger_hulls(left.copy(), cfg)  # same values, other memory
    assert again is first and len(made) == 1
    fresh = real(left, cfg)
    np.testing.assert_array_equal(first.vertices, fresh.vertices)
    np.testing.assert_array_equal(first.counts, fresh.counts)
    with pytest.raises(ValueError):
        first.vertices[0, 0, 0] = 1.0  # shared between callers: nobody may edit them
    nudged = left.copy()
    nudged[0, 0, 0] = np.nextafter(nudged[0, 0, 0], np.float32(2))  # one value, one ulp
    finger_tiling.remembered_finger_hulls(nudged, cfg)
    other = cfg.replace(geometry=dataclasses.replace(cfg.geometry, hull_vertices=16))
    assert finger_tiling.remembered_finger_hulls(left, other).max_vertices == 16
    assert len(made) == 3
