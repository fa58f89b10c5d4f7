"""f2f_jax.design, FingerPair and the f2f-design CLI (tiny config, randomly initialised nets).

Random nets make noisy, nearly tied designs; the ranking and filtering tests therefore replace the
generator's raw output (``design.propose``) and, where the ranking itself is under test, the
fitness net (``design.predict``) with constructed cases whose right answer is known.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

import f2f_jax
from f2f_jax import config
from f2f_jax import design_pool
from f2f_jax import designer as design_module
from f2f_jax.cli.design import main as design_main
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.errors import F2FError, VolumeError
from f2f_jax.geometry import (
    imprint_fingers,
    is_feasible,
    largest_component,
    mesh_to_tsdf,
    wsg50_fingers,
)
from f2f_jax.train.state import init_trained_nets

R = 40


@pytest.fixture(scope="module")
def models():
    return init_trained_nets(config.get("tiny"))


@pytest.fixture(scope="module")
def box_tsdf():
    return mesh_to_tsdf(trimesh.creation.box((0.04, 0.03, 0.05)))


def _floating_block(w_from=10):
    """Solid everywhere from plane w_from on: never touches the mount plane (infeasible)."""
    f = np.ones((R, R, R), np.float32)
    f[2:-2, 2:-2, w_from:] = -1.0
    return f


def _constructed_candidates():
    """Six candidates with their expected feasibility after post-processing.

    Solid fractions (the fake fitness below) are highest for the infeasible ones, so that a
    ranking that ignored feasibility would pick them.
    """
    empty = np.ones((R, R, R), np.float32)
    narrow, _ = wsg50_fingers(width=0.02, depth=0.03)
    wide, _ = wsg50_fingers(width=0.04, depth=0.04)
    wide_speck = wide.copy()
    wide_speck[2:4, 2:4, 36:38] = -1.0  # a floating speck: two components until post-processing
    flat, _ = wsg50_fingers(width=0.03, depth=0.02)
    stub_and_float = _floating_block(12)
    stub_and_float[18:22, 18:22, :4] = -1.0  # small part on the mount, the big part floats
    fingers = [empty, _floating_block(), narrow, wide_speck, flat, stub_and_float]
    feasible = [False, False, True, True, True, False]
    return np.stack(fingers), np.array(feasible)


def _fake_predict(models, objects, lefts, rights):
    """Stand-in fitness: the solid fraction of the (post-processed) left finger, for all 11."""
    frac = (np.asarray(lefts) < 0).mean(axis=(2, 3, 4))
    return np.repeat(frac[..., None], len(TRIAL_NAMES), axis=-1).astype(np.float32)


def _propose_from(fingers):
    """A propose() returning the same constructed candidates for every object."""

    def propose(models, objects, key, candidates, noise=0.0):
        assert candidates == len(fingers)
        f = np.broadcast_to(fingers, (len(objects),) + fingers.shape).copy()
        return f, f.copy()

    return propose


# ------------------------------------------------------------------------------------ design()


def test_design_sphere_single(models, sphere_tsdf):
    # f2f_jax.design is the function even after the designer module was imported (as above)
    pair = f2f_jax.design(sphere_tsdf, params=models, candidates=1, verify=False)
    assert isinstance(pair, design_module.FingerPair)
    assert pair.left.shape == pair.right.shape == (R, R, R)
    assert pair.left.dtype == pair.right.dtype == np.float32
    assert pair.predicted.shape == (11,) and pair.predicted.dtype == np.float32
    # the fitness net's probabilities of the pair it returned (candidate 0: no noise, no ranking)
    np.testing.assert_allclose(pair.predicted, np.asarray(models.predict(sphere_tsdf[None], pair.left[None],
                                                                        pair.right[None]))[0], atol=1e-5)
    assert pair.simulated is None
    assert pair.feasible == (is_feasible(pair.left) and is_feasible(pair.right))
    np.testing.assert_array_equal(pair.object, sphere_tsdf)
    # candidate 0 is the generator's own output, post-processed as in training
    left, right = models.generate(sphere_tsdf[None])
    np.testing.assert_allclose(pair.left, largest_component(np.asarray(left)[0]), atol=1e-6)
    np.testing.assert_allclose(pair.right, largest_component(np.asarray(right)[0]), atol=1e-6)
    # the repr is a table of outcomes, not arrays
    text = repr(pair)
    assert all(name in text for name in TRIAL_NAMES) and "array" not in text and len(text) < 1500
    assert str(pair) == text


def test_design_candidates_pick_best_feasible(models, sphere_tsdf):
    k, key = 8, 3
    pair = design_module.design(sphere_tsdf, params=models, candidates=k, key=key,
                                verify=False)
    # the same candidates, scored independently
    lefts, rights = design_module.propose(models, sphere_tsdf[None], design_module.as_key(key), k)
    assert np.abs(lefts[0, 1:] - lefts[0, :1]).max() > 0, "latent noise made no new candidates"
    lefts = np.stack([[largest_component(f) for f in lefts[0]]])
    rights = np.stack([[largest_component(f) for f in rights[0]]])
    feasible = np.array([is_feasible(a) and is_feasible(b) for a, b in zip(lefts[0], rights[0])])
    assert pair.n_feasible == feasible.sum() and pair.n_candidates == k
    assert pair.feasible == feasible.any()
    pred = models.predict(np.repeat(sphere_tsdf[None], k, 0), lefts[0], rights[0])
    means = np.asarray(pred).mean(axis=1)
    pool = means[feasible] if feasible.any() else means
    assert pair.predicted.mean() == pytest.approx(pool.max(), abs=1e-5)
    np.testing.assert_allclose(pair.left, lefts[0, pair.candidate], atol=1e-6)


def test_design_filters_infeasible_and_ranks(models, sphere_tsdf, monkeypatch):
    fingers, feasible = _constructed_candidates()
    monkeypatch.setattr(design_module, "propose", _propose_from(fingers))
    monkeypatch.setattr(design_module, "predict", _fake_predict)
    pair = design_module.design(sphere_tsdf, params=models, candidates=len(fingers),
                                verify=False)
    post = np.stack([largest_component(f) for f in fingers])
    assert [is_feasible(f) for f in post] == feasible.tolist()  # the construction is right
    frac = (post < 0).mean(axis=(1, 2, 3))
    assert frac.argmax() not in np.nonzero(feasible)[0]  # the best-predicted one is infeasible
    expected = int(np.nonzero(feasible)[0][frac[feasible].argmax()])
    assert expected == 3
    assert pair.feasible and pair.candidate == expected and pair.n_feasible == 3
    assert pair.predicted.mean() == pytest.approx(frac[feasible].max())
    # the returned finger is post-processed: the speck is gone
    np.testing.assert_array_equal(pair.left, post[3])
    assert (fingers[3] < 0).sum() > (pair.left < 0).sum()


def test_design_no_feasible_candidate_warns(models, sphere_tsdf, monkeypatch):
    fingers, feasible = _constructed_candidates()
    bad = fingers[~feasible]
    monkeypatch.setattr(design_module, "propose", _propose_from(bad))
    monkeypatch.setattr(design_module, "predict", _fake_predict)
    with pytest.warns(design_module.InfeasibleDesignWarning, match="none of the 3 candidates"):
        pair = design_module.design(sphere_tsdf, params=models, candidates=len(bad),
                                    verify=False)
    assert not pair.feasible and pair.n_feasible == 0
    frac = (np.stack([largest_component(f) for f in bad]) < 0).mean(axis=(1, 2, 3))
    assert pair.candidate == frac.argmax()
    with pytest.raises(VolumeError, match="not feasible"):
        pair.export_stl("unused")


def test_rank_candidates_keys():
    feasible = np.array([[True, True, True, False, True]])
    pred = np.array([0.9, 0.5, 0.6, 0.99, 0.6])[None, :, None].repeat(11, -1)
    sim = np.zeros((1, 5, 11), np.uint8)
    for k, passed in enumerate([3, 5, 5, 11, 5]):
        sim[0, k, :passed] = 1
    # predicted only: feasible by mean; a full tie goes to the lower index
    assert design_module.rank_candidates(feasible, pred).tolist() == [[0, 2, 4, 1, 3]]
    # simulated first, predicted breaks ties, then the index
    assert design_module.rank_candidates(feasible, pred, sim).tolist() == [[2, 4, 1, 0, 3]]
    # moved copies: the mean over the exact pair and its copies; 1, 2 and 4 pass 5 exactly, 2
    # none of them moved, so 0 (3 exact, 3 moved) now ranks above 2: (5 + 0 + 0) / 3 < 3
    moved = np.zeros((2, 1, 5, 11), np.uint8)
    for k, passed in enumerate([3, 5, 0, 11, 5]):
        moved[:, 0, k, :passed] = 1
    assert design_module.rank_candidates(feasible, pred, sim, moved).tolist() == [[4, 1, 0, 2, 3]]
    with pytest.raises(ValueError, match="exact"):
        design_module.rank_candidates(feasible, pred, None, moved)


def test_design_batch_returns_list(models, sphere_tsdf, box_tsdf):
    objs = np.stack([sphere_tsdf, box_tsdf])
    pairs = design_module.design(objs, params=models, candidates=2, key=1, verify=False)
    assert isinstance(pairs, list) and len(pairs) == 2
    for pair, obj in zip(pairs, objs):
        np.testing.assert_array_equal(pair.object, obj)
        assert pair.left.shape == (R, R, R) and pair.predicted.shape == (11,)
        assert pair.n_candidates == 2


def test_export_stl_millimetres_watertight(models, sphere_tsdf, monkeypatch, tmp_path):
    left, right = imprint_fingers(sphere_tsdf)
    cands = np.stack([left, right])  # two candidates; both feasible
    monkeypatch.setattr(design_module, "propose",
                        lambda m, o, k, c, noise=0.0: (cands[None].copy(), cands[None, ::-1].copy()))
    pair = design_module.design(sphere_tsdf, params=models, candidates=2, verify=False)
    assert pair.feasible
    paths = pair.export_stl(tmp_path / "stl")
    assert [p.name for p in paths] == ["left.stl", "right.stl"]
    for path in paths:
        mesh = trimesh.load(path)
        assert mesh.is_watertight
        assert mesh.volume > 0
        # the mount plate spans the 6 cm cube less a voxel: tens of millimetres, not metres
        assert 40.0 < mesh.extents.max() < 100.0
        assert mesh.extents.min() > 3.0


@pytest.mark.parametrize("bad, match", [
    (np.zeros((R, R, R - 1), np.float32), "expected"),
    (np.zeros((2, 2, R, R, R), np.float32), "expected one volume"),
    (np.full((R, R, R), np.nan, np.float32), "NaN"),
    (np.ones((R, R, R), np.float32), "empty"),
    (-np.ones((R, R, R), np.float32), "every voxel is inside"),
])
def test_design_bad_input_raises(models, bad, match):
    with pytest.raises(VolumeError, match=match):
        design_module.design(bad, params=models)


def test_design_bad_batch_member_and_options(models, sphere_tsdf):
    batch = np.stack([sphere_tsdf, sphere_tsdf])
    batch[1, 3, 3, 3] = np.nan
    with pytest.raises(VolumeError, match=r"obj_tsdf\[1\]"):
        design_module.design(batch, params=models)
    with pytest.raises(ValueError, match="candidates"):
        design_module.design(sphere_tsdf, params=models, candidates=0)
    with pytest.raises(ValueError, match="backend"):
        design_module.design(sphere_tsdf, params=models, backend="bullet")


def test_design_without_checkpoint_names_the_command(sphere_tsdf, tmp_path):
    with pytest.raises(F2FError, match="experiments/cotrain.py"):
        design_module.design(sphere_tsdf, run_dir=tmp_path / "no_run")


# ------------------------------------------------------------------------------------ the CLI


@pytest.fixture
def sphere_stl(tmp_path, sphere_mesh):
    path = tmp_path / "sphere.stl"
    sphere_mesh.export(path)
    return path


def test_cli_writes_four_files(models, sphere_stl, tmp_path, monkeypatch, capsys):
    """The one simulating test: --verify (the default) on two constructed candidates."""
    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr("f2f_jax.cli.design._load_trained_nets", lambda run_dir: models)

    def propose(m, objects, key, candidates, noise=0.0):
        # candidate 0: the imprint pair of the object (holds a sphere); 1: flat fingertips
        left, right = imprint_fingers(objects[0])
        wl, wr = wsg50_fingers()
        return np.stack([[left, wl]]), np.stack([[right, wr]])

    monkeypatch.setattr(design_module, "propose", propose)
    out = tmp_path / "out"
    assert design_main([str(sphere_stl), "--out", str(out), "--candidates", "2",
                        "--no-imprint"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["design.png", "left.stl", "right.stl",
                                                     "scores.json"]
    assert (out / "design.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    scores = json.loads((out / "scores.json").read_text())
    assert scores["feasible"] and scores["verified"] and scores["checkpoint"] == "random init"
    assert scores["input"] == str(sphere_stl.resolve())
    assert list(scores["predicted"]) == list(TRIAL_NAMES) == list(scores["simulated"])
    assert set(scores["simulated"].values()) <= {0, 1}
    # the imprint pair grasps the sphere, flat fingertips on a sphere do not lift it
    assert scores["simulated"]["grasp"] == 1 and scores["candidate"] == 0
    assert scores["n_candidates"] == 2 and scores["origin"] == "generator"
    assert "grasp" in capsys.readouterr().out
    # --force replaces the directory whole; without --verify nothing is simulated
    (out / "stale.txt").write_text("old")
    assert design_main([str(sphere_stl), "--out", str(out), "--candidates", "2", "--no-verify",
                        "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["design.png", "left.stl", "right.stl",
                                                     "scores.json"]
    scores = json.loads((out / "scores.json").read_text())
    assert scores["simulated"] is None and not scores["verified"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]  # no temp dirs left


def test_verified_pool_holds_the_imprints_and_never_loses_to_them(models, sphere_tsdf,
                                                                  monkeypatch, tmp_path):
    """Generated candidates that cannot lift the sphere (flat tips at mu 0.2): the verified pick
    is then one of the imprint candidates the pool adds, and it passes at least the trials the
    imprint pair passes on its own."""
    from f2f_jax.sim import evaluate

    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))
    wl, wr = wsg50_fingers()
    monkeypatch.setattr(design_module, "propose", lambda m, objects, key, candidates, noise=0.0: (
        np.stack([[wl, wl]]), np.stack([[wr, wr]])))
    pair = design_module.design(sphere_tsdf, params=models, candidates=2, verify=True)
    names = [name for name, _ in design_module.IMPRINT_VARIANTS]
    assert pair.n_candidates == 2 + len(names) and pair.origin in names
    assert pair.candidate == 2 + names.index(pair.origin)
    left, right = imprint_fingers(sphere_tsdf)
    alone = evaluate(sphere_tsdf[None], left[None], right[None], cfg=models.config, progress=False)
    assert pair.simulated[0] == 1 and pair.simulated.sum() >= alone.sum()
    assert pair.scores()["origin"] == pair.origin and pair.origin in str(pair)
    # without verify the pool is the generator's alone, unless asked for
    assert design_module.design(sphere_tsdf, params=models, candidates=2,
                                verify=False).n_candidates == 2
    assert design_module.design(sphere_tsdf, params=models, candidates=2, verify=False,
                                imprint=True).n_candidates == 5


def test_tolerance_picks_the_design_whose_outcome_survives_printing(models, sphere_tsdf, monkeypatch):
    """A knife-edge candidate passes all 11 trials exactly as designed and none once its fingers
    move by a printer's error; a steady one passes 10 either way.  Verified on the exact pairs the
    knife edge wins; with ``tolerance`` the copies really are moved (by about the asked amount,
    the same copies for the same key) and the steady design wins, on its mean."""
    from f2f_jax.nets.generator import tsdf_heights

    knife, _ = wsg50_fingers(width=0.02, depth=0.03)
    steady, _ = wsg50_fingers(width=0.04, depth=0.04)
    monkeypatch.setattr(design_module, "propose", _propose_from(np.stack([knife, steady])))
    seen = []

    def simulate(nets, objects, lefts, rights, feasible, backend, progress=None, object_hulls=None,
                 executor="threads"):
        out = np.zeros(feasible.shape + (11,), np.uint8)
        for (b, k), f in zip(np.ndindex(feasible.shape), lefts.reshape(-1, R, R, R)):
            narrow = abs(int((f < 0).sum()) - int((knife < 0).sum())) < 0.1 * (knife < 0).sum()
            out[b, k, :11 if np.array_equal(f, knife) else 0 if narrow else 10] = 1
        seen.append(np.asarray(tsdf_heights(lefts.reshape(-1, R, R, R))))
        return out

    monkeypatch.setattr(design_module, "simulate_candidates", simulate)  # design()'s call
    monkeypatch.setattr(design_pool, "simulate_candidates", simulate)  # simulate_moved's
    exact = design_module.design(sphere_tsdf, params=models, candidates=2, verify=True, imprint=False)
    assert exact.candidate == 0 and exact.simulated.sum() == 11 and exact.moved is None
    assert exact.simulated_mean == 11 and exact.scores()["moved_passed"] is None

    seen.clear()
    pair = design_module.design(sphere_tsdf, params=models, candidates=2, verify=True,
                                imprint=False, tolerance=0.15, copies=2, key=3)
    assert len(seen) == 3  # the exact pairs, then one call per copy
    solid = seen[0] > 0
    for copy in seen[1:]:  # 0.15 mm = 0.1 voxel: every column moves, by about that much
        change = np.abs(copy - seen[0])[solid]
        assert change.min() > 0 and 0.025 < change.mean() < 0.1 and change.max() < 0.5
        assert np.all(copy[~solid] == 0)
    assert not np.array_equal(seen[1], seen[2])  # each copy its own field
    both = solid[0] & solid[1]  # the two candidates moved by the same field (shared by the object)
    np.testing.assert_allclose((seen[1] - seen[0])[0][both], (seen[1] - seen[0])[1][both], atol=1e-3)
    assert pair.candidate == 1 and pair.simulated.sum() == 10 and pair.tolerance == 0.15
    assert pair.moved.shape == (2, 11) and pair.moved.dtype == np.uint8 and pair.simulated_mean == 10
    scores = pair.scores()
    assert scores["moved_passed"] == [10, 10] and scores["tolerance_mm"] == 0.15
    assert "2 copies moved by 0.15 mm" in str(pair)
    assert [line.split()[-1] for line in str(pair).splitlines() if line.split()[0] == "outcome"] == ["moved"]
    first = [s.copy() for s in seen[1:]]
    seen.clear()
    design_module.design(sphere_tsdf, params=models, candidates=2, verify=True, imprint=False,
                         tolerance=0.15, copies=2, key=3)
    np.testing.assert_array_equal(np.stack(seen[1:]), np.stack(first))  # seeded by the key
    with pytest.raises(ValueError, match="verify"):
        design_module.design(sphere_tsdf, params=models, verify=False, tolerance=0.15)
    for bad in ({"tolerance": -0.1}, {"tolerance": float("nan")}, {"copies": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            design_module.design(sphere_tsdf, params=models, verify=True, **bad)


def test_printed_copies_move_every_design_set_alike_for_one_seed(sphere_tsdf):
    """``printed_copies``: copy-major [copies x N], each copy moved (0.3 mm: 0.2 voxel), and the
    fields depend on the seed, copy, side and object index only, so two rows that share a design
    of an object get identical copies of it (the pairing of ``research/printed_table.py``)."""
    wide, _ = wsg50_fingers(width=0.04, depth=0.04)
    left, right = imprint_fingers(sphere_tsdf)
    row_a = np.stack([left, wide]), np.stack([right, wide])
    row_b = np.stack([left, left]), np.stack([right, right])
    a = design_module.printed_copies(*row_a, 0.3, config.GeometryConfig(), 3, [7, 3])
    b = design_module.printed_copies(*row_b, 0.3, config.GeometryConfig(), 3, [7, 3])
    assert a[0].shape == a[1].shape == (6, R, R, R)
    for c in range(3):  # object 0 holds the same pair in both rows: the same moved copies
        np.testing.assert_array_equal(a[0][2 * c], b[0][2 * c])
        np.testing.assert_array_equal(a[1][2 * c], b[1][2 * c])
        assert not np.array_equal(a[0][2 * c], left)  # and it did move
    assert not np.array_equal(a[0][0], a[0][2])  # each copy its own field
    other = design_module.printed_copies(*row_a, 0.3, config.GeometryConfig(), 3, [8, 3])
    assert not np.array_equal(other[0][0], a[0][0])
    assert design_module.tolerance_voxels(0.3, config.GeometryConfig()) == pytest.approx(0.2)


def test_simulate_moved_shares_fields_across_an_objects_candidates(models, sphere_tsdf, monkeypatch):
    """shared=True moves two equal candidates of one object alike in each copy (common random
    numbers: candidates compared under the same printing error), a second object and each copy
    by other fields, and leaves infeasible candidates alone; shared=False moves every finger by
    its own field."""
    left, right = imprint_fingers(sphere_tsdf)
    lefts = np.broadcast_to(left, (2, 3, R, R, R)).copy()
    rights = np.broadcast_to(right, (2, 3, R, R, R)).copy()
    feasible = np.array([[True, True, False], [True, True, True]])
    seen = []

    def simulate(nets, objects, ls, rs, feas, backend, progress=None, object_hulls=None,
                 executor="threads"):
        seen.append((ls.copy(), rs.copy()))
        return np.zeros(feas.shape + (11,), np.uint8)

    monkeypatch.setattr(design_module, "simulate_candidates", simulate)  # design()'s call
    monkeypatch.setattr(design_pool, "simulate_candidates", simulate)  # simulate_moved's
    objects = np.stack([sphere_tsdf, sphere_tsdf])
    out = design_module.simulate_moved(models, objects, lefts, rights, feasible, "mujoco", 0.2, 2,
                                       np.random.default_rng(0), shared=True)
    assert out.shape == (2, 2, 3, 11) and len(seen) == 2
    for ls, rs in seen:
        for moved in (ls, rs):
            np.testing.assert_array_equal(moved[0, 0], moved[0, 1])  # one object: one field
            np.testing.assert_array_equal(moved[1, 0], moved[1, 2])
            assert not np.array_equal(moved[0, 0], moved[1, 0])  # another object: another
        assert not np.array_equal(ls[0, 0], left) and not np.array_equal(rs[0, 0], right)
        np.testing.assert_array_equal(ls[0, 2], left)  # infeasible: not moved
    assert not np.array_equal(seen[0][0][0, 0], seen[1][0][0, 0])  # each copy its own field
    seen.clear()
    design_module.simulate_moved(models, objects, lefts, rights, feasible, "mujoco", 0.2, 1,
                                 np.random.default_rng(0), shared=False)
    assert not np.array_equal(seen[0][0][0, 0], seen[0][0][0, 1])


def test_imprint_variants_fit_looser_and_tighter(sphere_tsdf):
    lefts, rights, made = design_module.imprint_candidates(sphere_tsdf[None])
    assert made.all()
    assert lefts.shape == rights.shape == (1, len(design_module.IMPRINT_VARIANTS), R, R, R)
    exact = imprint_fingers(sphere_tsdf)
    np.testing.assert_array_equal(lefts[0, 0], exact[0])
    np.testing.assert_array_equal(rights[0, 0], exact[1])
    solid = {name: int((lefts[0, i] < 0).sum())
             for i, (name, _) in enumerate(design_module.IMPRINT_VARIANTS)}
    # grown by a voxel, the object leaves a voxel-deep layer of the finger empty; shrunk, fills one
    assert solid["imprint, 1 voxel looser"] < solid["imprint"] < solid["imprint, 1 voxel tighter"]
    assert all(is_feasible(f) for f in (*lefts[0], *rights[0]))


def test_cli_bad_inputs_write_nothing(sphere_stl, tmp_path, capsys):
    text = tmp_path / "x.obj"
    text.write_text("this is not a mesh\n")
    cases = [text, tmp_path / "missing.stl"]
    for i, mesh in enumerate(cases):
        out = tmp_path / f"out{i}"
        assert design_main([str(mesh), "--out", str(out)]) == 2
        assert not out.exists()
        err = capsys.readouterr().err.strip()
        assert err.startswith("f2f-design: error:") and len(err.splitlines()) == 1
        assert str(mesh) in err
    # --tolerance: only with --verify, never negative; --copies >= 1 (refused before any work)
    for flags, match in [(["--no-verify", "--tolerance", "0.15"], "needs --verify"),
                         (["--tolerance", "-1"], "--tolerance must be"),
                         (["--tolerance", "nan"], "--tolerance must be"),
                         (["--tolerance", "0.15", "--copies", "0"], "--copies must be")]:
        out = tmp_path / "out_tol"
        assert design_main([str(sphere_stl), "--out", str(out), *flags]) == 2
        assert match in capsys.readouterr().err and not out.exists()
    # no checkpoint in the run directory
    out = tmp_path / "out_ckpt"
    assert design_main([str(sphere_stl), "--out", str(out), "--run-dir", str(tmp_path / "run")]) == 2
    assert "cotrain.py" in capsys.readouterr().err and not out.exists()
    # a non-empty output directory is left alone without --force
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    assert design_main([str(sphere_stl), "--out", str(full)]) == 2
    assert "--force" in capsys.readouterr().err and (full / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "sphere.stl", "x.obj"]


def test_cli_process_exit_code_no_traceback(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "f2f_jax.cli.design", str(tmp_path / "nope.obj"),
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "mesh file not found" in proc.stderr
    assert not out.exists()


def test_simulate_candidates_follows_the_configured_trials(models, sphere_tsdf, monkeypatch, tmp_path):
    """A grasp-only configuration (Table 2's) gets one column per candidate, not the grasp copied
    into 11: the imprint pair holds the sphere, the infeasible slot scores 0 without simulation."""
    import dataclasses

    from f2f_jax.tables.table import grasp_only

    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))
    left, right = imprint_fingers(sphere_tsdf)
    nets = dataclasses.replace(models, config=grasp_only(models.config))
    out = design_module.simulate_candidates(
        nets, sphere_tsdf[None], np.stack([[left, left]]), np.stack([[right, right]]),
        np.array([[True, False]]), "mujoco", progress=False)
    assert out.shape == (1, 2, 1) and out.dtype == np.uint8
    assert out[0, :, 0].tolist() == [1, 0]


# ---------------------------------------------------------------- meshes, scale modes, defaults


def test_design_takes_a_mesh_at_its_real_size(models, tmp_path):
    """A mesh (object or path) goes in directly; the pair says how it was placed, the STL header
    and scores.json say it, and a TSDF refuses scale options."""
    box = trimesh.creation.box((40.0, 30.0, 20.0))
    path = tmp_path / "part.stl"
    box.export(path)
    from_path, from_mesh = design_module.design([path, box], params=models, candidates=1,
                                                verify=False, scale="real", units="mm")
    np.testing.assert_array_equal(from_path.object, from_mesh.object)
    assert from_path.placement.mode == "real" and from_path.placement.units == "mm"
    np.testing.assert_allclose(from_path.placement.size_m, (0.04, 0.03, 0.02), rtol=1e-9)
    assert from_path.scores()["object_scale"]["object_size_mm"] == [40.0, 30.0, 20.0]
    fit = design_module.design(box, params=models, candidates=1, verify=False, scale="fit")
    assert fit.placement.mode == "fit" and (fit.object < 0).sum() > (from_mesh.object < 0).sum()
    with pytest.raises(ValueError, match="TSDF"):
        design_module.design(fit.object, params=models, verify=False, scale="fit")
    with pytest.raises(ValueError, match="scale"):
        design_module.design(box, params=models, verify=False, scale="squash")


def test_stl_header_names_the_object_and_its_scale(models, tmp_path):
    box = trimesh.creation.box((40.0, 30.0, 20.0))
    pair = design_module.design(box, params=models, candidates=1, verify=False, imprint=True,
                                scale="real", units="mm")
    assert pair.feasible
    left, right = pair.export_stl(tmp_path, name="part.stl")
    header = left.read_bytes()[:80].decode("ascii")
    assert header.startswith("f2f_jax left finger (mm) for part.stl: real size 40.0x30.0x20.0 mm")
    assert right.read_bytes()[:80].decode("ascii").startswith("f2f_jax right finger")
    assert trimesh.load(left).is_watertight


def test_cli_and_api_share_their_defaults():
    import inspect

    from f2f_jax.cli import design as cli
    from f2f_jax.geometry import SCALES, UNITS

    params = inspect.signature(design_module.design).parameters
    assert params["candidates"].default == cli.DEFAULT_CANDIDATES == design_module.DEFAULT_CANDIDATES
    assert params["verify"].default is cli.DEFAULT_VERIFY is design_module.DEFAULT_VERIFY is True
    assert cli.SCALES == SCALES and tuple(cli.UNITS) == tuple(UNITS)
    p = cli._design_parser()
    choices = {a.dest: a.choices for a in p._actions}
    assert tuple(choices["scale"]) == SCALES and tuple(choices["units"]) == tuple(UNITS)
    args = p.parse_args(["m.stl", "--out", "o"])
    assert args.candidates == cli.DEFAULT_CANDIDATES and args.verify is True
