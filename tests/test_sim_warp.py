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


def test_pair_filter_keeps_every_pair_that_touches(wb, sphere_models, tiny_cfg):
    """The pair list leaves out only pairs that never touch: at openings across the jaws' whole
    range (fingers crossing), every contact plain MuJoCo finds between real pieces of the two
    jaws is a pair the list keeps; placeholder slots of every world drop out too."""
    import itertools

    import mujoco

    from f2f_jax.sim.scene import scene_ids

    ids = scene_ids(sphere_models[0])
    table = wb.MeshTable.of(sphere_models)
    fields = wb.candidate_fields(sphere_models, table)
    lists = []
    for c, m in enumerate(sphere_models):
        ch = wb.WorldChunk(m, table, {k: v[[c]] for k, v in fields.items()}, "cpu", ids.finger_geoms)
        kept = {tuple(p) for p in ch.m.nxn_geom_pair_filtered.numpy()}
        lists.append(kept)
        assert ch.listed_pairs == len(kept) < ch.all_pairs
        real = np.asarray(m.geom_rgba)[:, 3] > 0
        jaw = {int(g): side for side in (0, 1) for g in ids.finger_geoms[side]}
        d, seen = mujoco.MjData(m), 0
        d.qpos[ids.object_qpos + 2] = 1.0  # the object out of the way
        low, high = ids.jaw_range[0]
        for q in itertools.product(np.linspace(low - 0.005, 0.05, 12), repeat=2):
            d.qpos[ids.jaw_qpos] = q
            mujoco.mj_forward(m, d)
            for a, b in (sorted(c.geom) for c in d.contact[: d.ncon]):
                if real[a] and real[b] and {jaw.get(a), jaw.get(b)} == {0, 1}:
                    seen += 1
                    assert (a, b) in kept
        assert seen > 0  # the fingers do meet when they cross
    both = wb.WorldChunk(sphere_models[0], table, fields, "cpu", ids.finger_geoms)
    assert {tuple(p) for p in both.m.nxn_geom_pair_filtered.numpy()} == lists[0] | lists[1]


def test_pair_filter_leaves_the_physics_bit_for_bit(wb, sphere_models, tiny_cfg):
    """The grasp program (settle, approach, close, lift, hold) of the pads and the imprint ends
    in the same state, bit for bit, with and without the pair filter; fewer pairs are tested."""
    out, sims = [], []
    for pair_filter in (False, True):
        sim = wb.WarpGraspSimulator(tiny_cfg, devices=["cpu"], pair_filter=pair_filter)
        table = sim.prepare(sphere_models)
        which = np.array([0, 1])
        out.append(sim._grasp(sphere_models, table, which, np.zeros(2), None))
        sims.append(sim)
    for k in ("qpos", "qvel", "act", "qacc_warmstart"):
        np.testing.assert_array_equal(out[0][3][k], out[1][3][k])
    assert out[0][0].tolist() == out[1][0].tolist() == [False, True]
    listed = [s.pair_sums[2] / s.pair_sums[1] for s in sims]
    assert listed[1] < listed[0] and sims[0].pair_sums[0] >= sims[1].pair_sums[0]


@pytest.mark.slow
def test_rest_stop_ends_resting_phases_early_on_the_clear_cases(wb, sphere_models, tiny_cfg):
    """rest_stop (off by default) under the fast preset: the pads still drop the sphere, the
    imprint still holds it through every trial, in fewer steps; the reference preset (rest_speed
    0) and the default take every phase in full."""
    from f2f_jax.config import with_sim_preset

    fast = with_sim_preset(tiny_cfg, "fast")
    full = wb.WarpGraspSimulator(fast, devices=["cpu"])
    assert not full.rest_stop
    res = wb.WarpGraspSimulator(fast, devices=["cpu"], rest_stop=True).run(sphere_models)
    assert res["outcome"][0].sum() == 0 and res["outcome"][1].sum() == 11
    assert (res["steps"] < [full.grasp_steps, 7 * full.grasp_steps + 4 * full.push_steps]).all()
    ref = wb.WarpGraspSimulator(with_sim_preset(tiny_cfg, "reference"), devices=["cpu"],
                                rest_stop=True)
    table = ref.prepare(sphere_models[:1])
    ref._grasp(sphere_models[:1], table, np.array([0]), np.zeros(1), None)
    assert ref.last_steps == ref.grasp_steps


@pytest.mark.slow
def test_pair_filter_keeps_every_outcome_of_mixed_triples(wb, tiny_cfg):
    """All 11 trials of three builtin triples (imprint, WSG50, cut) tiled to four worlds: the
    same outcomes, steps and failures with and without the pair filter."""
    from f2f_jax.bench.agreement import builtin_triples

    pool, triples = builtin_triples(3, 0, tiny_cfg)
    models = [build_model(object_hulls(pool[t["object"]], tiny_cfg), finger_hulls(t["left"], tiny_cfg),
                          finger_hulls(t["right"], tiny_cfg), tiny_cfg, pad_collides=True)
              for t in triples]
    models.append(models[0])
    runs = [wb.WarpGraspSimulator(tiny_cfg, devices=["cpu"], pair_filter=f).run(models)
            for f in (False, True)]
    for k in ("outcome", "steps", "unstable"):
        np.testing.assert_array_equal(runs[0][k], runs[1][k])
    assert runs[0]["outcome"][0].sum() > 0  # the imprint holds: pushes and turned grasps ran
    assert runs[1]["listed_pairs"] < runs[0]["listed_pairs"]
