"""The grasp scene: the gripper MJCF, piece placement in the config.py frames, collision filtering,
the fixed layout and the jaw openings at t = 0.  No trials run here (see test_sim_physics.py)."""

import mujoco
import numpy as np
import pytest
import trimesh

from f2f_jax.errors import DecompositionError
from f2f_jax.geometry import finger_pose, imprint_fingers, mesh_to_tsdf, tsdf_to_mesh, wsg50_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import Hulls, pad_hulls
from f2f_jax.sim import GRIPPER_XML, GraspRunner, build_model, describe_layout, scene_ids
from f2f_jax.sim.scene import FINGER_BIT, finger_object_distance


def box_corners(lo, hi) -> np.ndarray:
    grid = np.meshgrid(*zip(lo, hi), indexing="ij")
    return np.stack([g.ravel() for g in grid], 1).astype(np.float64)


def world_vertices(model, data, geom) -> np.ndarray:
    """[n, 3] world vertices of a mesh geom at the current kinematics."""
    mesh = model.geom_dataid[geom]
    adr, num = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    local = model.mesh_vert[adr: adr + num]
    return local @ data.geom_xmat[geom].reshape(3, 3).T + data.geom_xpos[geom]


@pytest.fixture(scope="module")
def sphere_hulls(sphere_tsdf, cfg):
    # stand-in for coacd: a sphere is convex, one hull of its surface is its collision shape
    return pad_hulls([tsdf_to_mesh(sphere_tsdf, cfg.geometry).vertices], cfg.geometry.object_hulls,
                     cfg.geometry.hull_vertices)


@pytest.fixture(scope="module")
def wsg_hulls(cfg):
    left, right = wsg50_fingers(cfg)
    return finger_hulls(left, cfg), finger_hulls(right, cfg)


@pytest.fixture(scope="module")
def sphere_model(sphere_hulls, wsg_hulls, cfg):
    return build_model(sphere_hulls, *wsg_hulls, cfg)


def test_gripper_xml_compiles_alone_with_wsg50_proportions_and_finger_frames(cfg):
    model = mujoco.MjModel.from_xml_path(str(GRIPPER_XML))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    housing = model.geom("housing").id
    np.testing.assert_allclose(2 * model.geom_size[housing], [0.146, 0.05, 0.072])
    for side in ("left", "right"):
        joint = model.joint(f"{side}_jaw")
        # open: a 6 cm finger plus a 6 cm object turned 30 degrees, plus the margin
        assert joint.range[1] >= 0.06 + 0.03 * (np.cos(np.pi / 6) + np.sin(np.pi / 6)) + 0.004
        assert joint.range[0] < 0.0  # closing past the centre keeps the limit off the object
        act = model.actuator(f"{side}_grip")
        np.testing.assert_allclose(act.forcerange, [-cfg.sim.grip_force, cfg.sim.grip_force])
        site_rot = data.site(f"{side}_mount").xmat.reshape(3, 3)
        np.testing.assert_allclose(site_rot, finger_pose(side, 0.0, cfg)[:3, :3], atol=1e-12)
    for body in ("gripper", "left_jaw", "right_jaw"):
        assert model.body_gravcomp[model.body(body).id] == 1.0


def test_object_has_config_mass_rests_on_floor_and_turns_about_cube_axis(sphere_hulls,
                                                                          wsg_hulls, cfg):
    for yaw in (0.0, np.deg2rad(30)):
        model = build_model(sphere_hulls, *wsg_hulls, cfg, object_yaw=yaw)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        ids = scene_ids(model)
        assert model.body_mass[ids.object_body] == pytest.approx(cfg.sim.object_mass, rel=1e-6)
        verts = world_vertices(model, data, ids.object_geoms[0])
        assert verts[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # resting on the floor
        # a sphere's centre of mass lies on the cube's vertical axis at its middle height
        com = data.xipos[ids.object_body]
        np.testing.assert_allclose(com[:2], [0.0, 0.0], atol=1e-3)
        assert com[2] == pytest.approx(verts[:, 2].max() / 2, abs=1e-3)
        rot = data.xmat[ids.object_body].reshape(3, 3)
        np.testing.assert_allclose(rot[:2, 0], [np.cos(yaw), np.sin(yaw)], atol=1e-12)
    heavy = build_model(sphere_hulls, *wsg_hulls, cfg, object_mass=0.2)
    assert heavy.body_mass[scene_ids(heavy).object_body] == pytest.approx(0.2, rel=1e-6)


def test_box_object_turned_reaches_further_along_x(wsg_hulls, cfg):
    h = 0.0285
    box = pad_hulls([box_corners([-h, -h, 0.0015], [h, h, 0.0585])], 8, 32)
    reach = []
    for yaw in (0.0, np.deg2rad(30)):
        model = build_model(box, *wsg_hulls, cfg, object_yaw=yaw)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        verts = world_vertices(model, data, scene_ids(model).object_geoms[0])
        reach.append(np.abs(verts[:, 0]).max())
    assert reach[0] == pytest.approx(h, abs=1e-9)
    assert reach[1] == pytest.approx(h * (np.cos(np.pi / 6) + np.sin(np.pi / 6)), abs=1e-9)


def test_finger_pieces_are_placed_by_finger_pose(sphere_tsdf, sphere_hulls, cfg):
    left, right = imprint_fingers(sphere_tsdf, cfg)
    hulls = finger_hulls(left, cfg), finger_hulls(right, cfg)
    model = build_model(sphere_hulls, *hulls, cfg)
    data = mujoco.MjData(model)
    openings = np.array([0.07, 0.08])
    ids = scene_ids(model)
    data.qpos[ids.jaw_qpos] = openings
    mujoco.mj_forward(model, data)
    for side, mount_x, h in (("left", -openings[0], hulls[0]), ("right", openings[1], hulls[1])):
        pose = finger_pose(side, mount_x, cfg)
        for k, piece in enumerate(h.pieces()):
            want = piece @ pose[:3, :3].T + pose[:3, 3]
            got = world_vertices(model, data, model.geom(f"{side}_{k}").id)
            # MuJoCo keeps the hull's vertices (maybe reordered): compare the point sets
            dist = np.linalg.norm(got[:, None] - want[None], axis=-1)
            assert dist.min(1).max() < 1e-6 and dist.min(0).max() < 1e-6, (side, k)


def test_collision_pairs_are_finger_object_object_floor_and_left_right_fingers(
        sphere_hulls, wsg_hulls, cfg):
    """Fingers meet the object and the other jaw's fingers; the object meets the floor; nothing
    else collides, fingers never the floor."""
    model = build_model(sphere_hulls, *wsg_hulls, cfg)
    ids = scene_ids(model)
    left, right = set(ids.finger_geoms[0]), set(ids.finger_geoms[1])
    fingers, objects = left | right, set(ids.object_geoms)
    for a in range(model.ngeom):
        for b in range(a + 1, model.ngeom):
            if model.geom_bodyid[a] == model.geom_bodyid[b]:
                continue
            collide = bool((model.geom_contype[a] & model.geom_conaffinity[b])
                           or (model.geom_contype[b] & model.geom_conaffinity[a]))
            pair = {a, b}
            expected = ((len(pair & fingers) == 1 and len(pair & objects) == 1)
                        or (ids.floor_geom in pair and len(pair & objects) == 1)
                        or (len(pair & left) == 1 and len(pair & right) == 1))
            assert collide == expected, (model.geom(a).name, model.geom(b).name)


def test_layout_is_fixed_whatever_the_number_of_real_pieces(sphere_tsdf, cfg):
    layout = describe_layout(cfg)
    h = 0.02
    one = pad_hulls([box_corners([-h, -h, 0.0], [h, h, 0.04])], layout.object_pieces,
                    layout.hull_vertices)
    three = pad_hulls([box_corners([-h, -h, 0.0], [0, h, 0.04]),
                       box_corners([0, -h, 0.0], [h, 0, 0.04]),
                       box_corners([0, 0, 0.0], [h, h, 0.04])], layout.object_pieces,
                      layout.hull_vertices)
    left, right = imprint_fingers(sphere_tsdf, cfg)
    flat = wsg50_fingers(cfg)
    models = [build_model(one, finger_hulls(left, cfg), finger_hulls(right, cfg), cfg),
              build_model(three, finger_hulls(flat[0], cfg), finger_hulls(flat[1], cfg), cfg)]
    assert finger_hulls(flat[0], cfg).n_pieces < finger_hulls(left, cfg).n_pieces
    for model in models:
        assert model.ngeom == models[0].ngeom and model.nmesh == models[0].nmesh
        names = [model.geom(i).name for i in range(model.ngeom)]
        body_of = {n: model.body(model.geom_bodyid[i]).name for i, n in enumerate(names)}
        for geoms, body in ((layout.object_geoms, layout.object_body),
                            (layout.left_geoms, layout.jaw_bodies[0]),
                            (layout.right_geoms, layout.jaw_bodies[1])):
            assert all(body_of[g] == body for g in geoms)
            idx = [names.index(g) for g in geoms]
            assert idx == sorted(idx)  # slot order is geom order
    # placeholders never collide on the CPU backend; with pad_collides they would, but lie
    # where nothing reaches: no contact at the start of a grasp either way
    ids = scene_ids(models[1])
    assert len(ids.object_geoms) == 3 and len(ids.finger_geoms[0]) < layout.finger_pieces
    padded = build_model(one, finger_hulls(flat[0], cfg), finger_hulls(flat[1], cfg), cfg,
                         pad_collides=True)
    pids = scene_ids(padded)
    assert len(pids.object_geoms) == layout.object_pieces
    assert len(pids.finger_geoms[0]) == layout.finger_pieces
    runner = GraspRunner(padded, cfg)
    for yaw in (0.0, np.deg2rad(30)):
        assert runner.place(yaw) == 0
        _, touching = runner.approach()
        assert touching == 0
        mujoco.mj_step(padded, runner.data)
        for c in runner.data.contact[: runner.data.ncon].geom:
            assert not any(padded.geom(int(g)).name in ("object_1", "left_5", "right_5")
                           for g in c)


def test_flat_tips_primitive_reference_can_be_switched_on(sphere_hulls, cfg):
    model = build_model(sphere_hulls, None, None, cfg, flat_tips=True, friction=0.3)
    ids = scene_ids(model)
    for side in (0, 1):
        names = [model.geom(int(g)).name for g in ids.finger_geoms[side]]
        assert names == [("left", "right")[side] + "_tip"]
        tip = model.geom(names[0])
        assert tip.contype[0] == FINGER_BIT and tip.friction[0] == pytest.approx(0.3)


def test_bad_hulls_are_refused_with_clear_errors(sphere_hulls, wsg_hulls, cfg):
    empty = Hulls(np.zeros((8, 32, 3), np.float32), np.zeros(8, np.int32))
    with pytest.raises(DecompositionError, match="object hulls: no convex piece"):
        build_model(empty, *wsg_hulls, cfg)
    flat = np.zeros((8, 32, 3), np.float32)
    flat[0, :4] = [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0]]  # a square: no volume
    counts = np.zeros(8, np.int32)
    counts[0] = 4
    with pytest.raises(DecompositionError, match="spans no volume"):
        build_model(Hulls(flat, counts), *wsg_hulls, cfg)
    nan = sphere_hulls.vertices.copy()
    nan[0, 0, 0] = np.nan
    with pytest.raises(DecompositionError, match="NaN"):
        build_model(Hulls(nan, sphere_hulls.counts), *wsg_hulls, cfg)


def test_jaw_opening_is_the_gap_along_the_closing_axis_plus_the_margin(sphere_model, cfg):
    runner = GraspRunner(sphere_model, cfg)
    runner.place(0.0)
    runner.advance(cfg.sim.steps(cfg.sim.settle_time))
    openings, touching = runner.approach()
    assert touching == 0
    margin = cfg.sim.open_margin
    for side in (0, 1):
        # flat tip against a sphere: the nearest points lie on the closing axis, so the Euclidean
        # distance is the gap along x; lines 1 mm apart find it to within a fraction of a mm
        gap = finger_object_distance(sphere_model, runner.data, runner.ids, side)
        assert margin - 1e-3 < gap < margin + 1e-3
    # the 3 cm tips and the ~2.85 cm sphere radius set the openings; the sphere's 32-vertex
    # hull tips onto a face while it settles, which shifts and narrows it by a millimetre or two
    assert openings.sum() == pytest.approx(2 * (0.03 + 0.0285 + margin), abs=3e-3)


def l_shape_mesh() -> trimesh.Trimesh:
    """Two boxes in an L (seen from above): concave, so its imprint has several levels."""
    a = trimesh.creation.box([0.06, 0.025, 0.05])
    a.apply_translation([0.0, -0.0175, 0.025])
    b = trimesh.creation.box([0.025, 0.06, 0.05])
    b.apply_translation([0.0175, 0.0, 0.025])
    return trimesh.util.concatenate([a, b])


@pytest.mark.parametrize("shape", ["sphere", "l_shape"])
def test_no_finger_touches_the_object_at_t0_or_when_closing_starts(shape, sphere_tsdf, cfg):
    if shape == "sphere":
        obj = sphere_tsdf
    else:
        obj = mesh_to_tsdf(l_shape_mesh(), cfg.geometry, name="l_shape")
    solid_hull = tsdf_to_mesh(obj, cfg.geometry).vertices
    # the L as two convex pieces (what coacd would give), the sphere as one
    if shape == "l_shape":
        inner = 0.005 * 0.95 - 0.001  # the inner corner after normalisation, less a voxel
        pieces = [solid_hull[solid_hull[:, 1] <= -inner], solid_hull[solid_hull[:, 0] >= inner]]
    else:
        pieces = [solid_hull]
    obj_hulls = pad_hulls(pieces, cfg.geometry.object_hulls, cfg.geometry.hull_vertices)
    fingers = [imprint_fingers(obj, cfg), wsg50_fingers(cfg)]
    yaws = [0.0] + [np.deg2rad(a) for a in cfg.sim.robustness_angles_deg]
    for left, right in fingers:
        model = build_model(obj_hulls, finger_hulls(left, cfg), finger_hulls(right, cfg), cfg)
        runner = GraspRunner(model, cfg)
        for yaw in yaws:
            assert runner.place(yaw) == 0, (shape, yaw)  # t = 0, jaws fully open
            runner.advance(cfg.sim.steps(cfg.sim.settle_time))
            openings, touching = runner.approach()  # jaws moved in, about to close
            assert touching == 0, (shape, yaw)
            assert runner.data.ncon == 0 or np.all(
                np.isin(runner.data.contact.geom[: runner.data.ncon], [runner.ids.floor_geom,
                                                                      *runner.ids.object_geoms]))
            for side in (0, 1):
                assert finger_object_distance(model, runner.data, runner.ids, side) > 0.0
            assert np.all(openings <= runner.ids.jaw_range[:, 1])


def test_imprint_fingers_meet_the_object_one_margin_after_closing_starts(sphere_tsdf,
                                                                         sphere_hulls, cfg):
    """The opening is the gap along the closing axis, not a Euclidean distance: an imprint
    finger's rim passes beside the sphere, so the nearest points mislead."""
    left, right = imprint_fingers(sphere_tsdf, cfg)
    model = build_model(sphere_hulls, finger_hulls(left, cfg), finger_hulls(right, cfg), cfg)
    runner = GraspRunner(model, cfg)
    ids = runner.ids
    runner.place(0.0)
    runner.advance(cfg.sim.steps(cfg.sim.settle_time))
    openings, _ = runner.approach()
    data = runner.data
    data.ctrl[ids.grip_act] = ids.jaw_range[:, 0]
    met = [None, None]
    for _ in range(400):  # the jaws close at ~0.1 m/s: 0.2 mm per step
        mujoco.mj_step(model, data)
        for side in (0, 1):
            geoms = data.contact.geom[: data.ncon]
            if met[side] is None and np.isin(geoms, ids.finger_geoms[side]).any():
                met[side] = data.qpos[ids.jaw_qpos[side]]
        if None not in met:
            break
    travel = openings - np.array(met)
    margin = cfg.sim.open_margin
    assert np.all(travel > margin - 1e-3) and np.all(travel < margin + 1.5e-3), travel


def test_hull_slot_k_becomes_geom_k_even_with_gaps(wsg_hulls, cfg):
    """A batched backend swaps per-slot data; so a slot keeps its geom whatever the others hold."""
    h = 0.02
    vertices = np.zeros((8, 32, 3), np.float32)
    counts = np.zeros(8, np.int32)
    for k, lo_x in ((0, -h), (2, 0.0)):
        corners = box_corners([lo_x, -h, 0.0], [lo_x + h, h, 0.04])
        vertices[k, :8], vertices[k, 8:], counts[k] = corners, corners[0], 8
    model = build_model(Hulls(vertices, counts), *wsg_hulls, cfg)
    ids = scene_ids(model)
    assert [model.geom(int(g)).name for g in ids.object_geoms] == ["object_0", "object_2"]
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert world_vertices(model, data, model.geom("object_2").id)[:, 0].min() > -1e-9


def test_host_line_extents_are_the_shared_rule_bit_for_bit():
    """JawOpener's host extents (facets split by the sign of n_x) are ``x_extent``'s to the bit,
    also for boxes (facets parallel to the lines) and turns by right angles."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.transform import Rotation

    from f2f_jax.sim.opening import _host_extent, x_extent

    rng = np.random.default_rng(3)
    y = np.arange(-0.03, 0.03, 0.001)[:, None] + 1e-4
    z = np.arange(0.0, 0.06, 0.001)[None, :]
    for trial in range(120):
        if trial % 3 == 0:
            points = box_corners(-rng.uniform(0.002, 0.02, 3), rng.uniform(0.002, 0.02, 3))
        else:
            points = rng.normal(size=(rng.integers(4, 33), 3)) * 0.01
        turn = Rotation.from_euler("z", 90 * trial, degrees=True) if trial % 4 == 0 else \
            Rotation.random(random_state=trial)
        args = (ConvexHull(points).equations, turn.as_matrix(), rng.normal(size=3) * 0.01, y, z)
        for a, b in zip(x_extent(*args, np), _host_extent(*args)):
            assert a.shape == b.shape and np.array_equal(a, b)


def test_models_from_the_parsed_gripper_and_remembered_volumes_are_the_first_ones(
        sphere_hulls, wsg_hulls, cfg, monkeypatch):
    """build_model copies the gripper spec parsed once and remembers object piece volumes: the
    compiled model is byte for byte the one parsed from the file with every volume computed."""
    from f2f_jax.sim import scene

    def saved(model):
        buf = np.empty(mujoco.mj_sizeModel(model), np.uint8)
        mujoco.mj_saveModel(model, None, buf)
        return buf.tobytes()

    twice = [saved(build_model(sphere_hulls, *wsg_hulls, cfg)) for _ in range(2)]
    monkeypatch.setattr(scene, "_gripper_spec", lambda: mujoco.MjSpec.from_file(str(GRIPPER_XML)))
    monkeypatch.setattr(scene, "_volumes", type(scene._volumes)())
    assert twice[0] == twice[1] == saved(build_model(sphere_hulls, *wsg_hulls, cfg))


def test_finger_object_contacts_and_remembered_planes_match_their_first_forms(
        sphere_tsdf, cfg):
    """The contact count (sets of geom ids) is np.isin's count; a second opener on the same
    object reuses its pieces' planes and gives the same openings."""
    from f2f_jax.sim.opening import JawOpener
    from f2f_jax.sim.scene import finger_object_contacts

    left, right = imprint_fingers(sphere_tsdf, cfg.geometry)
    hulls = pad_hulls([tsdf_to_mesh(sphere_tsdf, cfg.geometry).vertices], cfg.geometry.object_hulls,
                      cfg.geometry.hull_vertices)
    model = build_model(hulls, finger_hulls(left, cfg), finger_hulls(right, cfg), cfg)
    runner = GraspRunner(model, cfg)
    runner.place(0.0)
    runner.advance(cfg.sim.steps(cfg.sim.settle_time))
    runner.approach()
    d, ids = runner.data, runner.ids
    d.ctrl[ids.grip_act] = ids.jaw_range[:, 0]
    runner.advance(cfg.sim.steps(cfg.sim.close_time))
    mujoco.mj_forward(model, d)
    geoms = d.contact.geom[: d.ncon]
    fingers = ids.all_finger_geoms
    expected = np.count_nonzero((np.isin(geoms[:, 0], fingers) & np.isin(geoms[:, 1], ids.object_geoms))
                                | (np.isin(geoms[:, 1], fingers) & np.isin(geoms[:, 0], ids.object_geoms)))
    assert expected > 0 and finger_object_contacts(model, d, ids) == expected
    runner.place(0.0)
    first, second = runner.opener, JawOpener(model, ids, cfg)
    assert all(second._local[int(g)] is first._local[int(g)] for g in ids.object_geoms)
    np.testing.assert_array_equal(first(mujoco.MjData(model), 0.003), second(mujoco.MjData(model), 0.003))
