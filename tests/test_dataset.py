"""The pretraining dataset builder: resumable after a kill, nothing duplicated."""

import numpy as np
import pytest
import trimesh

from f2f_jax import sim
from f2f_jax.dataset.pretraining import build_grasp_dataset
from f2f_jax.dataset.store import GraspStore
from f2f_jax.geometry import mesh_to_tsdf


@pytest.fixture(scope="module")
def three_objects():
    meshes = [trimesh.creation.icosphere(subdivisions=3), trimesh.creation.box((0.04, 0.03, 0.05)),
              trimesh.creation.cylinder(0.02, 0.05)]
    return np.stack([mesh_to_tsdf(m) for m in meshes]), ["sphere", "box", "cylinder"]


def test_killed_build_resumes_without_duplicates(tmp_path, three_objects, tiny_cfg, monkeypatch):
    tsdfs, names = three_objects
    real = sim.evaluate
    calls = {"n": 0}

    def dies_on_second_batch(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("killed")
        return real(*args, **kwargs)

    store = GraspStore(tmp_path / "store")
    monkeypatch.setattr(sim, "evaluate", dies_on_second_batch)
    with pytest.raises(KeyboardInterrupt):
        build_grasp_dataset(tsdfs, names, store, cfg=tiny_cfg, batch_objects=1, n_cut=0, progress=False)
    assert store.done_keys() == {"sphere"} and len(store) == 2  # imprint + wsg50 of the first
    monkeypatch.setattr(sim, "evaluate", real)
    summary = build_grasp_dataset(tsdfs, names, GraspStore(tmp_path / "store"), cfg=tiny_cfg,
                                  batch_objects=1, n_cut=0, progress=False)
    assert summary["imprint"]["pairs"] == 2  # only the two objects left were simulated
    data = GraspStore(tmp_path / "store").read(("kind", "outcome"))
    assert len(data["kind"]) == 6 and sorted(data["kind"]) == ["imprint"] * 3 + ["wsg50"] * 3
    # the imprint pairs of simple convex shapes hold; flat tips at mu 0.2 drop them
    kinds, outcome = data["kind"], data["outcome"]
    assert outcome[kinds == "imprint", 0].sum() >= 2
    assert outcome[kinds == "wsg50", 0].sum() == 0


def test_perturbed_pairs_are_one_objects_designs_that_differ_a_little(three_objects, tiny_cfg):
    """Perturbed imprint pairs come after the other pairs without changing them, are feasible, and
    move further from the imprint as their peak rises."""
    from f2f_jax.dataset import PERTURBED, pretraining_pairs
    from f2f_jax.geometry import is_feasible

    tsdfs, _ = three_objects
    plain = pretraining_pairs(tsdfs, 2, np.random.default_rng([0, 2]), tiny_cfg, n_cut=1)
    more = pretraining_pairs(tsdfs, 2, np.random.default_rng([0, 2]), tiny_cfg, n_cut=1, n_perturbed=3,
                             perturb_rng=np.random.default_rng([0, 2, 1]))
    assert [k for *_, k in more] == [k for *_, k in plain] + [PERTURBED] * 3
    for (a, b, _), (c, d, _) in zip(plain, more):
        assert np.array_equal(a, c) and np.array_equal(b, d)
    imprint_left, imprint_right = plain[0][:2]
    flipped = []
    for left, right, _ in more[len(plain):]:
        assert is_feasible(left, tiny_cfg.geometry) and is_feasible(right, tiny_cfg.geometry)
        flipped.append(np.count_nonzero((left < 0) != (imprint_left < 0))
                       + np.count_nonzero((right < 0) != (imprint_right < 0)))
    assert 0 < flipped[0] < flipped[-1]  # the first is nearly the imprint, the last clearly another design
    with pytest.raises(ValueError, match="perturb_rng"):
        pretraining_pairs(tsdfs, 2, np.random.default_rng(0), tiny_cfg, n_perturbed=1)


def test_dataset_stores_perturbed_pairs_beside_the_others(tmp_path, three_objects, tiny_cfg):
    tsdfs, names = three_objects
    store = GraspStore(tmp_path / "store")
    summary = build_grasp_dataset(tsdfs[:1], names[:1], store, cfg=tiny_cfg, n_cut=0, n_perturbed=2,
                                  progress=False)
    data = store.read(("kind", "outcome"))
    assert list(data["kind"]) == ["imprint", "wsg50", "perturbed", "perturbed"]
    assert summary["perturbed"]["pairs"] == 2
    # the sphere's imprint holds, and so does its least perturbed variant; the flat pads drop it
    assert data["outcome"][0, 0] == 1 and data["outcome"][2, 0] == 1 and data["outcome"][1, 0] == 0
    with pytest.raises(ValueError, match="n_perturbed"):
        build_grasp_dataset(tsdfs[:1], names[:1], store, cfg=tiny_cfg, n_perturbed=-1, progress=False)


def test_make_dataset_refuses_to_mix_settings_in_one_directory(tmp_path, capsys):
    """A rerun of make_dataset.py goes on only with the settings its rows were made with: other cut
    or perturbed pair counts would leave objects with different pairs in one store."""
    import json

    from f2f_jax.cli import make_dataset

    out = tmp_path / "ds"
    out.mkdir()
    (out / "dataset.json").write_text(json.dumps({
        "config": "tiny", "seed": 0, "sim_preset": "fast", "cut_pairs": 1, "perturbed_pairs": 0,
        "backend": "mujoco"}))
    with pytest.raises(SystemExit) as exc:
        make_dataset.main(["--out", str(out), "--config", "tiny", "--cut-pairs", "1", "--perturbed-pairs", "4"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.split("error:", 1)[1]
    assert "--perturbed-pairs 0" in err and "--perturbed-pairs 4" in err and "--cut-pairs" not in err
    assert sorted(p.name for p in out.iterdir()) == ["dataset.json"]  # nothing made, nothing changed
    # a dataset whose perturbed pairs had another peak (a flag up to commit dd4f091) is refused
    (out / "dataset.json").write_text(json.dumps({
        "config": "tiny", "seed": 0, "sim_preset": "fast", "cut_pairs": 1, "perturbed_pairs": 4,
        "perturbed_peak": 0.6, "backend": "mujoco"}))
    with pytest.raises(SystemExit):
        make_dataset.main(["--out", str(out), "--config", "tiny", "--cut-pairs", "1", "--perturbed-pairs", "4"])
    assert "peak 0.6" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["dataset.json"]
    with pytest.raises(SystemExit):
        make_dataset.main(["--out", str(out), "--config", "tiny", "--cut-pairs", "-1"])


def test_rows_share_their_objects_volume_and_read_back_as_stored(tmp_path):
    """read_rows with the run's objects: every field as a plain read gives it, the object volumes
    one copy per object; a store of another object set is refused."""
    from f2f_jax.errors import F2FError
    from f2f_jax.train.run_data import SharedVolumes, read_rows

    rng = np.random.default_rng(0)
    objects = rng.uniform(-1, 1, (3, 4, 4, 4)).astype(np.float32)
    store = GraspStore(tmp_path / "store")
    pick = np.array([2, 2, 0, 1, 2])
    for cycle, rows in ((1, pick[:3]), (2, pick[3:])):
        store.append(objects[rows], rng.uniform(-1, 1, (len(rows), 4, 4, 4)), rng.uniform(-1, 1, (len(rows), 4, 4, 4)),
                     rng.integers(0, 2, (len(rows), 11)), kind="generated", names=[f"o{i}" for i in rows],
                     cycle=cycle)
    names = ["o0", "o1", "o2"]
    plain = read_rows(store, lambda c, k: c >= 1)
    shared = read_rows(store, lambda c, k: c >= 1, objects=(objects.astype(np.float16), names))
    assert isinstance(shared["object"], SharedVolumes) and shared["object"].shape == plain["object"].shape
    for k in plain:
        got = shared[k][np.arange(len(pick))] if k == "object" else shared[k]
        np.testing.assert_array_equal(got, plain[k])
        assert got.dtype == plain[k].dtype
    assert len(shared["object"]) == 5 and shared["object"].table.shape[0] == 3
    later = read_rows(store, lambda c, k: c == 2, objects=(shared["object"].table, names))
    joined = read_rows(store, lambda c, k: c == 1, objects=(shared["object"].table, names))["object"]
    np.testing.assert_array_equal(joined.concatenate(later["object"])[[0, 4]], plain["object"][[0, 4]])
    with pytest.raises(F2FError, match="not the run's object"):
        read_rows(store, lambda c, k: c >= 1, objects=(objects[::-1].astype(np.float16), names))
    with pytest.raises(F2FError, match="not the run's"):
        read_rows(store, lambda c, k: c >= 1, objects=(objects[:2].astype(np.float16), names[:2]))
