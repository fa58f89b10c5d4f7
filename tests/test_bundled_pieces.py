"""The object pieces shipped for the builtin objects: found under the keys that runs, benchmarks
and tests compute, equal to what coacd makes, and never used where a caller asked for no cache."""

import numpy as np
import pytest

from f2f_jax.cli.bundle_pieces import builtin_volumes
from f2f_jax.config import GeometryConfig
from f2f_jax.geometry import coacd_pieces, hull_pool
from f2f_jax.geometry.coacd_pieces import CoacdSettings, bundled_hulls, cache_key, object_hulls
from f2f_jax.geometry.hull_pool import object_hulls_many

G = GeometryConfig()
K, V = G.object_hulls, G.hull_vertices
REBUILD = "python -m f2f_jax.cli.bundle_pieces"


def _key(vol):
    return cache_key(vol, G, K, V, CoacdSettings())


@pytest.fixture(scope="module")
def volumes():
    """Builtin objects 0-3 of seed 0, each raw and float16-rounded (an object set's form)."""
    return builtin_volumes(4, 0, G)


def test_the_builtin_objects_pieces_ship_under_their_keys(volumes):
    """A change to the families, the TSDF code or the cache key leaves the shipped pieces
    unreachable: every fresh CI machine and new user would then spend ~10 min of coacd."""
    missing = [i for i, vol in enumerate(volumes) if bundled_hulls(_key(vol), K, V) is None]
    assert not missing, f"volumes {missing} have no shipped pieces: rebuild them with `{REBUILD}`"
    assert len(volumes) == 8  # the float16 rounding changes every volume: both forms ship


def test_the_benchmarks_64th_builtin_object_ships_in_both_forms():
    """The agreement, fidelity and throughput benchmarks take builtin objects 0-63 as
    ``mesh_to_tsdf`` makes them, a run as an object set stores them: the last of them must ship
    in both forms, or a fresh machine spends minutes of coacd before a benchmark's first step."""
    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import mesh_to_tsdf

    raw = mesh_to_tsdf(builtin_objects(64, seed=0)[63], G)
    stored = raw.astype(np.float16).astype(np.float32)
    for name, vol in (("raw", raw), ("float16", stored)):
        assert bundled_hulls(_key(vol), K, V) is not None, f"object 63 ({name}) not shipped: `{REBUILD}`"


def test_shipped_pieces_are_read_instead_of_running_coacd(volumes, tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("coacd ran for a shipped object")

    monkeypatch.setattr(coacd_pieces, "decompose_mesh", refuse)
    for vol in volumes:
        h = object_hulls(vol, G, cache_dir=tmp_path)
        assert h.vertices.shape == (K, V, 3) and h.n_pieces >= 1
    assert not list(tmp_path.iterdir())  # read, not copied into the cache
    monkeypatch.setattr(hull_pool.subprocess, "Popen", refuse)  # no worker for shipped objects
    many = object_hulls_many(volumes, G, cache_dir=tmp_path, workers=2, progress=False)
    assert all(np.array_equal(a.vertices, object_hulls(v, G, cache_dir=tmp_path).vertices)
               for a, v in zip(many, volumes))


def test_no_cache_means_no_shipped_pieces_either(volumes, monkeypatch):
    """cache_dir=False computes (how uncached meshing is timed), also for a shipped object."""
    calls = []

    def counted(mesh, settings=None, **kwargs):
        calls.append(mesh)
        raise RuntimeError("counted")

    monkeypatch.setattr(coacd_pieces, "decompose_mesh", counted)
    nonconvex = []
    for vol in volumes:
        try:
            object_hulls(vol, G, cache_dir=False)
        except RuntimeError:
            nonconvex.append(vol)
    assert nonconvex, "objects 0-3 are all convex: pick others for this test"
    assert len(calls) == len(nonconvex)


@pytest.mark.slow
def test_shipped_pieces_equal_what_coacd_makes_now(volumes):
    """The bundle is a cache, not a source of truth: coacd here makes the same pieces for a
    non-convex shipped object (bit for bit on the machine that built it; 1e-6 allowed for
    another CPU's float rounding)."""
    g16 = volumes[1]  # object 0 as an object set stores it
    fresh = object_hulls(g16, G, cache_dir=False)
    shipped = bundled_hulls(_key(g16), K, V)
    assert np.array_equal(fresh.counts, shipped.counts)
    np.testing.assert_allclose(fresh.vertices, shipped.vertices, atol=1e-6)


def _teacher_volume(index: int) -> np.ndarray:
    """Builtin object ``index`` of seed 0 as an object set stores it (float16-rounded)."""
    from f2f_jax.data.objects import builtin_object
    from f2f_jax.geometry import mesh_to_tsdf

    return mesh_to_tsdf(builtin_object(index, 0), G).astype(np.float16).astype(np.float32)


def _assert_shipped(*indices: int) -> None:
    """Builtin objects ``indices`` of seed 0, as an object set stores them, have shipped pieces."""
    for index in indices:
        assert bundled_hulls(_key(_teacher_volume(index)), K, V) is not None, (
            f"builtin object {index} not shipped: `{REBUILD}`")


def test_the_teacher_objects_pieces_ship():
    """The teacher config's extra objects (builtin 64-299 of seed 0, as an object set stores them)
    ship their pieces: without them a teacher run first spends ~30 min of coacd on 2 cores."""
    from f2f_jax import config

    t = config.teacher().train
    _assert_shipped(t.n_objects, 200, t.n_objects + t.teacher_objects - 1)


def test_every_builtin_object_up_to_639_ships():
    """A teacher set of >= 500 objects (``--set train.teacher_objects=576``: builtin 64-639) reads
    its pieces instead of spending about an hour of coacd on 2 cores (340 objects; 65 min
    measured) before its first simulation."""
    _assert_shipped(300, 450, 639)


@pytest.mark.slow
def test_a_teacher_objects_shipped_pieces_equal_what_coacd_makes_now():
    """A sample of the teacher objects (one beyond the teacher config's 64-299): coacd here makes
    the pieces that ship for it."""
    vol = _teacher_volume(517)  # a mug, of the 300-639 range
    fresh = object_hulls(vol, G, cache_dir=False)
    shipped = bundled_hulls(_key(vol), K, V)
    assert shipped is not None and np.array_equal(fresh.counts, shipped.counts)
    np.testing.assert_allclose(fresh.vertices, shipped.vertices, atol=1e-6)
