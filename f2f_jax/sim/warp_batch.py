"""Batched backend on MuJoCo Warp: every trial a world, every world its own geometry.

``evaluate(..., backend="warp")`` builds each candidate's model on the host as the CPU backend
does (``scene.build_model(..., pad_collides=True)``: one layout, so every candidate has the same
bodies, joints and geom slots) and runs the trials as worlds of one MuJoCo Warp model:

* **Per-world geometry.**  The meshes of every candidate in a batch are concatenated into one
  mesh table (vertices, hull graphs and polygons exactly as MuJoCo compiled them for that
  candidate), and each world's ``geom_dataid`` points at its own candidate's meshes, with the
  candidate's geom sizes, poses and bounds and its object's mass and inertia.  A placeholder
  slot (a candidate with fewer pieces than the layout has) gets ``geom_dataid`` -1: absent from
  that world.  MuJoCo Warp collides convex meshes by GJK/EPA with early outs, so pairs that do
  not touch cost little (unlike MJX's separating-axis test over every edge pair).
* **The protocol of ``protocol.py``**, phase for phase and with its rules: place, settle,
  approach (``opening.JawOpener``'s rule from each world's settled pose, on the device: a kernel
  over every world and line of its grid, then its back-off by exact distances from collision
  passes with a margin; ``approach="host"`` runs ``JawOpener`` itself, ~20 ms of a host core
  per world), close, the lift profile, hold, the held
  check (rise, and a finger-object contact among the last step's contacts); pushes from each
  held grasp's saved state; six turned grasps; health checks every ``CHECK_EVERY`` steps.
  Like the MJX backend, every phase runs to its full length whatever the preset (all worlds
  step in lock-step: the ``reference`` preset's behaviour), and the lift command follows the
  profile's exact chord each step.  ``rest_stop=True`` (off by default: it changes physics)
  ends the settle, close, hold and post-push hold phases of a round once every world has been
  at rest (or, in a hold, dropped below the success height) as the CPU presets' early exits
  rule, when the preset's ``rest_speed`` is above 0.
* **Pairs that cannot touch are left out** of the broad phase's list (``pair_filter``, on by
  default; ``warp_worlds.reachable_pairs``): pieces of the two jaws whose extents across the
  closing axis never overlap, and slots that are placeholders in every world of a chunk.  Same
  contacts, so the same physics.
* **Failed worlds stop costing work by compaction**: the grasp at yaw 0 runs for every
  candidate; only candidates that held are simulated further, as 10 worlds each (4 pushes,
  6 turned grasps), in new, smaller batches.
* **Batches from device memory, all local GPUs**: worlds are cut into chunks that fit each
  device (``default_worlds``) and spread over every CUDA device; the chunks of one round step
  together, each device working asynchronously.  Without a GPU it runs on warp's CPU device:
  correct, and useful for tests at tiny sizes, but slow (400-800 environment steps/s at 2-4
  worlds on a 2-core machine: a tenth of plain MuJoCo).

Needs the ``warp`` extra (``pip install -e ".[warp]"``, mujoco-warp pinned to the mujoco
release).  Importing this module without it raises ``errors.MissingExtraError``.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np

from f2f_jax.config import Config
from f2f_jax.sim.opening import BACKOFF_ROUNDS, JawOpener
from f2f_jax.sim.protocol import (
    CHECK_EVERY,
    REST_CHECK_EVERY,
    SPIN_RADIUS,
    lift_targets,
)
from f2f_jax.sim.scene import scene_ids
from f2f_jax.sim.warp_worlds import (
    CONTACTS_PER_WORLD,
    LOST_OVERFLOWS,
    MeshTable,
    WorldChunk,
    candidate_fields,
    default_worlds,
    finger_object_pairs,
    local_devices,
    wp,
)

log = logging.getLogger(__name__)

# Where the approach's openings are computed: "device" (``opening.JawOpener``'s rule on the
# device: a kernel over every world and line of its grid, then its back-off by exact
# distances, from collision passes with a margin), or "host" (``opening.JawOpener`` itself, per
# world: ~20 ms of a host core each).
APPROACHES = ("device", "host")
# Devices whose kernels this process has compiled (loaded from warp's disk cache, or built):
# the first step on each is timed as compiling.
_WARM_DEVICES: set = set()


# --------------------------------------------------------------------------------------------
# The trials
# --------------------------------------------------------------------------------------------
class WarpGraspSimulator:
    """The 11 trials of candidate models (one layout) as MuJoCo Warp worlds.

    cfg: Config; every phase runs to its full length (``rest_speed`` is not used: lock-step
    worlds cannot end phases early one by one), as in the ``reference`` preset, unless
    ``rest_stop`` ends a round's phase once all its worlds rest.
    devices: warp devices to spread worlds over (default every local GPU, else the CPU);
    worlds: worlds per chunk (default ``default_worlds``); threads: host threads for the
    openings (default: Python's pool default).  pair_filter: leave pairs that cannot touch
    out of the broad phase (same outcomes); rest_stop: end a round's resting phases early (see
    the module's docstring; other outcomes than without).
    """

    def __init__(self, cfg: Config, *, devices: list[str] | None = None, worlds: int | None = None,
                 threads: int | None = None, approach: str = "device",
                 pair_filter: bool = True, rest_stop: bool = False):
        if approach not in APPROACHES:
            raise ValueError(f"approach {approach!r}: one of {APPROACHES}")
        self.cfg = cfg
        self.approach = approach
        self.pair_filter, self.rest_stop = pair_filter, rest_stop
        self._device_consts: dict = {}
        self.devices = devices or local_devices()
        self.worlds = worlds
        self.threads = threads
        s = self.cfg.sim
        self.n_settle, self.n_close = s.steps(s.settle_time), s.steps(s.close_time)
        self.n_hold, self.n_push = s.steps(s.hold_time), s.steps(s.push_time)
        self.n_push_hold = s.steps(s.push_hold_time)
        self.lift_ctrl = np.diff(lift_targets(self.cfg)) / s.timestep  # per step: exact chord
        self.grasp_steps = self.n_settle + self.n_close + len(self.lift_ctrl) + self.n_hold
        self.push_steps = self.n_push + self.n_push_hold
        self.compile_seconds = 0.0
        self.step_seconds = 0.0
        self.world_steps = 0
        self.approach_seconds = 0.0  # the host's opening rule (JawOpener per world)
        self.overflowed = 0  # worlds failed because a buffer overflowed (should stay 0)
        self.peak_pairs = 0.0  # most broad-phase pairs per world in a chunk, for sizing
        self.peak_rows = 0  # most constraint rows in one world
        self.pair_sums = np.zeros(3)  # broad-phase pairs at checks, world-checks, listed x worlds

    # ---------------------------------------------------------------- rounds
    def _chunks(self, models, table, which):
        """Split worlds ``which`` (candidate indices) over the devices in chunks; returns
        [(slice, WorldChunk)]."""
        out, start = [], 0
        per = [self.worlds or default_worlds(dev) for dev in self.devices]
        n = len(which)
        while start < n:
            for dev, size in zip(self.devices, per):
                if start >= n:
                    break
                stop = min(n, start + size)
                fields = {k: v[which[start:stop]] for k, v in self.fields.items()}
                jaws = self.ids.finger_geoms if self.pair_filter else None
                out.append((slice(start, stop), WorldChunk(models[0], table, fields, dev, jaws)))
                start = stop
        return out

    def _steps(self, chunks, n, healthy_state, before_step=None, *, until_rest=False,
               below=None) -> int:
        """Step every chunk ``n`` times (lock-step), checking health every CHECK_EVERY steps;
        ``before_step(k)`` may change controls first.  With ``rest_stop``, ``until_rest`` and a
        preset's rest_speed, stop once every world is done (``_rested``); below: [W] heights
        under which a world's object has dropped (done).  Returns the steps taken."""
        s = self.cfg.sim
        rest = self.rest_stop and until_rest and s.rest_speed > 0
        since = np.full(len(healthy_state), -1)  # the first step of each world's rest window
        done = np.zeros(len(healthy_state), bool)
        t = time.perf_counter()
        for k in range(n):
            if before_step is not None:
                before_step(k)
            for _, ch in chunks:
                ch.step()
            first = not all(ch.device in _WARM_DEVICES for _, ch in chunks)
            if first:  # the first step compiles every kernel (minutes on a CPU, once per process)
                for _, ch in chunks:
                    wp.synchronize_device(ch.device)
                    _WARM_DEVICES.add(ch.device)
                self.compile_seconds += time.perf_counter() - t
                t = time.perf_counter()
            stop = (rest and (k + 1) % REST_CHECK_EVERY == 0
                    and self._rested(chunks, k + 1, since, done, healthy_state, below))
            if (k + 1) % CHECK_EVERY == 0 or k == n - 1 or stop:
                self._check(chunks, healthy_state)
            if stop:
                n = k + 1
                break
        for _, ch in chunks:
            wp.synchronize_device(ch.device)
        self.step_seconds += time.perf_counter() - t
        self.world_steps += n * sum(ch.nworld for _, ch in chunks)
        return n

    def _speeds(self, ch) -> np.ndarray:
        """[W] the fastest motion in each world (``protocol.GraspRunner.speed``); NaN if not
        finite."""
        ids, qvel = self.ids, ch.get("qvel")
        v = qvel[:, ids.object_dof: ids.object_dof + 6]
        return np.maximum.reduce([np.linalg.norm(v[:, :3], axis=1),
                                  np.linalg.norm(v[:, 3:], axis=1) * SPIN_RADIUS,
                                  np.abs(qvel[:, self._speed_dofs]).max(1)])

    def _rested(self, chunks, step, since, done, bad, below) -> bool:
        """The CPU presets' rest rule, world by world, at step ``step`` of a phase: done[w] once
        its speed stayed below rest_speed for rest_time (sampled every REST_CHECK_EVERY steps),
        or its object is under below[w]; True when every world is done or failed."""
        s = self.cfg.sim
        for sl, ch in chunks:
            moving = ~(self._speeds(ch) < s.rest_speed)
            w = np.arange(sl.start, sl.stop)
            since[w[moving]] = -1
            since[w[~moving & (since[sl] < 0)]] = step
            done[sl] |= ~moving & (since[sl] >= 0) & (step - since[sl] >= s.steps(s.rest_time))
            if below is not None:
                done[sl] |= ch.get("xipos")[:, self.ids.object_body, 2] < below[sl]
        return bool((done | bad).all())

    def _check(self, chunks, bad):
        """bad[w] |= the state is not finite or anything moves faster than max_speed."""
        s = self.cfg.sim
        for sl, ch in chunks:
            qpos, qvel = ch.get("qpos"), ch.get("qvel")
            speed = self._speeds(ch)
            finite = np.isfinite(qpos).all(1) & np.isfinite(qvel).all(1)
            # a world whose pairs, contacts or constraint rows overflowed their buffers lost some
            # of them: its physics is wrong, so it fails like an exploding one, and is counted
            overflow = (ch.get("overflow") & LOST_OVERFLOWS) != 0
            self.overflowed += int(np.count_nonzero(overflow & ~bad[sl]))
            bad[sl] |= ~finite | ~(speed <= s.max_speed) | overflow
            pairs = int(ch.get("ncollision")[0])
            self.peak_pairs = max(self.peak_pairs, pairs / ch.nworld)
            self.pair_sums += (pairs, ch.nworld, ch.listed_pairs * ch.nworld)
            self.peak_rows = max(self.peak_rows, int(ch.get("nefc").max()))

    def _held(self, chunks, z_start):
        """(held [W], rise [W]) from each world's last step: risen success_min_height above
        z_start and a finger touching the object."""
        ids, s = self.ids, self.cfg.sim
        n = len(z_start)
        rise = np.zeros(n)
        touching = np.zeros(n, bool)
        for sl, ch in chunks:
            rise[sl] = ch.get("xipos")[:, ids.object_body, 2] - z_start[sl]
            geom, dist, world = ch.contacts()
            pair = finger_object_pairs(geom, ids.all_finger_geoms, ids.object_geoms)
            hit = world[pair & (dist < 0)]
            touching[sl.start + np.unique(hit)] = True
        return (rise >= s.success_min_height) & touching, rise

    # ---------------------------------------------------------------- programs
    def _device_openings(self, ch: WorldChunk) -> np.ndarray:
        """[W, 2] jaw openings by ``opening.JawOpener``'s rule, run on the chunk's device: clear
        of the object by ``open_margin`` along the closing axis on every line, clipped to the
        joint range, the lower limit where a jaw's finger meets no line of the object; then
        opened further wherever a finger is still nearer the object than half the margin."""
        ids, s = self.ids, self.cfg.sim
        dev = ch.device
        key = dev
        if key not in self._device_consts:
            as_int = lambda a: wp.array(np.asarray(a, np.int32), dtype=int, device=dev)  # noqa: E731
            self._device_consts[key] = (
                wp.array(self.opener_lines.astype(np.float32), dtype=wp.vec2, device=dev),
                as_int(ids.object_geoms), as_int(ids.finger_geoms[0]), as_int(ids.finger_geoms[1]))
        need = ch.clearance(*self._device_consts[key])
        low, high = ids.jaw_range[:, 0], ids.jaw_range[:, 1]
        margin = s.open_margin
        openings = np.where(need > -1.0e29, need + margin, low)
        openings = np.clip(openings, low, high)
        # JawOpener's back-off: lines 1 mm apart can miss a thin spike, and an imprint's rim can
        # come closer sideways than along the lines; open by what the exact distance lacks
        q = ch.get("qpos")
        for _ in range(BACKOFF_ROUNDS):
            q[:, ids.jaw_qpos] = openings
            ch.set_state(qpos=q)
            lack = margin / 2 - ch.finger_distance(ids, margin)
            more = (lack > 0) & (openings < high)
            if not more.any():
                break
            openings = np.where(more, np.minimum(openings + lack + margin / 2, high), openings)
        return openings

    def _grasp(self, models, table, which, yaws, openers):
        """Grasps of candidates ``which`` [W] at ``yaws`` [W]: (held, rise, bad, state, z)."""
        ids, s = self.ids, self.cfg.sim
        chunks = self._chunks(models, table, which)
        n = len(which)
        low, high = ids.jaw_range[:, 0], ids.jaw_range[:, 1]
        qpos = np.stack([np.array(models[c].qpos0) for c in which])
        qpos[:, ids.object_qpos + 3: ids.object_qpos + 7] = np.stack(
            [np.cos(yaws / 2), 0 * yaws, 0 * yaws, np.sin(yaws / 2)], 1)
        qpos[:, ids.jaw_qpos] = high
        ctrl = np.zeros((n, models[0].nu))
        ctrl[:, ids.grip_act] = high
        for sl, ch in chunks:
            if self.approach == "device":
                ch.keep_finger_poses(qpos[sl], ids.jaw_qpos)
            ch.set_state(qpos=qpos[sl], qvel=np.zeros((sl.stop - sl.start, models[0].nv)),
                         ctrl=ctrl[sl])
        bad = np.zeros(n, bool)
        taken = self._steps(chunks, self.n_settle, bad, until_rest=True)
        # approach: JawOpener's rule (on the device, or JawOpener itself), from each world's
        # settled pose
        t = time.perf_counter()
        z_start = np.empty(n)
        for sl, ch in chunks:
            ch.kinematics()
            q = ch.get("qpos")
            z_start[sl] = ch.get("xipos")[:, ids.object_body, 2]

            if self.approach == "device":
                openings = self._device_openings(ch)
            else:
                def opening(w, q=q, start=sl.start):
                    opener, data = openers(which[start + w])
                    data.qpos[:] = q[w]
                    return opener(data, s.open_margin)

                with ThreadPoolExecutor(self.threads) as pool:
                    openings = np.stack(list(pool.map(opening, range(len(q)))))
            q[:, ids.jaw_qpos] = openings
            qvel = ch.get("qvel")
            qvel[:, ids.jaw_dof] = 0.0
            c = ch.get("ctrl")
            c[:, ids.grip_act] = low
            ch.set_state(qpos=q, qvel=qvel, ctrl=c)
        self.approach_seconds += time.perf_counter() - t
        taken += self._steps(chunks, self.n_close, bad, until_rest=True)

        def lift(k):
            for _, ch in chunks:
                ch.set_column("ctrl", ids.lift_act, self.lift_ctrl[k])

        taken += self._steps(chunks, len(self.lift_ctrl), bad, lift)
        for _, ch in chunks:
            ch.set_column("ctrl", ids.lift_act, 0.0)
        below = z_start + s.success_min_height
        taken += self._steps(chunks, self.n_hold, bad, until_rest=True, below=below)
        self.last_steps = taken
        held, rise = self._held(chunks, z_start)
        state = {k: np.concatenate([ch.get(k) for _, ch in chunks])
                 for k in ("qpos", "qvel", "act", "ctrl", "qacc_warmstart")}
        return held & ~bad, rise, bad, state, z_start

    def _push(self, models, table, which, state, z_start, directions):
        """Pushes from saved post-grasp states: (held, rise, bad)."""
        ids, s = self.ids, self.cfg.sim
        chunks = self._chunks(models, table, which)
        n = len(which)
        nbody = models[0].nbody
        force = np.zeros((n, nbody, 6))
        force[:, ids.object_body, :3] = s.push_force * np.asarray(directions)
        for sl, ch in chunks:
            ch.set_state(**{k: v[sl] for k, v in state.items()}, xfrc_applied=force[sl])
        bad = np.zeros(n, bool)
        taken = self._steps(chunks, self.n_push, bad)
        for sl, ch in chunks:
            ch.set_state(xfrc_applied=np.zeros((sl.stop - sl.start, nbody, 6)))
        below = z_start + s.success_min_height
        taken += self._steps(chunks, self.n_push_hold, bad, until_rest=True, below=below)
        self.last_steps = taken
        held, rise = self._held(chunks, z_start)
        return held & ~bad, rise, bad

    def prepare(self, models: list[mujoco.MjModel]) -> MeshTable:
        """Check that the models share one layout, look up its ids and each candidate's
        WORLD_FIELDS (``self.fields``), and return their mesh table."""
        tmpl = models[0]
        for m in models:
            if m.ngeom != tmpl.ngeom or m.nmesh != tmpl.nmesh or m.nq != tmpl.nq:
                raise ValueError("candidate model does not share the first one's layout")
        self.ids = scene_ids(tmpl)
        self.opener_lines = JawOpener(tmpl, self.ids, self.cfg).lines  # the CPU rule's lines
        self._speed_dofs = np.concatenate([self.ids.jaw_dof, [tmpl.jnt_dofadr[
            tmpl.joint("lift").id]]]).astype(np.int64)
        table = MeshTable.of(models)
        self.fields = candidate_fields(models, table)
        return table

    def run(self, models: list[mujoco.MjModel]) -> dict:
        """The 11 trials of every model (``scene.build_model(..., pad_collides=True)``, one
        layout).  Returns dict(outcome [N, 11] uint8, unstable [N] (trials failed by an
        exploding state or an overflowed buffer), steps [N] (physics steps per candidate),
        compile_seconds, step_seconds (stepping after the first step), world_steps,
        approach_seconds (computing the openings), devices,
        overflowed (worlds failed by a full buffer: a warning is logged), peak_pairs (broad-phase
        pairs per world, most in one chunk), mean_pairs (the same, mean over health checks: the
        pairs that reach the narrow phase), listed_pairs (pairs the broad phase tests per world,
        mean over the checks), peak_rows)."""
        table = self.prepare(models)
        s = self.cfg.sim
        host: dict = {}

        def openers(c):
            if c not in host:
                host[c] = (JawOpener(models[c], self.ids, self.cfg), mujoco.MjData(models[c]))
            return host[c]

        n = len(models)
        n_push, n_rob = len(s.stability_directions), len(s.robustness_angles_deg)
        outcome = np.zeros((n, s.n_trials), np.uint8)
        unstable = np.zeros(n, np.int64)
        steps = np.zeros(n, np.int64)
        every = np.arange(n)
        ok, _, bad, state, z_start = self._grasp(models, table, every, np.zeros(n), openers)
        outcome[:, 0] = ok
        unstable += bad
        steps += self.last_steps
        held = np.nonzero(ok)[0]
        if len(held) and n_push:
            idx = np.repeat(held, n_push)
            dirs = np.tile(np.asarray(s.stability_directions, np.float64), (len(held), 1))
            st = {k: v[idx] for k, v in state.items()}
            pok, _, pbad = self._push(models, table, idx, st, z_start[idx], dirs)
            outcome[held, 1: 1 + n_push] = pok.reshape(len(held), n_push)
            unstable[held] += pbad.reshape(len(held), n_push).sum(1)
            steps[held] += n_push * self.last_steps
        if len(held) and n_rob:  # turned grasps
            idx = np.repeat(held, n_rob)
            yaws = np.tile(np.deg2rad(np.asarray(s.robustness_angles_deg, np.float64)), len(held))
            rok, _, rbad, _, _ = self._grasp(models, table, idx, yaws, openers)
            outcome[held, 1 + n_push:] = rok.reshape(len(held), n_rob)
            unstable[held] += rbad.reshape(len(held), n_rob).sum(1)
            steps[held] += n_rob * self.last_steps
        if self.overflowed:
            log.warning("warp backend: %d worlds overflowed a buffer and were failed (broad-phase "
                        "pairs per world up to %.0f of %d slots)", self.overflowed,
                        self.peak_pairs, CONTACTS_PER_WORLD)
        return dict(outcome=outcome, unstable=unstable, steps=steps,
                    compile_seconds=self.compile_seconds, step_seconds=self.step_seconds,
                    world_steps=self.world_steps, approach_seconds=self.approach_seconds,
                    devices=list(self.devices),
                    overflowed=self.overflowed, peak_pairs=self.peak_pairs,
                    mean_pairs=self.pair_sums[0] / max(self.pair_sums[1], 1),
                    listed_pairs=self.pair_sums[2] / max(self.pair_sums[1], 1),
                    peak_rows=self.peak_rows)


def evaluate_models(models: list[mujoco.MjModel], cfg: Config, **kwargs) -> dict:
    """The 11 trials of compiled candidate models (``build_model(..., pad_collides=True)``, one
    layout) on MuJoCo Warp.  See WarpGraspSimulator.run; kwargs go to its constructor."""
    return WarpGraspSimulator(cfg, **kwargs).run(models)
