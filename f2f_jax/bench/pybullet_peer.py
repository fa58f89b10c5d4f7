"""The PyBullet peer: the original Fit2Form grasp protocol, timed on the triples our backends get.

Fit2Form (CoRL 2020) scored every (left finger, object, right finger) triple in PyBullet with a
fixed script.  This module re-runs that script, written from a reading of the original code
(``environment/GraspSimulationEnv.py``, ``WSG50.py``, ``utils.py``, ``configs/default.json``), so a
benchmark can report how much faster our MuJoCo/MJX backends do the same work.  It is a *timing*
peer: the step counts and the per-step queries of every phase follow the original; the gripper is
our own, made of primitives with the original's masses and offsets.

What the original did, and what we keep:

* A world scaled 10x in length (the object cube is 0.6 units, not 6 cm) with gravity unscaled
  (9.81), timestep 1/240 s, Bullet's default solver; a ground plane from ``pybullet_data``.
* Object: mass 50 g, lateral friction 0.2 (fingers 1.0: Bullet multiplies the two, so 0.2 between
  finger and object), rolling friction 0.001; its collision shape a compound of convex pieces.
* Gripper base held by a fixed constraint (max force 40) whose pivot is moved to raise and lower it;
  two prismatic jaws under position control with a 1.0 force limit and position gain 0.01.
* One grasp: open (500 steps), lower 0.01 per step until the gripper touches the floor, back off
  0.01 per 10 steps until it does not, close (500 steps), raise 0.02 per step to the rest height 3,
  then 200 steps and "success" if any gripper link touches the object.
* Before the grasp: 50 steps plus up to 10,000 until the object's speeds are all below 5e-4.
* Stability (from the state saved after a successful grasp): 1.5 N along each of 4 directions for
  20 steps, 200 steps, then the success check again (200 more steps).
* Robustness (from the state saved before the grasp): the object set to a yaw of -30..+30 degrees,
  wait until stable, grasp again, success check.
* A move that makes no progress (the gripper's palm resting on a tall object because the fingers
  do not reach the floor) gives up after 10,000 iterations and the trial fails; so does a grasp
  whose object never comes to rest in 10,000 steps.  These are the slow failures of the protocol.

Where we differ, on purpose (each departure but the finger placement is a switch of
``OriginalProtocol``, default the peer's choice, so ``research/protocol_fidelity.py --ablations``
can measure what the original's choice changes):

* The fingers are placed with our frames (``f2f_jax.geometry.finger_pose``) at true relative scale
  (the original stretched its finger meshes by 1.15), and the jaws open from a finger-dependent
  width (1 cm clear of the object's cube) instead of a fixed one, as our MuJoCo scene does.  They
  close until the mount planes reach the object cube's faces (the original's stopped 2.45 cm
  further out), so every finger reaches into the object's space.
* Fingers collide with the object and the floor, not with each other (the original loaded the
  gripper with self-collision on), so imprint fingers that meet outside the object do not hold each
  other apart; the gripper links have no self-collision at all.
* The push acts at the object's centre of mass (the original passed the world origin as the point
  of application, which also twisted the object), and the object's centre of mass is the centroid
  of its pieces (the original's sat at the bottom centre of the object's mesh).
* Collision shapes come from our hull arrays (``f2f_jax.geometry.hulls.Hulls``), written as one
  multi-object OBJ per shape: Bullet turns each object of such a file into a convex hull inside one
  compound shape, exactly what the original got from its V-HACD files.  (``createCollisionShape``
  with ``vertices=`` makes one hull only, and ``createCollisionShapeArray`` takes no vertices.)
  The meshing itself (V-HACD, seconds per finger in the original) is not timed.

Three more switches keep the original's values by default, for ablations: ``substeps`` (Bullet's
``numSubSteps``: the original's 1/240 s step is not converged; split in 4 or 8, a fifth of the
imprint trials turn from failures into successes), ``solver_iterations`` and
``finger_rolling_friction`` (the fingers' rolling and spinning friction, 1 in the original's URDF).

``pybullet_runs`` records, renders and times its runs; ``python benchmarks/sim_throughput.py
--peer-shapes convex`` prints evaluations per second on imprint triples.  Needs the ``pybullet``
extra.
"""

from __future__ import annotations

import functools
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from f2f_jax.config import Config, default
from f2f_jax.errors import MissingExtraError
from f2f_jax.geometry import finger_pose
from f2f_jax.geometry.hulls import Hulls

try:
    import pybullet as p
    import pybullet_data
except ImportError as exc:  # pragma: no cover - exercised where the extra is missing
    raise MissingExtraError(f"the PyBullet peer needs pybullet ({exc.name} is not installed): "
                            'pip install -e ".[pybullet]"') from exc

N_TRIALS = 11


@dataclass(frozen=True)
class OriginalProtocol:
    """The original's constants.  Lengths are in its scaled world's units (1 unit = 10 cm real)."""

    world_scale: float = 10.0  # object cube 0.6 units for 6 cm (configs/default.json view_bounds)
    timestep: float = 1.0 / 240.0  # Bullet's default, never changed by the original
    # --- gripper (environment/urdfTemplates.py, WSG50.py) ---
    base_mass: float = 1.2
    jaw_link_mass: float = 0.1  # guide, mount and finger links, each
    link_inertia: float = 1.0  # every gripper link's inertia diagonal in the URDF
    base_half_extents: tuple[float, float, float] = (0.73, 0.25, 0.3625)  # WSG50_110.stl x10
    finger_drop: float = 1.35  # finger cube centre below the base frame (finger_z_offset)
    # the mount block sits on top of the finger cube, behind the mount plane (WSG50_MOUNT_SIMPLE
    # x10 is 0.49 x 0.5 x 0.27 above its finger): it never reaches an object the finger misses
    mount_half_extents: tuple[float, float, float] = (0.245, 0.25, 0.135)
    # lateral friction of the finger links (not called finger_friction: that name is
    # SimConfig's finger-object coefficient, the object's lateral friction here)
    finger_lateral_friction: float = 1.0
    # rolling and spinning friction of the finger links (the original's URDF: 1 each).  Bullet
    # combines them with the object's lateral friction (r_finger * mu_object + r_object *
    # mu_finger): 0.2 units of lever, 2 cm at true scale, against turning about any contact
    finger_rolling_friction: float = 1.0
    grip_force: float = 1.0  # max_grasp_force: the jaw motors' force limit
    grip_position_gain: float = 0.01  # WSG50.speed, passed as positionGains
    jaw_motion_steps: int = 500  # steps after every open / close command
    open_clearance: float = 0.1  # open finger tip to object cube, ~1.05 cm real in the original
    # --- lifting by a constraint (WSG50.set_height / move_to_floor / move_to_height) ---
    rest_height: float = 3.0
    lift_max_force: float = 40.0
    floor_increment: float = 0.01  # lowered per step until the floor is touched
    floor_backoff_steps: int = 10  # steps per 0.01 raise while still touching the floor
    lift_increment: float = 0.02  # raised per step on the way back to the rest height
    max_move_steps: int = 10000
    # --- object (urdfTemplates.grasp_object_template) ---
    object_rolling_friction: float = 0.001
    # --- settling and checks (utils.wait_until_object_is_stable, GraspSimulationEnv) ---
    settle_min_steps: int = 50
    settle_max_steps: int = 10000
    stationary_tolerance: float = 5e-4  # units/s and rad/s, every component
    check_steps: int = 200  # steps before "does the gripper touch the object"
    push_steps: int = 20  # steps_to_apply_force
    push_hold_steps: int = 200
    # --- the peer's departures from the original, as switches (defaults: the peer's choice; the
    # original's value in each comment).  research/protocol_fidelity.py --ablations flips them.
    self_collision: bool = False  # True: the two fingers collide with each other (original)
    push_point: str = "com"  # "origin": the force applied at the world origin (original)
    centre_of_mass: str = "centroid"  # "base": at the mesh's bottom centre (original)
    stroke_short: float = 0.0  # jaws stop this far before the cube's faces (original: 0.245)
    settle_turned: bool = True  # False: no settling after turning the object (not the original)
    # --- Bullet's own solver, for ablations (the original left every one at Bullet's default) ---
    substeps: int = 0  # numSubSteps: 0 (Bullet's default) one step per 1/240 s; k > 1 splits it
    solver_iterations: int = 50  # numSolverIterations, Bullet's default


PROTOCOL = OriginalProtocol()
# Bullet engine parameter -> the OriginalProtocol field that sets it (only when an ablation changes it)
_ENGINE_FIELDS = {"numSubSteps": "substeps", "numSolverIterations": "solver_iterations"}


class _Api:
    """pybullet functions bound to one client id (bound once: the hot loops call them per step)."""

    def __init__(self, client: int):
        self.client = client

    def __getattr__(self, name):
        fn = functools.partial(getattr(p, name), physicsClientId=self.client)
        setattr(self, name, fn)
        return fn


@dataclass
class _Gripper:
    body: int
    constraint: int
    jaws: tuple[int, int]  # joint indices of the left and right prismatic jaws
    strokes: tuple[float, float]  # closed targets (upper joint limits), units


class OriginalSession:
    """One PyBullet client set up like the original's environment, reused for many triples.

    Use as a context manager.  ``steps`` counts every ``stepSimulation`` call since creation.
    """

    def __init__(self, cfg: Config | None = None, protocol: OriginalProtocol = PROTOCOL, *,
                 gui: bool = False):
        self.cfg = cfg or default()
        self.proto = protocol
        self.gui = gui
        client = p.connect(p.GUI if gui else p.DIRECT)
        if client < 0:
            raise RuntimeError(f"pybullet: could not connect a {'GUI' if gui else 'DIRECT'} client")
        self.api = _Api(client)
        self.steps = 0
        self.unstable = 0  # trials ended by a non-finite state
        self.build_seconds = 0.0  # writing and loading collision shapes, creating bodies
        api = self.api
        api.resetSimulation()
        api.setAdditionalSearchPath(pybullet_data.getDataPath())
        api.setPhysicsEngineParameter(enableFileCaching=0)
        api.setTimeStep(protocol.timestep)
        engine = {name: getattr(protocol, field) for name, field in _ENGINE_FIELDS.items()
                  if getattr(protocol, field) != getattr(PROTOCOL, field)}
        if engine:  # only what an ablation changed: the peer's default run stays Bullet's own
            api.setPhysicsEngineParameter(**engine)
        api.setGravity(0, 0, -self.cfg.sim.gravity)  # unscaled, as the original
        self.plane = api.loadURDF("plane.urdf")
        self._tmp = tempfile.TemporaryDirectory(prefix="f2f_pybullet_")
        self._n_files = 0

    # -- lifetime ------------------------------------------------------------------------------
    def close(self):
        if self.api.client >= 0:
            p.disconnect(physicsClientId=self.api.client)
            self.api.client = -1
        self._tmp.cleanup()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- building ------------------------------------------------------------------------------
    def _compound(self, pieces: list[np.ndarray]) -> int:
        """Collision shape id of the compound of convex pieces [n_k, 3] (scaled units)."""
        self._n_files += 1
        path = Path(self._tmp.name) / f"shape{self._n_files}.obj"
        lines, offset = [], 1
        for k, piece in enumerate(pieces):
            faces = ConvexHull(piece).simplices
            lines.append(f"o hull{k}")
            lines.extend(f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in piece)
            lines.extend(f"f {a + offset} {b + offset} {c + offset}" for a, b, c in faces)
            offset += len(piece)
        path.write_text("\n".join(lines) + "\n")
        return self.api.createCollisionShape(p.GEOM_MESH, fileName=str(path))

    def add_object(self, hulls: Hulls) -> int:
        """The object resting at the grasp location: its local frame is the world frame (scaled)."""
        s = self.proto.world_scale
        pieces = [piece.astype(np.float64) * s for piece in hulls.pieces()]
        if self.proto.centre_of_mass == "base":  # the bottom centre of the pieces' box
            points = np.concatenate(pieces)
            lo, hi = points.min(0), points.max(0)
            centroid = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        else:
            meshes = [trimesh.convex.convex_hull(piece) for piece in pieces]
            volumes = np.array([m.volume for m in meshes])
            centroid = np.sum([v * m.center_mass for v, m in zip(volumes, meshes)], 0) / volumes.sum()
        body = self.api.createMultiBody(
            baseMass=self.cfg.sim.object_mass, baseCollisionShapeIndex=self._compound(pieces),
            basePosition=[0, 0, 0], baseInertialFramePosition=centroid.tolist())
        self.object_com = centroid  # the base's inertial frame in its link frame (scaled units)
        self.api.changeDynamics(body, -1, lateralFriction=self.cfg.sim.finger_friction,
                                rollingFriction=self.proto.object_rolling_friction)
        return body

    def add_gripper(self, left: Hulls, right: Hulls) -> _Gripper:
        """Base box at the rest height, and per side: guide (prismatic, no collision) -> mount block
        -> finger, as in the original's URDF.  Finger link frames sit on the mount plane at the
        finger cube's vertical centre, ``finger_drop`` below the base frame."""
        api, pr, s = self.api, self.proto, self.proto.world_scale
        half_cube = self.cfg.geometry.cube_size / 2 * s
        base_shape = api.createCollisionShape(
            p.GEOM_BOX, halfExtents=pr.base_half_extents,
            collisionFramePosition=[0, 0, -pr.base_half_extents[2]])
        mount_half = np.asarray(pr.mount_half_extents)
        masses, shapes, positions, parents, types, axes, strokes = [], [], [], [], [], [], []
        for side, hulls, sign in (("left", left, 1.0), ("right", right, -1.0)):
            rot = finger_pose(side, 0.0, self.cfg)[:3, :3]
            pieces = [(piece.astype(np.float64) @ rot.T) * s for piece in hulls.pieces()]
            extent = max(float(np.max(piece[:, 2])) for piece in hulls.pieces()) * s
            open_x = half_cube + pr.open_clearance + extent  # mount plane distance from x = 0
            first = len(masses) + 1  # link indices start at 1 in parent lists (0 is the base)
            mount = api.createCollisionShape(
                p.GEOM_BOX, halfExtents=mount_half.tolist(),
                collisionFramePosition=[-sign * mount_half[0], 0, half_cube + mount_half[2]])
            masses += [pr.jaw_link_mass] * 3
            shapes += [-1, mount, self._compound(pieces)]
            positions += [[-sign * open_x, 0, 0], [0, 0, -pr.finger_drop], [0, 0, 0]]
            parents += [0, first, first + 1]
            types += [p.JOINT_PRISMATIC, p.JOINT_FIXED, p.JOINT_FIXED]
            axes += [[sign, 0, 0], [0, 0, 1], [0, 0, 1]]
            # closed target = the joint limit, where the mount plane reaches the object cube's
            # face: a jaw cannot enter the object's space (the original's stopped its mount
            # 2.45 cm outside it), and any finger reaches into that space before its jaw stops
            strokes.append(open_x - half_cube - pr.stroke_short)
        n = len(masses)
        body = api.createMultiBody(
            baseMass=pr.base_mass, baseCollisionShapeIndex=base_shape,
            basePosition=[0, 0, pr.rest_height],
            linkMasses=masses, linkCollisionShapeIndices=shapes, linkVisualShapeIndices=[-1] * n,
            linkPositions=positions, linkOrientations=[[0, 0, 0, 1]] * n,
            linkInertialFramePositions=[[0, 0, 0]] * n,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
            linkParentIndices=parents, linkJointTypes=types, linkJointAxis=axes,
            # a multibody's links never meet each other without this flag, whatever the filters
            flags=p.URDF_USE_SELF_COLLISION if pr.self_collision else 0)
        for link in range(-1, n):
            api.changeDynamics(body, link, localInertiaDiagonal=[pr.link_inertia] * 3)
        jaws = (0, 3)
        fingers = (2, 5)
        for a in range(-1, n):  # with self-collision, finger against finger only
            for b in range(a + 1, n):
                api.setCollisionFilterPair(body, body, a, b, int(
                    pr.self_collision and (a, b) == fingers))
        for joint, stroke in zip(jaws, strokes):
            api.changeDynamics(body, joint, jointLowerLimit=0.0, jointUpperLimit=stroke)
        for finger in fingers:
            api.changeDynamics(body, finger, lateralFriction=pr.finger_lateral_friction,
                               rollingFriction=pr.finger_rolling_friction,
                               spinningFriction=pr.finger_rolling_friction)
        constraint = api.createConstraint(
            parentBodyUniqueId=body, parentLinkIndex=-1, childBodyUniqueId=-1, childLinkIndex=-1,
            jointType=p.JOINT_FIXED, jointAxis=[0, 0, 0], parentFramePosition=[0, 0, 0],
            childFramePosition=[0, 0, 0])
        gripper = _Gripper(body, constraint, jaws, tuple(strokes))
        self._set_height(gripper, pr.rest_height)
        return gripper

    # -- primitives of the original script ---------------------------------------------------
    def _step(self, n: int = 1):
        step = self.api.stepSimulation
        for _ in range(n):
            step()
        self.steps += n
        if self.gui:
            time.sleep(n * self.proto.timestep)

    def _touches(self, a: int, b: int) -> bool:
        return len(self.api.getClosestPoints(bodyA=a, bodyB=b, distance=0.0)) > 0

    def _height(self, g: _Gripper) -> float:
        return self.api.getBasePositionAndOrientation(g.body)[0][2]

    def _set_height(self, g: _Gripper, height: float):
        self.api.changeConstraint(g.constraint, jointChildPivot=[0, 0, height],
                                  maxForce=self.proto.lift_max_force)

    def _jaws(self, g: _Gripper, targets):
        pr = self.proto
        self.api.setJointMotorControlArray(
            g.body, list(g.jaws), p.POSITION_CONTROL, targetPositions=list(targets),
            forces=[pr.grip_force] * 2, positionGains=[pr.grip_position_gain] * 2)
        self._step(pr.jaw_motion_steps)

    def _is_stationary(self, obj: int) -> bool:
        lin, ang = self.api.getBaseVelocity(obj)
        tol = self.proto.stationary_tolerance
        return max(map(abs, lin)) < tol and max(map(abs, ang)) < tol

    def _settle(self, obj: int) -> bool:
        self._step(self.proto.settle_min_steps)
        for _ in range(self.proto.settle_max_steps):
            self._step()
            if self._is_stationary(obj):
                return True
        return False

    def _move_to_floor(self, g: _Gripper) -> bool:
        pr, count = self.proto, 0
        while not self._touches(g.body, self.plane):
            self._set_height(g, self._height(g) - pr.floor_increment)
            self._step()
            count += 1
            if count > pr.max_move_steps:
                return False
        while self._touches(g.body, self.plane):
            self._set_height(g, self._height(g) + pr.floor_increment)
            self._step(pr.floor_backoff_steps)
            count += 1
            if count > pr.max_move_steps:
                return False
        return True

    def _move_to_rest_height(self, g: _Gripper) -> bool:
        pr, count = self.proto, 0
        height = self._height(g)
        while not height > pr.rest_height:
            self._set_height(g, height + pr.lift_increment)
            self._step()
            height = self._height(g)
            count += 1
            if count > pr.max_move_steps:
                return False
        return True

    def _grasp(self, g: _Gripper) -> bool:
        """Open, lower to the floor, close, lift.  False when a move gave up."""
        self._jaws(g, (0.0, 0.0))
        if not self._move_to_floor(g):
            return False
        self._jaws(g, g.strokes)
        return self._move_to_rest_height(g)

    def _held(self, g: _Gripper, obj: int) -> bool:
        """The original's success check: 200 steps, then any gripper link touching the object."""
        self._step(self.proto.check_steps)
        pos = self.api.getBasePositionAndOrientation(obj)[0]
        if not all(map(math.isfinite, pos)):
            self.unstable += 1
            return False
        return self._touches(g.body, obj)

    def _push(self, obj: int, force: np.ndarray):
        for _ in range(self.proto.push_steps):
            if self.proto.push_point == "origin":
                point = (0.0, 0.0, 0.0)
            else:
                point = self.api.getBasePositionAndOrientation(obj)[0]
            self.api.applyExternalForce(obj, -1, force.tolist(), point, p.WORLD_FRAME)
            self._step()
        self._step(self.proto.push_hold_steps)

    # -- the protocol --------------------------------------------------------------------------
    def simulate(self, object_hulls: Hulls, left_hulls: Hulls, right_hulls: Hulls) -> np.ndarray:
        """The 11 outcomes of one triple: [grasp, S1..S4, R-30..R+30] uint8.

        Empty hull sets (an infeasible finger, rejected before meshing) score all 0 without a step.
        """
        out = np.zeros(N_TRIALS, np.uint8)
        if min(h.n_pieces for h in (object_hulls, left_hulls, right_hulls)) == 0:
            return out
        api, sim = self.api, self.cfg.sim
        start = time.perf_counter()
        obj = self.add_object(object_hulls)
        g = self.add_gripper(left_hulls, right_hulls)
        self.build_seconds += time.perf_counter() - start
        states = []
        try:
            if not self._settle(obj):
                return out
            stable = api.saveState()
            states.append(stable)
            if not (self._grasp(g) and self._held(g, obj)):
                return out
            out[0] = 1
            grasped = api.saveState()
            states.append(grasped)
            for i, direction in enumerate(sim.stability_directions):
                api.restoreState(grasped)
                self._push(obj, sim.push_force * np.asarray(direction))
                out[1 + i] = self._held(g, obj)
            for j, angle in enumerate(sim.robustness_angles_deg):
                api.restoreState(stable)
                pos = api.getBasePositionAndOrientation(obj)[0]
                api.resetBasePositionAndOrientation(
                    obj, pos, api.getQuaternionFromEuler([0, 0, math.radians(angle)]))
                if self.proto.settle_turned:
                    self._settle(obj)  # the original ignored whether it settled here
                out[1 + len(sim.stability_directions) + j] = self._grasp(g) and self._held(g, obj)
            return out
        finally:
            for state in states:
                api.removeState(state)
            api.removeBody(g.body)
            api.removeBody(obj)
