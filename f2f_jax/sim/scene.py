"""The grasp scene as a MuJoCo model: WSG50-like gripper, two fingers and an object on a floor.

``build_model`` loads ``assets/wsg50/wsg50.xml`` into an ``mujoco.MjSpec``, sets every physical
constant from ``SimConfig`` and adds one convex mesh geom per hull piece: the object's pieces on a
free body, each finger's pieces on its jaw.  Every body gets the same number of geoms whatever the
number of real pieces (unused slots hold a tiny tetrahedron that never collides), so all models
built from one ``describe_layout`` share one structure: what a batched simulator needs.

Frames are those of ``f2f_jax.config``: the object's hull vertices are in its volume's local frame,
which is the world frame of the object resting on the floor; finger vertices are in the finger
frame ``(u, v, w)`` and are placed on the jaw by the rotation of ``geometry.finger_pose``.
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.config import Config
from f2f_jax.errors import DecompositionError
from f2f_jax.geometry.fingers import finger_pose
from f2f_jax.geometry.hulls import Hulls

ASSET_DIR = Path(__file__).resolve().parents[1] / "assets" / "wsg50"
GRIPPER_XML = ASSET_DIR / "wsg50.xml"

# Collision bits (see the XML's header): the floor and the fingers each have one bit, the object
# accepts both; the fingers accept the finger bit too, so they also meet the other jaw's fingers
# (as real fingers and the original's gripper, self-collision on, do: no design closes by passing
# through its partner); nothing else collides.
FLOOR_BIT = 1
FINGER_BIT = 2
OBJECT_AFFINITY = FLOOR_BIT | FINGER_BIT

# A placeholder piece: a 1 mm tetrahedron.  It fills an unused slot so the layout stays fixed.
_PAD_EDGE = 0.001
_PAD_TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64) * _PAD_EDGE
# Finger placeholders sit 5 cm behind the mount plate (w = -0.05), where no object can be.
_FINGER_PAD_W = -0.05

SIDES = ("left", "right")


@dataclass(frozen=True)
class SceneLayout:
    """The fixed structure shared by every model built for one configuration.

    object_pieces, finger_pieces: geom slots on the object body and on each jaw.
    hull_vertices: vertices per piece (the batched backend pads mesh data to this).
    object_geoms, left_geoms, right_geoms: geom names per slot, in slot order.
    """

    object_pieces: int
    finger_pieces: int
    hull_vertices: int
    object_geoms: tuple[str, ...]
    left_geoms: tuple[str, ...]
    right_geoms: tuple[str, ...]
    object_body: str = "object"
    jaw_bodies: tuple[str, str] = ("left_jaw", "right_jaw")
    jaw_joints: tuple[str, str] = ("left_jaw", "right_jaw")
    lift_joint: str = "lift"
    actuators: tuple[str, str, str] = ("left_grip", "right_grip", "lift")


def describe_layout(cfg: Config | None = None, *, object_pieces: int | None = None,
                    finger_pieces: int | None = None) -> SceneLayout:
    """The layout (pieces per body, vertices per piece, geom names) of models built with ``cfg``.

    Defaults come from ``GeometryConfig``: object_hulls (8), finger_hulls (16), hull_vertices (32).
    """
    g = (cfg or Config()).geometry
    ko = object_pieces or g.object_hulls
    kf = finger_pieces or g.finger_hulls
    return SceneLayout(
        object_pieces=ko, finger_pieces=kf, hull_vertices=g.hull_vertices,
        object_geoms=tuple(f"object_{k}" for k in range(ko)),
        left_geoms=tuple(f"left_{k}" for k in range(kf)),
        right_geoms=tuple(f"right_{k}" for k in range(kf)),
    )


@dataclass(frozen=True)
class SceneIds:
    """Indices into one compiled model that the trials need.

    object_body: body id; object_qpos: address of the free joint's 7 qpos (xyz, quat wxyz);
    object_dof: address of its 6 dofs; jaw_qpos, jaw_dof: [2] (left, right); lift_qpos;
    grip_act: [2] actuator ids; lift_act: actuator id; lift_act_adr: its activation address;
    object_geoms: [n] geom ids of real object pieces; finger_geoms: [2] arrays of the colliding
    geom ids on each jaw; floor_geom.
    """

    object_body: int
    object_qpos: int
    object_dof: int
    jaw_qpos: np.ndarray
    jaw_dof: np.ndarray
    jaw_range: np.ndarray  # [2, 2] joint ranges (m)
    lift_qpos: int
    grip_act: np.ndarray
    lift_act: int
    lift_act_adr: int
    object_geoms: np.ndarray
    finger_geoms: tuple[np.ndarray, np.ndarray]
    floor_geom: int

    @property
    def all_finger_geoms(self) -> np.ndarray:
        return np.concatenate(self.finger_geoms)

    @functools.cached_property
    def geom_sets(self) -> tuple[frozenset, frozenset]:
        """(finger geom ids, object geom ids) as sets of ints: ``finger_object_contacts``' test."""
        return (frozenset(self.all_finger_geoms.tolist()), frozenset(self.object_geoms.tolist()))


def scene_ids(model: mujoco.MjModel) -> SceneIds:
    """Look up the bodies, joints, actuators and colliding geoms of a model from ``build_model``."""
    def jid(name):
        return model.joint(name).id

    obj = model.body("object").id
    obj_joint = int(model.body_jntadr[obj])
    jaws = [jid("left_jaw"), jid("right_jaw")]
    geom_body = model.geom_bodyid
    colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    finger_geoms = tuple(
        np.nonzero((geom_body == model.body(f"{s}_jaw").id) & colliding)[0].astype(np.int32)
        for s in SIDES)
    lift_act = model.actuator("lift").id
    return SceneIds(
        object_body=obj,
        object_qpos=int(model.jnt_qposadr[obj_joint]),
        object_dof=int(model.jnt_dofadr[obj_joint]),
        jaw_qpos=np.array([model.jnt_qposadr[j] for j in jaws]),
        jaw_dof=np.array([model.jnt_dofadr[j] for j in jaws]),
        jaw_range=np.array([model.jnt_range[j] for j in jaws]),
        lift_qpos=int(model.jnt_qposadr[jid("lift")]),
        grip_act=np.array([model.actuator("left_grip").id, model.actuator("right_grip").id]),
        lift_act=lift_act,
        lift_act_adr=int(model.actuator_actadr[lift_act]),
        object_geoms=np.nonzero((geom_body == obj) & colliding)[0].astype(np.int32),
        finger_geoms=finger_geoms,
        floor_geom=model.geom("floor").id,
    )


def _slot_pieces(hulls: Hulls, what: str) -> list[np.ndarray | None]:
    """Per slot of the layout: the piece's [n, 3] float64 vertices, or None for an unused slot.
    Slot k of the Hulls becomes geom ``<body>_k`` whatever the other slots hold."""
    if not isinstance(hulls, Hulls):
        raise TypeError(f"{what}: expected geometry.hulls.Hulls, got {type(hulls).__name__}")
    slots = [np.asarray(hulls.vertices[k, :n], np.float64) if n > 0 else None
             for k, n in enumerate(hulls.counts)]
    if all(p is None for p in slots):
        raise DecompositionError(f"{what}: no convex piece (all {hulls.max_pieces} slots empty)")
    for k, p in enumerate(slots):
        if p is not None and not np.all(np.isfinite(p)):
            raise DecompositionError(f"{what}: piece {k} has NaN/inf vertices")
    return slots


def _hull_volume(points: np.ndarray, what: str) -> float:
    try:
        return float(ConvexHull(points).volume)
    except (QhullError, ValueError) as exc:
        raise DecompositionError(f"{what}: a piece spans no volume ({len(points)} points): "
                                 f"{str(exc).strip().splitlines()[0]}") from None


_parsed: list[mujoco.MjSpec] = []  # the gripper's XML, parsed once per process
_lock = threading.Lock()


def _gripper_spec() -> mujoco.MjSpec:
    """A fresh MjSpec of ``GRIPPER_XML``: a copy of the one parsed once (the same spec)."""
    with _lock:
        if not _parsed:
            _parsed.append(mujoco.MjSpec.from_file(str(GRIPPER_XML)))
        return _parsed[0].copy()


# Object piece volumes by their vertices: every candidate of one object builds the same pieces.
_VOLUMES_KEPT = 64
_volumes: OrderedDict[bytes, list[float]] = OrderedDict()


def _piece_volumes(slots: list, what: str) -> list[float]:
    """``_hull_volume`` of each real piece of ``_slot_pieces``' slots, in slot order; remembered
    for the last ``_VOLUMES_KEPT`` piece sets (an error is raised again, not remembered)."""
    real = [p for p in slots if p is not None]
    key = b"".join(np.ascontiguousarray(p).tobytes() + len(p).to_bytes(4, "little") for p in real)
    with _lock:
        hit = _volumes.get(key)
        if hit is not None:
            _volumes.move_to_end(key)
            return hit
    volumes = [_hull_volume(p, f"{what} piece {k}") for k, p in enumerate(slots) if p is not None]
    with _lock:
        _volumes[key] = volumes
        while len(_volumes) > _VOLUMES_KEPT:
            _volumes.popitem(last=False)
    return volumes


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _add_piece(spec: mujoco.MjSpec, body, name: str, vertices: np.ndarray, **geom):
    spec.add_mesh(name=name, uservert=np.asarray(vertices, np.float64).ravel().tolist())
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, **geom)


def _apply_sim_config(spec: mujoco.MjSpec, cfg: Config) -> None:
    s = cfg.sim
    opt = spec.option
    opt.timestep = s.timestep  # SimConfig says why 4 ms (fast) and 2 ms (reference)
    integrators = {"euler": mujoco.mjtIntegrator.mjINT_EULER,
                   "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
    try:
        opt.integrator = integrators[s.integrator]
    except KeyError:
        raise ValueError(f"SimConfig.integrator {s.integrator!r}: choose one of "
                         f"{sorted(integrators)}") from None
    opt.solver = mujoco.mjtSolver.mjSOL_NEWTON  # few, stiff contacts: Newton converges in a few
    opt.iterations = s.iterations  # grasps are contact-rich and need a converged solve
    opt.ls_iterations = s.ls_iterations
    cones = {"elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC,
             "pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL}
    opt.cone = cones[s.cone]  # elliptic: friction limits close to Coulomb's circle
    opt.impratio = s.impratio  # stiffer friction than normal: a held object does not creep
    opt.gravity = [0.0, 0.0, -s.gravity]
    for side in SIDES:
        # damping is [linear, higher-order terms] in mujoco 3.17: keep the linear law only;
        # the jaws close at grip_force / jaw_damping = 0.1 m/s
        spec.joint(f"{side}_jaw").damping = [s.jaw_damping, 0.0, 0.0]
        act = spec.actuator(f"{side}_grip")
        act.gainprm[0] = s.jaw_kp
        act.biasprm[1] = -s.jaw_kp
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-s.grip_force, s.grip_force]  # the paper's 1 N grip
    spec.joint("lift").damping = [s.lift_damping, 0.0, 0.0]  # near-critical: zeta ~0.8
    lift = spec.actuator("lift")
    lift.gainprm[0] = s.lift_kp  # stiff: the object's weight sags the lift by 0.25 mm only
    lift.biasprm[1] = -s.lift_kp


def build_model(object_hulls: Hulls, left_hulls: Hulls | None, right_hulls: Hulls | None,
                cfg: Config | None = None, *, object_yaw: float = 0.0,
                object_mass: float | None = None, friction: float | None = None,
                object_xy=(0.0, 0.0), flat_tips: bool = False,
                pad_collides: bool = False, max_geom_pairs: int | None = None,
                max_contact_points: int | None = None) -> mujoco.MjModel:
    """Compile the grasp scene for one (object, left finger, right finger) triple.

    object_hulls: Hulls [K_o, V, 3], metres, the object volume's local frame (= world frame of the
        object resting on the floor at the grasp location).
    left_hulls, right_hulls: Hulls [K_f, V, 3], metres, finger frames (u, v, w); None leaves that
        jaw with placeholders only (e.g. with ``flat_tips``).
    object_yaw: rad, turns the object about the vertical axis through the cube's centre.
    object_mass: kg (default ``SimConfig.object_mass``); inertia from the pieces at uniform
        density, centre of mass at their centroid.
    friction: finger-object coefficient (default ``SimConfig.finger_friction``).  Finger geoms
        have ``priority=1``, so a contact takes the finger's friction, not MuJoCo's max rule.
    object_xy: (x, y) m, shifts the object on the floor.
    flat_tips: also enable the XML's primitive flat fingertips (a reference for wsg50_fingers).
    pad_collides: give placeholder pieces the collision bits of real ones (a batched backend's
        template, where a slot may be real for another candidate); they lie where nothing
        reaches: object placeholders at the centre of a real piece, finger ones behind the mount.

    max_geom_pairs: MJX's broad-phase cap on pairs per collision function (a numeric read by
        MJX; plain MuJoCo ignores it).
    max_contact_points: MJX's cap on the contacts passed to the solver (the deepest first; a
        numeric read by MJX, ignored by plain MuJoCo).

    The object's lowest point touches the floor (z = 0); the jaws start at their upper joint
    limit: ``JawOpener`` moves them in so nothing touches.  Raises DecompositionError
    for hulls without a real piece, NaN vertices or a flat piece, ValueError if MuJoCo refuses.
    """
    cfg = cfg or Config()
    s = cfg.sim
    mu = s.finger_friction if friction is None else float(friction)
    mass = s.object_mass if object_mass is None else float(object_mass)
    spec = _gripper_spec()
    _apply_sim_config(spec, cfg)
    spec.modelname = "f2f_grasp"
    spec.geom("floor").friction = [s.object_friction, 0.005, 0.0001]
    spec.geom("floor").condim = s.condim

    _add_object(spec, object_hulls, cfg, mass=mass, yaw=object_yaw, xy=object_xy,
                pad_collides=pad_collides)
    for side, hulls in zip(SIDES, (left_hulls, right_hulls)):
        _add_finger(spec, side, hulls, cfg, friction=mu, flat_tips=flat_tips,
                    pad_collides=pad_collides)
    if max_geom_pairs is not None:
        spec.add_numeric(name="max_geom_pairs", data=[float(max_geom_pairs)])
    if max_contact_points is not None:
        spec.add_numeric(name="max_contact_points", data=[float(max_contact_points)])
    try:
        return spec.compile()
    except ValueError as exc:
        raise ValueError(f"MuJoCo could not compile the grasp scene: {exc}") from None


def _add_object(spec: mujoco.MjSpec, object_hulls: Hulls, cfg: Config, *, mass: float, yaw: float,
                xy, pad_collides: bool) -> None:
    """The object: a free body whose frame is the object volume's frame, its lowest point on the
    floor, inertia from its pieces at uniform density."""
    s = cfg.sim
    slots = _slot_pieces(object_hulls, "object hulls")
    pieces = [p for p in slots if p is not None]
    volumes = _piece_volumes(slots, "object hulls")
    density = mass / sum(volumes)  # overlapping pieces count twice; coacd's overlap is small
    z_min = min(float(p[:, 2].min()) for p in pieces)
    body = spec.worldbody.add_body(name="object", pos=[xy[0], xy[1], -z_min], quat=_yaw_quat(yaw))
    body.add_freejoint(name="object")
    pad = _PAD_TETRA + pieces[int(np.argmax(volumes))].mean(0)  # inside the largest piece
    for k, piece in enumerate(slots):
        real = piece is not None
        bits = OBJECT_AFFINITY if (real or pad_collides) else 0
        _add_piece(spec, body, f"object_{k}", piece if real else pad, contype=0,
                   conaffinity=bits, density=density if real else 0.0, condim=s.condim,
                   friction=[s.object_friction, 0.005, 0.0001], group=2,
                   rgba=[0.85, 0.45, 0.2, 1.0] if real else [0, 0, 0, 0])


def _add_finger(spec: mujoco.MjSpec, side: str, hulls: Hulls | None, cfg: Config, *, friction: float,
                flat_tips: bool, pad_collides: bool) -> None:
    """One finger's pieces on its jaw, rotated from (u, v, w) into the jaw frame."""
    s = cfg.sim
    finger_geom = dict(condim=s.condim, priority=1, friction=[friction, 0.005, 0.0001], group=2)
    # the fingers also meet the other jaw's fingers (pieces on one jaw share a body, which MuJoCo
    # never collides with itself).  Not the floor: the fingers' cube reaches a voxel below it
    # (GeometryConfig.rest_offset, as the object's volume does), and a floor pressing on that
    # layer would drag the closing jaws.
    pose = finger_pose(side, 0.0, cfg)
    rot = pose[:3, :3]
    jaw = spec.body(f"{side}_jaw")
    jaw.pos = pose[:3, 3]  # the mount plane's centre at the finger cube's mid-height
    slots = ([None] * cfg.geometry.finger_hulls if hulls is None
             else _slot_pieces(hulls, f"{side} finger hulls"))
    pad = _PAD_TETRA + np.array([0.0, 0.0, _FINGER_PAD_W])
    for k, piece in enumerate(slots):
        real = piece is not None
        if real:
            _hull_volume(piece, f"{side} finger hulls piece {k}")
        bits = FINGER_BIT if (real or pad_collides) else 0
        _add_piece(spec, jaw, f"{side}_{k}", (piece if real else pad) @ rot.T, contype=bits,
                   conaffinity=FINGER_BIT if bits else 0,
                   rgba=[0.25, 0.45, 0.8, 1.0] if real else [0, 0, 0, 0], **finger_geom)
    if flat_tips:
        tip = spec.geom(f"{side}_tip")
        tip.contype = FINGER_BIT
        tip.conaffinity = FINGER_BIT
        tip.friction = [friction, 0.005, 0.0001]
        tip.condim = s.condim
        tip.group = 2

def object_quat(yaw: float) -> np.ndarray:
    """[4] (w, x, y, z) orientation of the object turned by ``yaw`` rad about world z."""
    return _yaw_quat(yaw)


def finger_object_distance(model: mujoco.MjModel, data: mujoco.MjData, ids: SceneIds,
                           side: int, distmax: float = 0.2) -> float:
    """Smallest signed distance (m) between one finger's pieces and the object's, at the current
    kinematics (``mj_kinematics`` must have run).  Negative: they intersect."""
    fingers, objects = ids.finger_geoms[side], ids.object_geoms
    if len(fingers) == 0 or len(objects) == 0:
        return distmax
    # pairs nearest first by their bounding spheres, whose gap no pair's distance is below:
    # once that gap reaches the best distance found, no later pair can beat it
    gap = (np.linalg.norm(data.geom_xpos[fingers][:, None] - data.geom_xpos[objects][None], axis=2)
           - model.geom_rbound[fingers][:, None] - model.geom_rbound[objects][None])
    order = np.argsort(gap, axis=None)
    best = distmax
    per_finger = len(objects)
    fingers, objects = fingers.tolist(), objects.tolist()  # plain ints and floats: a tight loop
    for flat, lower in zip(order.tolist(), gap.ravel()[order].tolist()):
        if lower >= best:
            break
        fg, og = fingers[flat // per_finger], objects[flat % per_finger]
        best = min(best, mujoco.mj_geomDistance(model, data, fg, og, distmax, None))
    return best


def finger_object_contacts(model: mujoco.MjModel, data: mujoco.MjData, ids: SceneIds) -> int:
    """Number of active contacts between a finger geom and an object geom in ``data``."""
    n = data.ncon
    if n == 0:
        return 0
    fingers, objects = ids.geom_sets
    return sum(1 for g0, g1 in data.contact.geom[:n].tolist()
               if (g0 in fingers and g1 in objects) or (g1 in fingers and g0 in objects))
