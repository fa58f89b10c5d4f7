"""The 11 grasp trials of one candidate as phases over a MuJoCo (model, data) pair.

Trial order is ``config.TRIAL_NAMES``: the grasp (settle, close, lift, hold, check); four pushes
S1..S4 from the restored post-grasp state; six grasps of the object turned by
``SimConfig.robustness_angles_deg``.  Every phase length and threshold comes from ``SimConfig``.

Rules (DESIGN.md section 2):

* success = the object's centre of mass is at least ``success_min_height`` above where it settled
  AND a finger touches it;
* a failed grasp makes every other trial 0 without simulating it;
* a NaN or exploding state (MuJoCo warnings, non-finite state, a speed above ``max_speed``) ends
  that trial as a failure and is counted in ``TrialResult.unstable``, never raised;
* once the object is below the success height after the lift is done, nothing can raise it again
  (the gripper stands still), so that trial stops early: a failure costs few steps;
* during the lift, once the object is below the success height, every finger is above its top
  and it rises no faster than the gripper, no finger can meet it again: the trial stops there
  (``GraspRunner.dropped``), in every preset, as the outcome is decided;
* with ``SimConfig.rest_speed > 0`` the settle, close, hold and post-push hold phases also end
  early once nothing moves faster than ``rest_speed`` for ``rest_time``: an object at rest in
  the fingers with the gripper standing still stays where it is, so the rest of the hold cannot
  change the outcome (``benchmarks/sim_agreement.py`` measures that it does not);
* with ``SimConfig.shared_settle`` a turned grasp starts from the first grasp's settled object
  turned about the vertical through its starting point (``GraspRunner.turn_settled``) instead of
  settling again: the floor is unchanged by that turn and the open jaws touch nothing, so it is
  the same state up to rounding.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from f2f_jax.config import TRIAL_NAMES, Config
from f2f_jax.errors import F2FError
from f2f_jax.geometry.finger_tiling import remembered_finger_hulls
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.sim.opening import JawOpener
from f2f_jax.sim.scene import (
    SceneIds,
    build_model,
    finger_object_contacts,
    object_quat,
    scene_ids,
)

# Steps between health checks: 50 ms of simulated time, short enough that an exploding state is
# caught before it does anything but fail its own trial, long enough that Python's overhead
# stays a few percent of the stepping.
CHECK_EVERY = 25
# Steps between rest checks in phases that may end at rest: the rest window is sampled this
# often, so a swinging object passing through zero speed is not mistaken for one at rest.
REST_CHECK_EVERY = 5
# The lift command changes every LIFT_CHUNK_TIME seconds along its profile (5 steps of 2 ms, 2
# of 4 ms): ``lift_chunk``.
LIFT_CHUNK_TIME = 0.01
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
# A body's angular speed counts as the speed of a point this far (m) from its centre: the
# object cube's half diagonal.
SPIN_RADIUS = 0.052
# A dropped object counts as out of reach once the fingers' lowest point is this far (m) above
# its highest point.
DROP_CLEARANCE = 0.001


@dataclass
class TrialResult:
    """What the 11 trials of one candidate gave.

    outcome: [11] uint8, 1 = success, in ``TRIAL_NAMES`` order.
    steps: physics steps taken in all trials together.
    unstable: trials ended by a NaN / exploding state (counted as failures).
    trial_steps: [11] int64, steps per trial (0 for trials not run).
    heights: [11] float64, object centre above its settled height (m) at each trial's end; NaN
        where the trial was not run or went unstable.
    initial_contacts: grasp set-ups (of 7) in which a finger touched the object at t = 0 or when
        the jaws, moved in after settling, start to close (should be 0).
    seconds: wall time of the trials.
    error: why the candidate was not simulated (model build failure), else None.
    """

    outcome: np.ndarray
    steps: int = 0
    unstable: int = 0
    trial_steps: np.ndarray = field(default_factory=lambda: np.zeros(len(TRIAL_NAMES), np.int64))
    heights: np.ndarray = field(default_factory=lambda: np.full(len(TRIAL_NAMES), np.nan))
    initial_contacts: int = 0
    seconds: float = 0.0
    error: str | None = None

    @classmethod
    def zeros(cls, n_trials: int = len(TRIAL_NAMES), error: str | None = None) -> "TrialResult":
        return cls(outcome=np.zeros(n_trials, np.uint8), trial_steps=np.zeros(n_trials, np.int64),
                   heights=np.full(n_trials, np.nan), error=error)


def lift_chunk(cfg: Config | None = None) -> int:
    """Steps per constant lift command: LIFT_CHUNK_TIME at the config's timestep, at least 1."""
    s = (cfg or Config()).sim
    return max(1, int(round(LIFT_CHUNK_TIME / s.timestep)))


def lift_targets(cfg: Config | None = None) -> np.ndarray:
    """Lift position targets at the lift phase's step boundaries: [n_lift + 1] float64 (m).

    A minimum-jerk profile (10 t^3 - 15 t^4 + 6 t^5) from 0 to lift_height over lift_time.  A
    constant-speed ramp starts with a velocity step that the stiff lift servo turns into a jolt
    of ~6 m/s^2 (v * sqrt(kp / m)); the 50 g object then needs 0.3 N more friction than its
    weight, so grasps that hold statically would slip.  This profile peaks at
    5.8 lift_height / lift_time^2 (1.2 m/s^2 with the default phases: 0.06 N).
    """
    s = (cfg or Config()).sim
    t = np.linspace(0.0, 1.0, s.steps(s.lift_time) + 1)
    return s.lift_height * t ** 3 * (10.0 - 15.0 * t + 6.0 * t ** 2)


class Unstable(Exception):
    """Raised inside a trial when the state is NaN or exploding; the trial scores 0."""


class GraspRunner:
    """Steps one model through the trial phases, counting steps and watching for instability.

    model: a model from ``scene.build_model``; data: its MjData (created if None).
    """

    def __init__(self, model: mujoco.MjModel, cfg: Config | None = None,
                 data: mujoco.MjData | None = None):
        self.model = model
        self.cfg = cfg or Config()
        self._own_data = data is None  # free to run kinematics on before the first place()
        self.data = data if data is not None else mujoco.MjData(model)
        self.ids: SceneIds = scene_ids(model)
        self.opener = JawOpener(model, self.ids, self.cfg)
        self.steps = 0
        self.z_start = np.nan  # object centre height after settling in the last grasp (m)
        # the object's free-joint (qpos [7], qvel [6]) after the last yaw-0 settle
        self.settled: tuple[np.ndarray, np.ndarray] | None = None
        self._warnings = 0
        self._lift_dof = int(self.model.jnt_dofadr[self.model.joint("lift").id])
        self._speed_dofs = np.concatenate([self.ids.jaw_dof, [self._lift_dof]]).astype(np.int64)
        self._speed_dof_list = self._speed_dofs.tolist()
        # views into the MjData (its arrays never move): the checks after every few steps read
        # them without building a new array object each time
        d = self.data
        self._qpos, self._qvel, self._xipos, self._xpos = d.qpos, d.qvel, d.xipos, d.xpos
        self._warning_numbers = d.warning.number
        self._lift_targets = lift_targets(self.cfg)
        self._reach_setup()

    def _reach_setup(self) -> None:
        """What ``dropped`` needs: each jaw's lowest finger point below the jaw body's origin
        (jaws only slide, so it is fixed), the object pieces' vertices in their geom frames,
        and their furthest distance from the object's centre of mass."""
        m = self.model
        data = self.data if self._own_data else mujoco.MjData(m)  # fresh; place() resets it
        mujoco.mj_kinematics(m, data)
        mujoco.mj_comPos(m, data)

        def world_vertices(gid):
            mesh = m.geom_dataid[gid]
            local = m.mesh_vert[m.mesh_vertadr[mesh]: m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
            return local, local @ data.geom_xmat[gid].reshape(3, 3).T + data.geom_xpos[gid]

        self._jaw_bodies = np.array([m.body(f"{side}_jaw").id for side in ("left", "right")])
        self._finger_low = np.zeros(2)
        for side, geoms in enumerate(self.ids.finger_geoms):
            low = min((float(world_vertices(g)[1][:, 2].min()) for g in geoms), default=np.inf)
            self._finger_low[side] = low - data.xpos[self._jaw_bodies[side], 2]
        self._jaw_list, self._finger_low_list = self._jaw_bodies.tolist(), self._finger_low.tolist()
        self._object_vertices = [(int(g), world_vertices(g)[0]) for g in self.ids.object_geoms]
        com = data.xipos[self.ids.object_body]
        self._object_radius = max(float(np.linalg.norm(world_vertices(g)[1] - com, axis=1).max())
                                  for g in self.ids.object_geoms)

    # --- low level --------------------------------------------------------------------------
    def _warning_count(self) -> int:
        return sum(self._warning_numbers.tolist())

    def _finite(self) -> bool:
        """False if MuJoCo warned since the trial began or the state is not finite."""
        # a sum is NaN or infinite when any of its terms is: one check instead of one per entry
        # (this runs after every few steps)
        return (sum(self._warning_numbers.tolist()) == self._warnings
                and math.isfinite(float(self._qpos.sum()) + float(self._qvel.sum())))

    def healthy(self) -> bool:
        """False if MuJoCo warned since the trial began, the state is not finite or anything
        moves faster than ``max_speed``."""
        return self._finite() and self.speed() <= self.cfg.sim.max_speed

    def speed(self) -> float:
        """The fastest motion in the scene (m/s): the object's linear speed, its angular speed
        at ``SPIN_RADIUS``, the jaws' and the lift's speeds."""
        o = self.ids.object_dof
        # plain floats: this runs after every few steps, where numpy's per-call cost dominates
        qvel = self._qvel.tolist()
        vx, vy, vz, wx, wy, wz = qvel[o: o + 6]
        return max(math.sqrt(vx * vx + vy * vy + vz * vz),
                   math.sqrt(wx * wx + wy * wy + wz * wz) * SPIN_RADIUS,
                   max(abs(qvel[i]) for i in self._speed_dof_list))

    def _checked_speed(self) -> float:
        """``speed()`` if ``_finite()``, else inf, from one read.  Plain sums: MuJoCo resets (and
        warns about) entries beyond 1e10, so these are finite exactly when numpy's are."""
        qvel = self._qvel.tolist()
        if (sum(self._warning_numbers.tolist()) != self._warnings
                or not math.isfinite(sum(self._qpos.tolist()) + sum(qvel))):
            return math.inf
        o = self.ids.object_dof
        vx, vy, vz, wx, wy, wz = qvel[o: o + 6]
        return max(math.sqrt(vx * vx + vy * vy + vz * vz),
                   math.sqrt(wx * wx + wy * wy + wz * wz) * SPIN_RADIUS,
                   max(abs(qvel[i]) for i in self._speed_dof_list))

    def advance(self, n: int, *, stop_below: float | None = None,
                chunk: int = CHECK_EVERY, until_rest: bool = False) -> bool:
        """Step ``n`` times in chunks of ``chunk`` steps, checking health after each chunk.

        stop_below: stop early (return False) once the object's centre is below this height.
        until_rest: also stop early (return True) once ``speed()`` has stayed below
            ``SimConfig.rest_speed`` for ``rest_time`` (sampled every REST_CHECK_EVERY steps);
            ignored when rest_speed is 0 (the ``reference`` preset).
        Returns True if the phase ran to its end or to rest.  Raises Unstable.
        """
        s = self.cfg.sim
        rest_steps = s.steps(s.rest_time) if until_rest and s.rest_speed > 0 else None
        if rest_steps is not None:
            chunk = min(chunk, REST_CHECK_EVERY)
        resting_since = None  # step count of the first sample of the current rest window
        done = 0
        while done < n:
            k = min(chunk, n - done)
            mujoco.mj_step(self.model, self.data, nstep=k)
            done += k
            self.steps += k
            speed = self._checked_speed()
            if speed > s.max_speed:
                raise Unstable(f"unstable state at t = {self.data.time:.3f} s")
            if stop_below is not None and self.object_height() < stop_below:
                return False
            if rest_steps is not None:
                if speed >= s.rest_speed:
                    resting_since = None
                elif resting_since is None:
                    resting_since = done
                elif done - resting_since >= rest_steps:
                    return True
        return True

    def object_height(self) -> float:
        return float(self._xipos[self.ids.object_body, 2])

    def dropped(self, below: float) -> bool:
        """True once no finger can meet the object again while the gripper rises: its centre
        is below ``below``, it rises no faster than the gripper, and the fingers' lowest point
        is ``DROP_CLEARANCE`` above its highest point.  Nothing else lifts it (the floor only
        holds it up), so the trial's outcome is decided: a failure."""
        d, ids = self.data, self.ids
        centre = float(self._xipos[ids.object_body, 2])
        if centre >= below or self._qvel[ids.object_dof + 2] > self._qvel[self._lift_dof]:
            return False
        xpos, (left, right), (left_low, right_low) = self._xpos, self._jaw_list, self._finger_low_list
        low, other = float(xpos[left, 2]) + left_low, float(xpos[right, 2]) + right_low
        low = other if math.isnan(other) or other < low else low  # np.min's: NaN wins
        if low <= centre:  # the fingers still reach below its centre: the common case
            return False
        if low > centre + self._object_radius + DROP_CLEARANCE:
            return True
        top = max(float((v @ d.geom_xmat[g].reshape(3, 3)[2] + d.geom_xpos[g, 2]).max())
                  for g, v in self._object_vertices)
        return low > top + DROP_CLEARANCE

    def held(self, z_start: float) -> tuple[bool, float]:
        """(success, height above start): lifted by success_min_height and touching a finger."""
        mujoco.mj_forward(self.model, self.data)  # contacts of the current state
        rise = self.object_height() - z_start
        touching = finger_object_contacts(self.model, self.data, self.ids) > 0
        return bool(rise >= self.cfg.sim.success_min_height and touching), rise

    # --- phases -----------------------------------------------------------------------------
    def place(self, yaw: float) -> int:
        """Reset to t = 0: the object turned by ``yaw`` (rad) resting where the model put it, the
        jaws fully open, the lift at rest.  Returns the finger-object contacts after mj_forward
        (0 unless a finger cannot clear the object even fully open)."""
        m, d, ids = self.model, self.data, self.ids
        mujoco.mj_resetData(m, d)
        d.qpos[ids.object_qpos + 3: ids.object_qpos + 7] = object_quat(yaw)
        d.qpos[ids.jaw_qpos] = ids.jaw_range[:, 1]
        d.ctrl[ids.grip_act] = ids.jaw_range[:, 1]
        d.ctrl[ids.lift_act] = 0.0
        d.act[ids.lift_act_adr] = 0.0
        mujoco.mj_forward(m, d)
        self._warnings = self._warning_count()
        return finger_object_contacts(m, d, ids)

    def turn_settled(self, yaw: float) -> None:
        """After ``place(yaw)``: put the object where the last yaw-0 settle left it, turned by
        ``yaw`` about the vertical through its starting point (where ``place`` turns it), its
        velocity turned with it."""
        m, d, ids = self.model, self.data, self.ids
        q, v = ids.object_qpos, ids.object_dof
        qpos, qvel = self.settled
        c, s = math.cos(yaw), math.sin(yaw)
        turn = np.array([[c, -s], [s, c]])
        start = d.qpos[q: q + 2].copy()
        d.qpos[q: q + 2] = start + turn @ (qpos[:2] - start)
        d.qpos[q + 2] = qpos[2]
        quat = np.empty(4)
        mujoco.mju_mulQuat(quat, object_quat(yaw), qpos[3:])
        d.qpos[q + 3: q + 7] = quat
        d.qvel[v: v + 2] = turn @ qvel[:2]
        d.qvel[v + 2] = qvel[2]
        d.qvel[v + 3: v + 6] = qvel[3:]  # a free joint's angular velocity is in its body's frame
        mujoco.mj_forward(m, d)

    def approach(self) -> tuple[np.ndarray, int]:
        """Move the open jaws in to ``open_margin`` from the object where it now lies.

        Done after settling: a coarse hull of a round object tips onto a face and rolls a few
        millimetres when set down, so openings computed before settling would let it roll into
        a finger.  The jaws are set in place at rest (they touch nothing but the object).
        Returns (openings [2] m, finger-object contacts after mj_forward: should be 0).
        """
        m, d, ids = self.model, self.data, self.ids
        openings = self.opener(d, self.cfg.sim.open_margin)
        d.qvel[ids.jaw_dof] = 0.0
        mujoco.mj_forward(m, d)
        return openings, finger_object_contacts(m, d, ids)

    def grasp(self, yaw: float) -> tuple[bool, float, int]:
        """One grasp attempt: place, settle, approach, close, lift, hold, check.

        Returns (success, object height above its settled height at the end (m), finger-object
        contacts at t = 0 and when the jaws start closing).  Raises Unstable.
        """
        s, d, ids = self.cfg.sim, self.data, self.ids
        touching = self.place(yaw)
        if s.shared_settle and yaw != 0.0 and self.settled is not None:
            self.turn_settled(yaw)
        else:
            self.advance(s.steps(s.settle_time), until_rest=True)
            if yaw == 0.0:
                q, v = ids.object_qpos, ids.object_dof
                self.settled = (d.qpos[q: q + 7].copy(), d.qvel[v: v + 6].copy())
        z_start = self.object_height()
        self.z_start = z_start
        _, touching_closing = self.approach()
        touching += touching_closing
        d.ctrl[ids.grip_act] = ids.jaw_range[:, 0]  # beyond any contact: both servos saturate
        self.advance(s.steps(s.close_time), until_rest=True)
        # The lift actuator integrates its command (a speed) into its position target: a
        # constant command per chunk moves the target exactly along the profile's chord.
        targets = self._lift_targets
        chunk = lift_chunk(self.cfg)
        below = z_start + s.success_min_height
        for i in range(0, len(targets) - 1, chunk):
            j = min(i + chunk, len(targets) - 1)
            d.ctrl[ids.lift_act] = (targets[j] - targets[i]) / ((j - i) * s.timestep)
            self.advance(j - i, chunk=chunk)
            if self.dropped(below):
                d.ctrl[ids.lift_act] = 0.0
                return False, self.object_height() - z_start, touching
        d.ctrl[ids.lift_act] = 0.0
        self.advance(s.steps(s.hold_time), stop_below=below, until_rest=True)
        ok, rise = self.held(z_start)
        return ok, rise, touching

    def push(self, state: np.ndarray, z_start: float, direction) -> tuple[bool, float]:
        """From the saved post-grasp state: push_force along ``direction`` at the object's centre
        of mass for push_time, then hold push_hold_time; success if still held."""
        s, d, ids = self.cfg.sim, self.data, self.ids
        mujoco.mj_setState(self.model, d, state, _STATE)
        self._warnings = self._warning_count()
        d.xfrc_applied[:] = 0.0
        force = s.push_force * np.asarray(direction, np.float64)
        d.xfrc_applied[ids.object_body, :3] = force
        below = z_start + s.success_min_height
        running = self.advance(s.steps(s.push_time), stop_below=below)
        d.xfrc_applied[ids.object_body, :] = 0.0
        if running:
            self.advance(s.steps(s.push_hold_time), stop_below=below, until_rest=True)
        return self.held(z_start)


def run_trials(model: mujoco.MjModel, cfg: Config | None = None, *,
               data: mujoco.MjData | None = None, runner: GraspRunner | None = None) -> TrialResult:
    """All 11 trials of one candidate on one model (from ``scene.build_model`` at yaw 0).

    runner: a GraspRunner (or subclass, e.g. one that records frames) for this model.

    Returns a TrialResult; never raises for unstable physics (counted in ``unstable``).
    """
    cfg = cfg or Config()
    s = cfg.sim
    start = time.perf_counter()
    runner = runner if runner is not None else GraspRunner(model, cfg, data)
    result = TrialResult.zeros(s.n_trials)
    n_push = len(s.stability_directions)

    def trial(index, fn):
        before = runner.steps
        try:
            ok, rise = fn()
        except Unstable:
            result.unstable += 1
            ok, rise = False, np.nan
        result.outcome[index] = ok
        result.heights[index] = rise
        result.trial_steps[index] = runner.steps - before
        return ok

    def grasp(yaw):
        ok, rise, touching = runner.grasp(yaw)
        result.initial_contacts += touching > 0
        return ok, rise

    if trial(0, lambda: grasp(0.0)):
        z_start = runner.z_start
        state = np.empty(mujoco.mj_stateSize(model, _STATE))
        mujoco.mj_getState(model, runner.data, state, _STATE)
        for i, direction in enumerate(s.stability_directions):
            trial(1 + i, lambda: runner.push(state, z_start, direction))
        for i, angle in enumerate(s.robustness_angles_deg):
            trial(1 + n_push + i, lambda: grasp(np.deg2rad(angle)))
    result.steps = runner.steps
    result.seconds = time.perf_counter() - start
    return result


def simulate_candidate(obj_hulls: Hulls | str, left: np.ndarray, right: np.ndarray, cfg: Config,
                       object_xy=None) -> TrialResult:
    """Hulls, model and trials of one feasible candidate: the work of one worker thread
    (``mujoco_cpu``) or one Ray task's candidate (``ray_executor``); any geometry error is a
    failure, never raised.  obj_hulls: the object's pieces, or the error message of an object
    that has none (scored zeros).  object_xy: None or (x, y) m, the object's shift on the floor
    (``scene.build_model``)."""
    if isinstance(obj_hulls, str):
        return TrialResult.zeros(cfg.sim.n_trials, error=f"object hulls: {obj_hulls}")
    place = {} if object_xy is None else {"object_xy": (float(object_xy[0]), float(object_xy[1]))}
    try:
        model = build_model(obj_hulls, remembered_finger_hulls(left, cfg),
                            remembered_finger_hulls(right, cfg), cfg, **place)
    except (F2FError, ValueError) as exc:
        return TrialResult.zeros(cfg.sim.n_trials, error=f"{type(exc).__name__}: {exc}")
    return run_trials(model, cfg)
