"""Batched backend: many candidate grasps at once in MJX (JAX), on CPU, GPU or TPU.

One template model per layout (``scene.describe_layout``: K pieces per body, V vertices per
piece); every candidate's geometry (convex mesh data, geom poses and bounds, body mass and
inertia) is stacked along a batch axis and vmapped together with the trials, phases run as
``lax.scan`` over steps, and each phase program is jitted once per (layout, batch size).

Mesh grasps are tractable in MJX by one collision function for all piece pairs and convex data
computed here (``mjx_collision``).

The protocol is the one of ``protocol.py`` (same phases, lengths, thresholds and opening rule):
grasps at yaw 0 first; only candidates that held go on to the four pushes (from the saved
post-grasp state) and the six turned grasps, compacted into smaller batches, so failures stop
costing work.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import jax
import jax.numpy as jp
import mujoco
import numpy as np

from f2f_jax.config import Config
from f2f_jax.sim.mjx_collision import ConvexSizes, convex_data, merged_mesh_collisions, model_convex
from f2f_jax.sim.opening import MJX_LINE_SPACING, line_grid, x_extent
from f2f_jax.sim.protocol import SPIN_RADIUS, lift_targets
from f2f_jax.sim.scene import scene_ids

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from mujoco import mjx
    from mujoco.mjx._src import mesh as mjx_mesh
    from mujoco.mjx._src.types import ConvexMesh

# Model fields that differ between candidates of one layout (found by comparing models of very
# different triples); everything else is shared with the template.
BATCHED_FIELDS = (
    "qpos0", "body_pos", "body_ipos", "body_iquat", "body_mass", "body_subtreemass",
    "body_inertia", "body_invweight0", "dof_invweight0", "dof_M0", "geom_size", "geom_aabb",
    "geom_rbound", "geom_pos", "geom_quat", "geom_friction",
)


# --------------------------------------------------------------------------------------------
# Candidates of one layout as a batch of model fields
# --------------------------------------------------------------------------------------------
@dataclass
class CandidateBatch:
    """Per-candidate model data, stacked on axis 0 (numpy).

    fields: {name: [B, ...]} for BATCHED_FIELDS; convex: ConvexMesh with leaves [B, nmesh, ...];
    planes: [B, G, F, 4] face planes (n, d; n . p + d <= 0 inside) of the object and finger
    geoms in their own frames, for the jaw opening rule.
    """

    fields: dict
    convex: ConvexMesh
    planes: np.ndarray

    def __len__(self):
        return self.planes.shape[0]

    def take(self, idx) -> "CandidateBatch":
        idx = np.asarray(idx)
        return CandidateBatch({k: v[idx] for k, v in self.fields.items()},
                              jax.tree_util.tree_map(lambda x: x[idx], self.convex), self.planes[idx])


def _planes(c: ConvexMesh, faces: int) -> np.ndarray:
    """[faces, 4] planes of a padded convex mesh; padding rows (0, 0, 0, -1) exclude nothing."""
    n = np.asarray(c.face_normal, np.float64)
    d = -np.einsum("fk,fk->f", n, np.asarray(c.face[:, 0], np.float64))
    out = np.concatenate([n, d[:, None]], 1)
    # repeated (padded) faces are harmless duplicates; keep them as they are
    return out[:faces]


class MjxGraspSimulator:
    """The 11 trials for batches of candidates sharing one layout, in MJX.

    cfg: Config (SimConfig phases and physics, GeometryConfig layout).
    template: a model from ``scene.build_model(..., pad_collides=True)``; any candidate's.
    """

    def __init__(self, template: mujoco.MjModel, cfg: Config):
        self.cfg = cfg
        self.sizes = ConvexSizes.for_vertices(cfg.geometry.hull_vertices)
        self.ids = scene_ids(template)
        self.template_mj = template
        self.geoms = np.concatenate([self.ids.object_geoms, self.ids.all_finger_geoms])
        n_obj = len(self.ids.object_geoms)
        nf = len(self.ids.finger_geoms[0])
        self.geom_role = np.array([0] * n_obj + [1] * nf + [2] * nf)  # object, left, right
        tmpl = template
        orig = mjx_mesh.convex
        mjx_mesh.convex = lambda m, i: jax.tree_util.tree_map(
            jp.asarray, convex_data(m.mesh_vert[m.mesh_vertadr[i]: m.mesh_vertadr[i] + m.mesh_vertnum[i]],
                                    self.sizes))
        try:
            with merged_mesh_collisions():
                self.mx = mjx.put_model(tmpl)
                self.d0 = mjx.make_data(self.mx)
        finally:
            mjx_mesh.convex = orig
        s = cfg.sim
        self.n_settle, self.n_close = s.steps(s.settle_time), s.steps(s.close_time)
        self.n_hold, self.n_push = s.steps(s.hold_time), s.steps(s.push_time)
        self.n_push_hold = s.steps(s.push_hold_time)
        targets = lift_targets(cfg)
        self.lift_ctrl = np.diff(targets) / s.timestep  # per step: exact chord of the profile
        self.lines = line_grid(cfg, MJX_LINE_SPACING).astype(np.float32)
        self._programs: dict = {}
        self.compile_seconds = 0.0

    # ---------------------------------------------------------------- candidates -> batch
    def batch(self, models: list[mujoco.MjModel]) -> CandidateBatch:
        """Stack the varying fields of compiled candidate models (same layout as the template)."""
        fields = {k: np.stack([np.asarray(getattr(m, k)) for m in models]) for k in BATCHED_FIELDS}
        convex, planes = [], []
        for m in models:
            if m.ngeom != self.template_mj.ngeom or m.nmesh != self.template_mj.nmesh:
                raise ValueError("candidate model does not share the template's layout")
            meshes = model_convex(m, self.sizes)
            convex.append(jax.tree_util.tree_map(lambda *x: np.stack(x), *meshes))
            planes.append(np.stack([_planes(meshes[m.geom_dataid[gid]], self.sizes.faces)
                                    for gid in self.geoms]))
        stacked = jax.tree_util.tree_map(lambda *x: np.stack(x), *convex)
        return CandidateBatch(fields, stacked, np.stack(planes).astype(np.float32))

    # ---------------------------------------------------------------- one candidate, traced
    def _model(self, fields, convex):
        nmesh = self.template_mj.nmesh
        meshes = tuple(jax.tree_util.tree_map(lambda x, i=i: x[i], convex) for i in range(nmesh))
        return self.mx.replace(**fields).tree_replace({"_impl.mesh_convex": meshes})

    def _intervals(self, planes, xpos, xmat):
        """Union of the geoms' extents along x on every line: (lo [L], hi [L]), +-inf on a miss.
        planes: [G, F, 4] geom-local; xpos [G, 3]; xmat [G, 3, 3]."""
        y, z = jp.asarray(self.lines[:, 0]), jp.asarray(self.lines[:, 1])

        def one(acc, geom):
            lo, hi = acc
            pl, pos, mat = geom
            lower, upper, ok = x_extent(pl, mat, pos, y, z, jp)
            return (jp.where(ok, jp.minimum(lo, lower), lo), jp.where(ok, jp.maximum(hi, upper), hi)), None

        init = (jp.full(y.shape, jp.inf), jp.full(y.shape, -jp.inf))
        (lo, hi), _ = jax.lax.scan(one, init, (planes, xpos, xmat.reshape(-1, 3, 3)))
        return lo, hi

    def _healthy(self, d):
        ids, s = self.ids, self.cfg.sim
        v = d.qvel[ids.object_dof: ids.object_dof + 6]
        other = d.qvel[np.concatenate([ids.jaw_dof, [self.template_mj.jnt_dofadr[
            self.template_mj.joint("lift").id]]])]
        speed = jp.maximum(jp.maximum(jp.linalg.norm(v[:3]), jp.linalg.norm(v[3:]) * SPIN_RADIUS),
                           jp.abs(other).max())
        finite = jp.all(jp.isfinite(d.qpos)) & jp.all(jp.isfinite(d.qvel))
        return finite & (speed <= s.max_speed)

    def _run(self, m, d, bad, xs, body):
        """One lax.scan over the steps of a program: ``body(d, x) -> d`` sets the controls of a
        step from its inputs ``x`` (unbatched: every candidate is in the same phase), then MJX
        steps.  A single mjx.step in the program keeps compile time to one copy of the physics."""
        def step(state, x):
            d, bad = state
            d = mjx.step(m, body(d, x))
            return (d, bad | ~self._healthy(d)), None

        (d, bad), _ = jax.lax.scan(step, (d, bad), xs)
        return d, bad

    def _held(self, m, d, z_start):
        # The contacts of the last step (its forward pass): a second collision pass in the
        # program would double its compile time for a state one step older.
        ids, s = self.ids, self.cfg.sim
        c = d._impl.contact
        g1, g2 = c.geom1, c.geom2
        obj_g, fin_g = jp.asarray(ids.object_geoms), jp.asarray(ids.all_finger_geoms)
        obj = jp.isin(g1, obj_g) | jp.isin(g2, obj_g)
        fin = jp.isin(g1, fin_g) | jp.isin(g2, fin_g)
        pair = obj & fin
        touching = jp.any(pair & (c.dist < 0))
        rise = d.xipos[ids.object_body, 2] - z_start
        return (rise >= s.success_min_height) & touching, rise

    def _grasp_one(self, fields, convex, planes, yaw):
        ids, s = self.ids, self.cfg.sim
        m = self._model(fields, convex)
        low, high = jp.asarray(ids.jaw_range[:, 0]), jp.asarray(ids.jaw_range[:, 1])
        role = self.geom_role
        # finger reach, measured with the mount planes on the gripper's centre plane
        d = self.d0.replace(qpos=fields["qpos0"].at[ids.jaw_qpos].set(0.0))
        dk = mjx.kinematics(m, d)
        gx, gm = dk.geom_xpos[self.geoms], dk.geom_xmat[self.geoms]
        _, left_hi = self._intervals(planes[role == 1], gx[role == 1], gm[role == 1])
        right_lo, _ = self._intervals(planes[role == 2], gx[role == 2], gm[role == 2])
        # place: object turned by yaw, jaws fully open, lift at rest
        q = fields["qpos0"].at[ids.object_qpos + 3: ids.object_qpos + 7].set(
            jp.stack([jp.cos(yaw / 2), 0.0, 0.0, jp.sin(yaw / 2)]))
        q = q.at[ids.jaw_qpos].set(high)
        ctrl = jp.zeros(self.mx.nu).at[ids.grip_act].set(high)
        d = self.d0.replace(qpos=q, ctrl=ctrl)
        obj = role == 0

        def approach(d):
            """protocol.approach: open to the margin from where the object now lies, then
            command the jaws beyond any contact so both servos saturate."""
            dk = mjx.kinematics(m, d)
            gx, gm = dk.geom_xpos[self.geoms], dk.geom_xmat[self.geoms]
            obj_lo, obj_hi = self._intervals(planes[obj], gx[obj], gm[obj])
            gap_l = jp.where(jp.isfinite(left_hi - obj_lo), left_hi - obj_lo, -jp.inf).max()
            gap_r = jp.where(jp.isfinite(obj_hi - right_lo), obj_hi - right_lo, -jp.inf).max()
            openings = jp.stack([gap_l, gap_r]) + s.open_margin
            openings = jp.clip(jp.where(jp.isfinite(openings), openings, low), low, high)
            return d.replace(qpos=d.qpos.at[ids.jaw_qpos].set(openings),
                             qvel=d.qvel.at[ids.jaw_dof].set(0.0),
                             ctrl=d.ctrl.at[ids.grip_act].set(low))

        def body(d, x):
            k, lift = x
            d = jax.lax.cond(k == self.n_settle, approach, lambda d: d, d)
            z = jax.lax.cond(k == self.n_settle, lambda d: d.xipos[ids.object_body, 2],
                             lambda d: jp.float32(0.0), d)
            return d.replace(ctrl=d.ctrl.at[ids.lift_act].set(lift)), z

        def step(state, x):
            d, bad, z_start = state
            d, z = body(d, x)
            z_start = jp.where(x[0] == self.n_settle, z, z_start)
            d = mjx.step(m, d)
            return (d, bad | ~self._healthy(d), z_start), None

        (d, bad, z_start), _ = jax.lax.scan(step, (d, jp.array(False), jp.float32(0.0)),
                                            self._grasp_xs())
        ok, rise = self._held(m, d, z_start)
        state = (d.qpos, d.qvel, d.act, d.ctrl, d.qacc_warmstart, d.time)
        return ok & ~bad, rise, bad, state, z_start

    def _push_one(self, fields, convex, state, z_start, direction):
        ids, s = self.ids, self.cfg.sim
        m = self._model(fields, convex)
        qpos, qvel, act, ctrl, warm, t = state
        d = self.d0.replace(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, qacc_warmstart=warm, time=t)
        push = jp.zeros((self.mx.nbody, 6)).at[ids.object_body, :3].set(s.push_force * direction)
        on = np.arange(self.n_push + self.n_push_hold) < self.n_push

        def body(d, push_on):
            return d.replace(xfrc_applied=jp.where(push_on, push, 0.0))

        d, bad = self._run(m, d, jp.array(False), jp.asarray(on), body)
        ok, rise = self._held(m, d, z_start)
        return ok & ~bad, rise, bad

    def _grasp_xs(self):
        """Per-step inputs of the grasp program: (step index, lift speed command).  The jaws
        are placed at step n_settle (approach), then the lift follows its profile."""
        n_lift = len(self.lift_ctrl)
        total = self.n_settle + self.n_close + n_lift + self.n_hold
        lift = np.zeros(total, np.float32)
        lift[self.n_settle + self.n_close: self.n_settle + self.n_close + n_lift] = self.lift_ctrl
        return jp.arange(total), jp.asarray(lift)

    # ---------------------------------------------------------------- batched programs
    def _program(self, name: str, size: int):
        key = (name, size)
        if key not in self._programs:
            fn = {"grasp": self._grasp_one, "push": self._push_one}[name]
            self._programs[key] = jax.jit(jax.vmap(fn))
        return self._programs[key]

    def _call(self, name, size, *args):
        """Run a program on one bucket-sized batch, tracing under the merged collision groups.
        The batch axis is sharded over all local devices."""
        prog = self._program(name, size)
        devices = jax.local_devices()
        if len(devices) > 1 and size % len(devices) == 0:
            mesh = jax.sharding.Mesh(np.array(devices), ("batch",))
            sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
            args = jax.device_put(args, sharding)
        first = not getattr(prog, "_f2f_compiled", False)
        t = time.perf_counter()
        with merged_mesh_collisions():
            out = prog(*args)
        out = jax.block_until_ready(out)
        if first:
            self.compile_seconds += time.perf_counter() - t
            prog._f2f_compiled = True
        return out

    @staticmethod
    def bucket(n: int, minimum: int = 1) -> int:
        """Batch sizes are powers of two (>= minimum), so few programs are ever compiled."""
        return max(minimum, 1 << max(0, math.ceil(math.log2(max(n, 1)))))

    def _chunks(self, n: int, chunk: int):
        for start in range(0, n, chunk):
            yield np.arange(start, min(start + chunk, n))

    def run(self, batch: CandidateBatch, *, chunk: int = 1024) -> dict:
        """The 11 trials of every candidate of ``batch``.

        Returns dict(outcome [B, 11] uint8, unstable [B] int, steps [B] int (physics steps
        simulated per candidate), compile_seconds).
        """
        s = self.cfg.sim
        n = len(batch)
        n_push, n_rob = len(s.stability_directions), len(s.robustness_angles_deg)
        outcome = np.zeros((n, s.n_trials), np.uint8)
        unstable = np.zeros(n, np.int64)
        steps = np.zeros(n, np.int64)
        grasp_steps = self.n_settle + self.n_close + len(self.lift_ctrl) + self.n_hold
        push_steps = self.n_push + self.n_push_hold

        def run_program(name, index, extra):
            """Run ``name`` over candidates ``index`` with per-item ``extra`` args, in chunks."""
            results = []
            for part in self._chunks(len(index), chunk):
                size = self.bucket(len(part))
                idx = np.concatenate([part, np.repeat(part[:1], size - len(part))])
                sub = batch.take(index[idx])
                args = [sub.fields, sub.convex]
                if name == "grasp":
                    args += [sub.planes, *[e[idx] for e in extra]]
                else:
                    args += [jax.tree_util.tree_map(lambda x: x[idx], e) for e in extra]
                out = self._call(name, size, *args)
                results.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[: len(part)], out))
            return jax.tree_util.tree_map(lambda *x: np.concatenate(x), *results)

        every = np.arange(n)
        ok, _, bad, state, z_start = run_program("grasp", every, [np.zeros(n, np.float32)])
        outcome[:, 0] = ok
        unstable += bad
        steps += grasp_steps
        held = np.nonzero(ok)[0]
        if len(held) and n_push:
            # pushes from each held candidate's post-grasp state
            idx = np.repeat(held, n_push)
            dirs = np.tile(np.asarray(s.stability_directions, np.float32), (len(held), 1))
            st = jax.tree_util.tree_map(lambda x: x[idx], state)
            pok, _, pbad = run_program("push", idx, [st, z_start[idx], dirs])
            outcome[held, 1: 1 + n_push] = pok.reshape(len(held), n_push)
            unstable[held] += pbad.reshape(len(held), n_push).sum(1)
            steps[held] += n_push * push_steps
        if len(held) and n_rob:  # turned grasps
            idx = np.repeat(held, n_rob)
            yaws = np.tile(np.deg2rad(np.asarray(s.robustness_angles_deg, np.float32)), len(held))
            rok, _, rbad, _, _ = run_program("grasp", idx, [yaws])
            outcome[held, 1 + n_push:] = rok.reshape(len(held), n_rob)
            unstable[held] += rbad.reshape(len(held), n_rob).sum(1)
            steps[held] += n_rob * grasp_steps
        return dict(outcome=outcome, unstable=unstable, steps=steps,
                    compile_seconds=self.compile_seconds)


# --------------------------------------------------------------------------------------------
# evaluate(..., backend="mjx")
# --------------------------------------------------------------------------------------------
_SIMULATORS: dict = {}


def simulator_for(model: mujoco.MjModel, cfg: Config) -> MjxGraspSimulator:
    """One simulator (template and compiled programs) per configuration, reused across calls."""
    key = (cfg, model.ngeom, model.nmesh)
    if key not in _SIMULATORS:
        _SIMULATORS[key] = MjxGraspSimulator(model, cfg)
    return _SIMULATORS[key]


def evaluate_models(models: list[mujoco.MjModel], cfg: Config, *, chunk: int | None = None) -> dict:
    """The 11 trials of compiled candidate models (``build_model(..., pad_collides=True,
    max_geom_pairs=MAX_GEOM_PAIRS, max_contact_points=MAX_CONTACT_POINTS)``, one layout) in MJX.
    See MjxGraspSimulator.run."""
    sim = simulator_for(models[0], cfg)
    batch = sim.batch(models)
    if chunk is None:
        chunk = default_chunk()
    return sim.run(batch, chunk=chunk)


def default_chunk() -> int:
    """Candidates per program call: from the accelerator's memory where it reports it (measured
    ~2.5 MB of device memory per candidate with the default layout, ~4x that while compiling),
    else 64 on a CPU, where larger batches only add latency."""
    dev = jax.local_devices()[0]
    stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    if dev.platform == "cpu" or not stats or "bytes_limit" not in stats:
        return 64
    per_candidate = 10 * 2**20
    n = int(0.6 * stats["bytes_limit"] / per_candidate) * jax.local_device_count()
    return max(8, min(4096, 1 << int(math.log2(max(n, 8)))))
