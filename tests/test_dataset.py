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
