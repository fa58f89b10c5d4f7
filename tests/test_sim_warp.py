"""The MuJoCo Warp backend on warp's CPU device: per-world geometry and the clear cases (tiny
phases).  Skipped, with the reason, where the ``warp`` extra is not installed; the
missing-extra error itself is tested everywhere."""

import importlib
import sys

import numpy as np
import pytest

from f2f_jax.errors import MissingExtraError
from f2f_jax.geometry import imprint_fingers, wsg50_fingers
from f2f_jax.geometry.coacd_pieces import object_hulls
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.sim.protocol import run_trials
from f2f_jax.sim.scene import build_model


def test_missing_extra_names_the_install_command(monkeypatch, sphere_tsdf, tiny_cfg):
    """As on a machine without the extra (warp's modules unimportable), whether or not it is
    installed here: the error comes before any work and names the install command."""
    import f2f_jax.sim
    from f2f_jax.sim import evaluate

    for name in ("warp", "mujoco_warp"):
        monkeypatch.setitem(sys.modules, name, None)  # None in sys.modules: ImportError
    for module in ("warp_batch", "warp_worlds"):  # as if never imported
        monkeypatch.delitem(sys.modules, f"f2f_jax.sim.{module}", raising=False)
        monkeypatch.delattr(f2f_jax.sim, module, raising=False)
    left, right = imprint_fingers(sphere_tsdf, tiny_cfg.geometry)
    with pytest.raises(MissingExtraError, match=r'pip install -e "\.\[warp\]"'):
        evaluate([sphere_tsdf], [left], [right], cfg=tiny_cfg, backend="warp")


@pytest.fixture(scope="module")
def wb():
    pytest.importorskip("mujoco_warp", reason="the warp extra is not installed: "
                                              'pip install -e ".[warp]"')
    return importlib.import_module("f2f_jax.sim.warp_batch")


@pytest.fixture(scope="module")
def sphere_models(sphere_tsdf, tiny_cfg):
    """Flat pads first, the imprint second: the imprint's meshes sit past the pads' in the
    shared mesh table, so its grasp holds only if every world reads its own meshes."""
    hulls = object_hulls(sphere_tsdf, tiny_cfg)
    return [build_model(hulls, finger_hulls(left, tiny_cfg), finger_hulls(right, tiny_cfg),
                        tiny_cfg, pad_collides=True)
            for left, right in (wsg50_fingers(), imprint_fingers(sphere_tsdf))]


def test_mesh_table_keeps_every_candidates_meshes(wb, sphere_models):
    table = wb.MeshTable.of(sphere_models)
    f = table.fields
    assert table.sizes["nmesh"] == sum(m.nmesh for m in sphere_models)
    assert table.sizes["nmeshvert"] == len(f["mesh_vert"])
    for c, m in enumerate(sphere_models):
        for i in range(m.nmesh):
            j = table.offset[c] + i
            got = f["mesh_vert"][f["mesh_vertadr"][j]: f["mesh_vertadr"][j] + f["mesh_vertnum"][j]]
            own = m.mesh_vert[m.mesh_vertadr[i]: m.mesh_vertadr[i] + m.mesh_vertnum[i]]
            np.testing.assert_array_equal(got, own)
            gadr = f["mesh_graphadr"][j]
            n = 2 + 2 * m.mesh_vertnum[i]  # the graph's header and per-vertex tables
            np.testing.assert_array_equal(f["mesh_graph"][gadr: gadr + n],
                                          m.mesh_graph[m.mesh_graphadr[i]: m.mesh_graphadr[i] + n])
    ids = wb.candidate_fields(sphere_models, table)["geom_dataid"][np.array([1, 0, 1])]
    assert ids.shape == (3, sphere_models[0].ngeom)
    # world 1 is candidate 0: its real meshes keep their ids; worlds 0 and 2 read candidate 1's
    mesh = np.asarray(sphere_models[0].geom_dataid) >= 0
    real = mesh & (np.asarray(sphere_models[1].geom_rgba)[:, 3] > 0)
    assert (ids[0][real] >= sphere_models[0].nmesh).all() and (ids[1][real] < sphere_models[0].nmesh).all()
    assert (ids[0] == ids[2]).all()


def test_device_openings_follow_the_host_rule(wb, sphere_models, tiny_cfg):
    """The approach's openings computed on the device equal opening.JawOpener's, per world, for
    the object at rest and turned by 30 degrees."""
    import mujoco

    from f2f_jax.sim.opening import JawOpener
    from f2f_jax.sim.scene import object_quat

    sim = wb.WarpGraspSimulator(tiny_cfg, devices=["cpu"])
    table = sim.prepare(sphere_models)
    ids = sim.ids
    which = np.array([0, 1, 1])
    yaws = np.deg2rad([0.0, 0.0, 30.0])
    qpos = np.stack([np.array(sphere_models[c].qpos0) for c in which])
    for w, yaw in enumerate(yaws):
        qpos[w, ids.object_qpos + 3: ids.object_qpos + 7] = object_quat(yaw)
    ch = wb.WorldChunk(sphere_models[0], table, {k: v[which] for k, v in sim.fields.items()}, "cpu")
    ch.keep_finger_poses(qpos, ids.jaw_qpos)
    ch.set_state(qpos=qpos)
    ch.kinematics()
    got = sim._device_openings(ch)
    for w, c in enumerate(which):
        data = mujoco.MjData(sphere_models[c])
        data.qpos[:] = qpos[w]
        want = JawOpener(sphere_models[c], ids, tiny_cfg)(data, tiny_cfg.sim.open_margin)
        np.testing.assert_allclose(got[w], want, atol=2e-5)
    # the imprint's fingers wrap the sphere: it opens wider than the pads stand off
    assert (got[1] > got[0]).all()


@pytest.mark.slow
def test_warp_trials_agree_with_mujoco_on_the_clear_cases(wb, sphere_models, tiny_cfg):
    cpu = [run_trials(m, tiny_cfg).outcome for m in sphere_models]
    assert cpu[0].sum() == 0 and cpu[1].sum() == 11  # flat pads drop the sphere; the imprint holds it
    res = wb.WarpGraspSimulator(tiny_cfg, devices=["cpu"]).run(sphere_models)
    assert res["outcome"][0].sum() == 0
    # the imprint holds through every trial as on plain MuJoCo, from a mesh table it shares
    assert res["outcome"][1].tolist() == cpu[1].tolist()
    assert res["unstable"].tolist() == [0, 0] and res["overflowed"] == 0
    s = tiny_cfg.sim
    assert res["steps"][0] < res["steps"][1]  # the pads' failed grasp cost one trial only
    warp_worlds = importlib.import_module("f2f_jax.sim.warp_worlds")  # the buffers each world has
    assert res["peak_pairs"] < warp_worlds.CONTACTS_PER_WORLD
    assert res["peak_rows"] < warp_worlds.ROWS_PER_WORLD
    assert s.n_trials == 11


def test_evaluate_warp_maps_outcomes_to_feasible_candidates(wb, monkeypatch, sphere_tsdf, tiny_cfg):
    from f2f_jax.sim import evaluate, evaluate_with_info

    seen = []

    def fake(models, cfg):
        seen.extend(models)
        out = np.zeros((len(models), 11), np.uint8)
        out[:, 0] = np.arange(1, len(models) + 1)
        return dict(outcome=out, steps=np.full(len(models), 5), unstable=np.zeros(len(models)))

    monkeypatch.setattr(wb, "evaluate_models", fake)
    left, right = imprint_fingers(sphere_tsdf, tiny_cfg.geometry)
    out, info = evaluate_with_info([sphere_tsdf] * 3, [np.ones_like(left), left, left], [right] * 3,
                                   cfg=tiny_cfg, backend="warp")
    assert len(seen) == 2 and out[:, 0].tolist() == [0, 1, 2]
    assert info.steps.tolist() == [0, 5, 5]
    with pytest.raises(NotImplementedError, match="object_xy"):
        evaluate([sphere_tsdf], [left], [right], cfg=tiny_cfg, backend="warp", object_xy=(0.01, 0))
    with pytest.raises(ValueError, match="executor='ray'"):
        evaluate([sphere_tsdf], [left], [right], cfg=tiny_cfg, backend="warp", executor="ray")
