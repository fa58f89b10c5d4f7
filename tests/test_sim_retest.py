"""The test-retest figures of research/sim_retest.py."""

import importlib

import numpy as np

retest = importlib.import_module("research.sim_retest")


def _outcomes(trials_passed: np.ndarray) -> np.ndarray:
    """[N, K] trials passed -> [N, K, 11] outcomes (the first t trials pass)."""
    return (np.arange(11) < trials_passed[..., None]).astype(np.uint8)


def test_identical_runs_retest_perfectly():
    a = _outcomes(np.array([[0, 3, 7, 11], [2, 2, 5, 9]]))
    s = retest.retest_stats(a, a)
    assert s["spearman"] == 1.0 and s["objects_ranked"] == 2
    assert s["best_first"] == s["best_retest"] == 10.0
    assert s["mean"] == np.mean([0, 3, 7, 11, 2, 2, 5, 9])


def test_reversed_rerun_exposes_selection_luck():
    first = np.array([[0, 3, 7, 11], [1, 4, 6, 8]])
    second = first[:, ::-1]  # the rerun ranks every object's candidates backwards
    s = retest.retest_stats(_outcomes(first), _outcomes(second))
    assert s["spearman"] == -1.0
    assert s["best_first"] == 9.5 and s["best_retest"] == 0.5


def test_tied_objects_are_left_out():
    first = np.array([[5, 5, 5], [1, 2, 3]])
    s = retest.retest_stats(_outcomes(first), _outcomes(first))
    assert s["objects_ranked"] == 1 and s["spearman"] == 1.0


def test_bad_arguments_are_refused_before_any_work(tmp_path, capsys):
    import pytest

    assert retest.main(["--run-dir", str(tmp_path)]) == 2  # no run.json: not a co-training run
    assert "not a co-training run directory" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        retest.main(["--candidates", "1"])
    assert exc.value.code == 2


def test_pieces_rerun_asks_coacd_for_the_next_seed_and_simulates_what_it_gets(tmp_path, monkeypatch):
    """``--perturb pieces``: the rerun's object pieces come from ``object_hulls_many`` with coacd's
    seed + 1.  Here the stand-in hands back the first run's pieces (no coacd in the fast suite), so
    the rerun must reproduce the first run to the trial: the pieces it got are the pieces it used."""
    import json

    from f2f_jax.geometry import hull_pool
    from f2f_jax.geometry.coacd_pieces import CoacdSettings

    real = hull_pool.object_hulls_many
    asked, handed, simulated = [], [], []

    def same_pieces(objects, cfg=None, *, settings=None, **kw):
        asked.append(settings)
        made = real(objects, cfg, **kw)  # the default settings: the shipped pieces
        handed.append(made)
        return made

    real_evaluate = retest.sim.evaluate

    def recording_evaluate(*args, object_hulls=None, **kw):
        simulated.append(object_hulls)
        return real_evaluate(*args, object_hulls=object_hulls, **kw)

    monkeypatch.setattr(hull_pool, "object_hulls_many", same_pieces)
    monkeypatch.setattr(retest.sim, "evaluate", recording_evaluate)
    out = tmp_path / "retest.json"
    assert retest.main(["--n", "3", "--config", "tiny", "--perturb", "pieces", "--threads", "1",
                        "--json", str(out)]) == 0
    assert asked[0] is None and asked[1] == CoacdSettings(seed=CoacdSettings().seed + 1)
    assert len(simulated) == 2 and all(any(h is m for m in handed[1]) for h in simulated[1])
    got = json.loads(out.read_text())["perturbations"]["pieces"]
    assert got["agreement"] == 1.0 and got["whole_vectors"] == 1.0


def test_heights_rerun_moves_what_the_simulator_meshes_by_the_asked_amount():
    """``--perturb heights``: a finger's height map (all the simulator meshes of it) moves by about
    the asked standard deviation, its empty columns stay empty, and at 0 only the
    re-voxelisation is left, which the simulator's height map does not see."""
    from f2f_jax import config
    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf
    from f2f_jax.geometry.finger_tiling import finger_height_map
    from f2f_jax.nets.inference import perturbed_heights

    g = config.get("default").geometry
    left, right = imprint_fingers(mesh_to_tsdf(builtin_objects(1, seed=0)[0], g), g)
    fingers = np.stack([left, right])
    before = np.stack([finger_height_map(f, g) for f in fingers]) / g.voxel_size  # voxels
    solid = before > 0

    def heights(sd, seed=0):
        moved = perturbed_heights(fingers, sd, g.truncation_voxels, np.random.default_rng(seed))
        assert moved.shape == fingers.shape and moved.dtype == np.float32
        return np.stack([finger_height_map(f, g) for f in moved]) / g.voxel_size

    np.testing.assert_allclose(heights(0.0), before, atol=1e-4)
    inside = solid & (before < g.resolution - 0.5)  # the columns that end inside the cube move
    assert inside.sum() > 100
    for sd in (0.2, 1.0):
        after = heights(sd)
        assert np.all(after[~solid] == 0) and np.all(after[solid] > 0)
        np.testing.assert_array_equal(after[solid & ~inside], before[solid & ~inside])
        change = np.abs(after - before)[inside]
        # a smooth field of sd s at the grid points, bilinear between: |change| ~ 0.4-0.8 s on average
        assert 0.25 * sd < change.mean() < sd and change.max() < 5 * sd
    np.testing.assert_array_equal(heights(0.2, seed=1), heights(0.2, seed=1))
    assert not np.array_equal(heights(0.2, seed=1), heights(0.2, seed=2))
    import pytest

    with pytest.raises(ValueError, match="sd_voxels"):
        perturbed_heights(fingers, -0.1, g.truncation_voxels, np.random.default_rng(0))
    # the field's grid values given instead of drawn: the same draws give the same fingers, and
    # one grid moves two fingers alike (a benchmark's paired copies)
    grid = np.random.default_rng(5).standard_normal((2, 5, 5))
    np.testing.assert_array_equal(perturbed_heights(fingers, 0.2, g.truncation_voxels, grid=grid),
                                  perturbed_heights(fingers, 0.2, g.truncation_voxels,
                                                    np.random.default_rng(5)))
    same = perturbed_heights(fingers[[0, 0]], 0.2, g.truncation_voxels, grid=grid[[1, 1]])
    np.testing.assert_array_equal(same[0], same[1])
    with pytest.raises(ValueError, match="grid"):
        perturbed_heights(fingers, 0.2, g.truncation_voxels, grid=grid[:1])
    with pytest.raises(ValueError, match="one of the two"):
        perturbed_heights(fingers, 0.2, g.truncation_voxels)
    with pytest.raises(SystemExit):
        retest.main(["--perturb", "heights", "--height-sd", "-1"])
