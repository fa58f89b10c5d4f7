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
  profile's exact chord each step.
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
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import numpy as np

from f2f_jax.config import Config
from f2f_jax.errors import MissingExtraError

try:
    import warp as wp

    # warp prints a banner and a line per compiled module; a library's user did not ask for them
    wp.config.quiet = True
    import mujoco_warp as mjw
except ImportError as exc:  # pragma: no cover - exercised where the extra is missing
    raise MissingExtraError(
        f"backend='warp' needs MuJoCo Warp ({exc.name} is not installed): "
        'pip install -e ".[warp]"') from exc

from f2f_jax.sim.protocol import CHECK_EVERY, SPIN_RADIUS, lift_targets
from f2f_jax.sim.opening import BACKOFF_ROUNDS, JawOpener
from f2f_jax.sim.scene import scene_ids

log = logging.getLogger(__name__)

# Model fields that differ between candidates of one layout (as the MJX backend's
# BATCHED_FIELDS, plus the mesh each geom uses); everything else is the template's.
WORLD_FIELDS = (
    "qpos0", "body_pos", "body_ipos", "body_iquat", "body_mass", "body_subtreemass",
    "body_inertia", "body_invweight0", "dof_invweight0", "geom_dataid", "geom_size",
    "geom_aabb", "geom_rbound", "geom_pos", "geom_quat", "geom_friction",
)
# Per-mesh fields that address the shared tables, and the table each one points into.
_MESH_ADR = {"mesh_vertadr": "mesh_vert", "mesh_faceadr": "mesh_face",
             "mesh_normaladr": "mesh_normal", "mesh_graphadr": "mesh_graph",
             "mesh_polyadr": "mesh_polynormal"}
_MESH_PLAIN = ("mesh_vertnum", "mesh_normalnum", "mesh_polynum", "mesh_pos", "mesh_quat")
# Per-polygon and per-vertex fields that address tables of their own.
_POLY_ADR = {"mesh_polyvertadr": "mesh_polyvert"}
_VERT_ADR = {"mesh_polymapadr": "mesh_polymap"}
_TABLES = ("mesh_vert", "mesh_face", "mesh_normal", "mesh_graph", "mesh_polynormal",
           "mesh_polyvertnum", "mesh_polyvert", "mesh_polymapnum", "mesh_polymap")
# Tables whose length is a Model count (mesh_vert -> nmeshvert, ...).
_COUNTED = {"mesh_vert": "nmeshvert", "mesh_face": "nmeshface", "mesh_normal": "nmeshnormal",
            "mesh_graph": "nmeshgraph", "mesh_polynormal": "nmeshpoly",
            "mesh_polyvert": "nmeshpolyvert", "mesh_polymap": "nmeshpolymap"}
# Contact slots per world.  MuJoCo Warp's broad phase writes every pair whose bounds overlap into
# the same pool as the contacts: a held imprint grasp of the default layout had ~150 such pairs
# per world and 29 contacts (warp's CPU device, tiny config), so 512 leaves room.  Constraint
# rows per world: elliptic cones with condim 4 take 4 rows per contact; 400 overflowed in
# default-config grasps of builtin objects (more contacts than plain MuJoCo keeps).
CONTACTS_PER_WORLD = 512
ROWS_PER_WORLD = 1024
# Device memory per world: the Model and Data arrays took 0.3 MB per world (measured on warp's
# CPU device, default layout, one candidate per world, with 320 contact slots and 400 rows; the
# buffers above take more); the step's collision buffers come on top.  3 MB is a guess with room until it is measured on a GPU; chunks keep
# within 60% of a device's memory.
BYTES_PER_WORLD = 3 * 2**20
# Where the approach's openings are computed: "device" (``opening.JawOpener``'s rule on the
# device: a kernel over every world and line of its grid, then its back-off by exact
# distances, from collision passes with a margin), or "host" (``opening.JawOpener`` itself, per
# world: ~20 ms of a host core each).
APPROACHES = ("device", "host")
# Overflows that lose pairs, contacts or constraint rows: the world's physics is wrong.  The
# solver's iteration limits (ITERATIONS, LS_ITERATIONS) are not among them: plain MuJoCo stops
# at the same limits without a word.
_OT = mjw.OverflowType
_LOST = int(_OT.NEFC | _OT.NJMAX_NNZ | _OT.BROADPHASE | _OT.NARROWPHASE | _OT.CCD
            | _OT.EPA_HORIZON | _OT.NVMAX)
# Devices whose kernels this process has compiled (loaded from warp's disk cache, or built):
# the first step on each is timed as compiling.
_WARM_DEVICES: set = set()


def local_devices() -> list[str]:
    """Every CUDA device warp sees, or ["cpu"] without one."""
    n = wp.get_cuda_device_count()
    return [f"cuda:{i}" for i in range(n)] if n else ["cpu"]


def default_worlds(device: str) -> int:
    """Worlds per chunk on ``device``: from its memory on a GPU, 64 on a CPU (where more worlds
    only add latency)."""
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return 64
    n = int(0.6 * dev.total_memory / BYTES_PER_WORLD)
    return max(64, min(16384, 1 << int(math.log2(max(n, 64)))))


# --------------------------------------------------------------------------------------------
# Small kernels: controls and forces set on the device, without a host round trip
# --------------------------------------------------------------------------------------------
@wp.kernel
def _set_column(values: wp.array2d(dtype=float), col: int, value: float):
    w = wp.tid()
    values[w, col] = value


@wp.func
def _span(dataid: wp.array2d(dtype=int), planes: wp.array2d(dtype=wp.vec4),
          nplane: wp.array(dtype=int), geoms: wp.array(dtype=int),
          xpos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33), w: int,
          y: float, z: float):
    """Union of the geoms' extents along x on the line (y, z): (lo, hi), (+big, -big) on a
    miss (``opening.JawOpener._intervals``, one line, one world)."""
    lo = float(1.0e30)
    hi = float(-1.0e30)
    for i in range(geoms.shape[0]):
        g = geoms[i]
        mesh = dataid[w, g]
        if mesh < 0:
            continue
        rot = xmat[w, g]
        pos = xpos[w, g]
        upper = float(1.0e30)
        lower = float(-1.0e30)
        ok = bool(True)
        for f in range(nplane[mesh]):
            pl = planes[mesh, f]
            n = rot * wp.vec3(pl[0], pl[1], pl[2])
            d = pl[3] - wp.dot(n, pos)
            c = -(d + n[1] * y + n[2] * z)
            if n[0] > 1.0e-12:
                upper = wp.min(upper, c / n[0])
            elif n[0] < -1.0e-12:
                lower = wp.max(lower, c / n[0])
            elif c < 0.0:
                ok = False
        if ok and lower <= upper:
            lo = wp.min(lo, lower)
            hi = wp.max(hi, upper)
    return lo, hi


@wp.kernel
def _clearance(dataid: wp.array2d(dtype=int), planes: wp.array2d(dtype=wp.vec4),
               nplane: wp.array(dtype=int), obj: wp.array(dtype=int), left: wp.array(dtype=int),
               right: wp.array(dtype=int), xpos: wp.array2d(dtype=wp.vec3),
               xmat: wp.array2d(dtype=wp.mat33), fxpos: wp.array2d(dtype=wp.vec3),
               fxmat: wp.array2d(dtype=wp.mat33), lines: wp.array(dtype=wp.vec2),
               need: wp.array2d(dtype=float)):
    """need[w] = max over lines of (left reach - object's near side, object's far side - right
    reach): the openings less the margin, as ``opening.JawOpener`` computes them.  Fingers at
    their jaw-0 poses (fxpos, fxmat), the object where it lies now (xpos, xmat)."""
    w, k = wp.tid()
    y = lines[k][0]
    z = lines[k][1]
    olo, ohi = _span(dataid, planes, nplane, obj, xpos, xmat, w, y, z)
    if olo > ohi:
        return
    llo, lhi = _span(dataid, planes, nplane, left, fxpos, fxmat, w, y, z)
    if llo <= lhi:
        wp.atomic_max(need, w, 0, lhi - olo)
    rlo, rhi = _span(dataid, planes, nplane, right, fxpos, fxmat, w, y, z)
    if rlo <= rhi:
        wp.atomic_max(need, w, 1, ohi - rlo)


# --------------------------------------------------------------------------------------------
# Candidates -> one model with per-world geometry
# --------------------------------------------------------------------------------------------
@dataclass
class MeshTable:
    """The meshes of several compiled models in one table; ``offset[c]`` is candidate c's first
    mesh id in it."""

    fields: dict
    offset: np.ndarray
    sizes: dict  # the Model's counts of the table (nmesh, nmeshvert, ..., npolygonmax)
    planes: np.ndarray  # [nmesh, F, 4] face planes (n, d), n . p + d <= 0 inside, mesh frame;
    # rows past a mesh's faces are (0, 0, 0, -1), which exclude nothing

    @classmethod
    def of(cls, models: list[mujoco.MjModel]) -> "MeshTable":
        out: dict[str, list] = {k: [] for k in (*_MESH_ADR, *_MESH_PLAIN, *_POLY_ADR, *_VERT_ADR,
                                               *_TABLES)}
        sizes = {t: 0 for t in _TABLES}
        offset, nmesh = [], 0
        for m in models:
            offset.append(nmesh)
            nmesh += m.nmesh
            for adr, table in {**_MESH_ADR, **_POLY_ADR, **_VERT_ADR}.items():
                a = np.array(getattr(m, adr))
                out[adr].append(np.where(a >= 0, a + sizes[table], a))
            for name in _MESH_PLAIN:
                out[name].append(np.array(getattr(m, name)))
            for table in _TABLES:
                t = np.array(getattr(m, table))
                out[table].append(t)
                sizes[table] += len(t)
        fields = {k: np.concatenate(v) for k, v in out.items()}
        counts = {"nmesh": nmesh, **{_COUNTED[t]: n for t, n in sizes.items() if t in _COUNTED}}
        counts["npolygonmax"] = max(int(m.npolygonmax) for m in models)
        counts["nmeshdegmax"] = max(int(m.nmeshdegmax) for m in models)
        return cls(fields, np.asarray(offset, np.int64), counts, _face_planes(fields))


def _face_planes(f: dict) -> np.ndarray:
    """[nmesh, F, 4] outward face planes of every mesh of a table, from MuJoCo's polygons (the
    hull's faces, coplanar triangles merged) and one vertex of each."""
    nmesh = len(f["mesh_polyadr"])
    most = int(f["mesh_polynum"].max()) if nmesh else 0
    out = np.zeros((nmesh, max(most, 1), 4))
    out[..., 3] = -1.0
    mesh = np.repeat(np.arange(nmesh), f["mesh_polynum"])
    poly = f["mesh_polyadr"][mesh] + (np.arange(len(mesh)) - np.repeat(
        np.cumsum(f["mesh_polynum"]) - f["mesh_polynum"], f["mesh_polynum"]))
    slot = poly - f["mesh_polyadr"][mesh]
    n = f["mesh_polynormal"][poly]
    vert = f["mesh_vert"][f["mesh_vertadr"][mesh] + f["mesh_polyvert"][f["mesh_polyvertadr"][poly]]]
    out[mesh, slot, :3] = n
    out[mesh, slot, 3] = -np.einsum("pk,pk->p", n, vert)
    return out


def candidate_fields(models: list[mujoco.MjModel], table: MeshTable) -> dict:
    """{field: [N, ...]} of WORLD_FIELDS, one row per candidate of ``models`` (the order of
    ``table``): a world of candidate c takes row c.  ``geom_dataid`` points into the table;
    build_model's empty slots (invisible placeholders) get -1."""
    per = []
    for c, m in enumerate(models):
        dataid = np.array(m.geom_dataid)
        placeholder = np.asarray(m.geom_rgba)[:, 3] == 0.0
        mesh = dataid >= 0
        dataid = np.where(mesh, dataid + table.offset[c], dataid)
        dataid[mesh & placeholder] = -1
        per.append({k: (dataid if k == "geom_dataid" else np.array(getattr(m, k)))
                    for k in WORLD_FIELDS})
    return {k: np.stack([row[k] for row in per]) for k in WORLD_FIELDS}


def _finger_object(geom: np.ndarray, fingers, obj) -> np.ndarray:
    """[C] bool: contacts (geom pairs [C, 2]) between one of ``fingers`` and one of ``obj``."""
    return ((np.isin(geom[:, 0], fingers) & np.isin(geom[:, 1], obj))
            | (np.isin(geom[:, 1], fingers) & np.isin(geom[:, 0], obj)))


class _Chunk:
    """One device's share of a round: its model, data and host-side view of the worlds."""

    def __init__(self, template: mujoco.MjModel, table: MeshTable, fields: dict, device: str):
        nworld = len(fields["qpos0"])
        self.device, self.nworld = device, nworld
        self._graph, self._steps_taken = None, 0
        self._capture = wp.get_device(device).is_cuda
        with wp.ScopedDevice(device):
            m = mjw.put_model(template, batch_sizes={k: nworld for k in WORLD_FIELDS})
            for k, v in table.fields.items():
                setattr(m, k, wp.array(v, dtype=getattr(m, k).dtype))
            for k, v in fields.items():
                arr = getattr(m, k)
                setattr(m, k, wp.array(v, dtype=arr.dtype, shape=arr.shape))
            m.opt.warn_overflow = _LOST  # printed from the device; iteration limits are not
            for k, v in table.sizes.items():
                setattr(m, k, v)
            self.m = m
            self.d = mjw.put_data(template, mujoco.MjData(template), nworld=nworld,
                                  nconmax=CONTACTS_PER_WORLD, njmax=ROWS_PER_WORLD)
            self.planes = wp.array(table.planes.astype(np.float32), dtype=wp.vec4)
            self.nplane = wp.array(table.fields["mesh_polynum"].astype(np.int32), dtype=int)
            self.finger_xpos = self.finger_xmat = None
            self._reach = None  # (reach, the fingers' margins for finger_distance's pass)

    def kinematics(self):
        """Positions of every body and geom for the current qpos (a step leaves those of the
        state before it)."""
        with wp.ScopedDevice(self.device):
            mjw.kinematics(self.m, self.d)

    def keep_finger_poses(self, qpos: np.ndarray, jaw_qpos: np.ndarray):
        """The geoms' poses with the jaws at 0 (the fingers' reach is measured there), kept for
        ``clearance``; leaves the state to be set by the caller."""
        q = np.array(qpos)
        q[:, jaw_qpos] = 0.0
        self.set_state(qpos=q)
        with wp.ScopedDevice(self.device):
            mjw.kinematics(self.m, self.d)
            self.finger_xpos = wp.clone(self.d.geom_xpos)
            self.finger_xmat = wp.clone(self.d.geom_xmat)

    def finger_distance(self, ids, reach: float) -> np.ndarray:
        """[W, 2] smallest distance (m) between each jaw's finger pieces and the object's at the
        current qpos, where it is below ``reach`` (``reach`` elsewhere), as
        ``scene.finger_object_distance``: one collision pass with the fingers' margin set to
        ``reach``, so pairs closer than that report their distance as a contact's."""
        own = self.m.geom_margin
        if self._reach is None or self._reach[0] != reach:
            margin = np.zeros(own.shape, np.float32)
            margin[:, ids.all_finger_geoms] = reach
            self._reach = (reach, wp.array(margin, dtype=own.dtype, device=self.device))
        self.m.geom_margin = self._reach[1]
        try:
            with wp.ScopedDevice(self.device):
                mjw.kinematics(self.m, self.d)
                mjw.collision(self.m, self.d)
        finally:
            self.m.geom_margin = own
        best = np.full((self.nworld, 2), reach)
        geom, dist, world = self.contacts()
        for side in (0, 1):
            pair = _finger_object(geom, ids.finger_geoms[side], ids.object_geoms)
            np.minimum.at(best[:, side], world[pair], dist[pair])
        return best

    def clearance(self, lines: wp.array, obj: wp.array, left: wp.array, right: wp.array) -> np.ndarray:
        """[W, 2] what each jaw must open, less the margin (``_clearance``), for the object where
        it lies now (after ``kinematics``); -1e30 where no line meets both."""
        need = wp.full((self.nworld, 2), -1.0e30, dtype=float, device=self.device)
        wp.launch(_clearance, dim=(self.nworld, lines.shape[0]), device=self.device,
                  inputs=[self.m.geom_dataid, self.planes, self.nplane, obj, left, right,
                          self.d.geom_xpos, self.d.geom_xmat, self.finger_xpos, self.finger_xmat,
                          lines, need])
        return need.numpy()

    def set_state(self, **arrays):
        for k, v in arrays.items():
            arr = getattr(self.d, k)
            arr.assign(np.asarray(v, np.float32).reshape(arr.shape + getattr(arr.dtype, "_shape_", ())))

    def get(self, name: str) -> np.ndarray:
        return getattr(self.d, name).numpy()

    def contacts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The contacts of the last collision pass: geom pairs [C, 2], distances [C], worlds [C]."""
        nacon = int(self.get("nacon")[0])
        c = self.d.contact
        return c.geom.numpy()[:nacon], c.dist.numpy()[:nacon], c.worldid.numpy()[:nacon]

    def set_column(self, name: str, col: int, value: float):
        wp.launch(_set_column, dim=self.nworld, inputs=[getattr(self.d, name), col, float(value)],
                  device=self.device)

    def step(self):
        """One physics step of every world.  On a GPU the step is a CUDA graph captured at the
        second call (the first loads the kernels), so one launch replays its ~100 kernels; if
        capturing fails, steps are launched kernel by kernel (slower, same physics)."""
        with wp.ScopedDevice(self.device):
            if self._graph is not None:
                wp.capture_launch(self._graph)
                return
            if self._steps_taken >= 1 and self._capture:
                try:
                    with wp.ScopedCapture() as capture:
                        mjw.step(self.m, self.d)
                    self._graph = capture.graph
                    wp.capture_launch(self._graph)  # the captured step did not run yet
                    return
                except Exception as exc:  # noqa: BLE001 - a slower path remains
                    log.warning("warp backend: CUDA graph capture failed on %s (%s); "
                                "launching kernels one by one", self.device, exc)
                    self._capture = False
            mjw.step(self.m, self.d)
            self._steps_taken += 1


# --------------------------------------------------------------------------------------------
# The trials
# --------------------------------------------------------------------------------------------
class WarpGraspSimulator:
    """The 11 trials of candidate models (one layout) as MuJoCo Warp worlds.

    cfg: Config; every phase runs to its full length (``rest_speed`` is not used: lock-step
    worlds cannot end phases early one by one), as in the ``reference`` preset.
    devices: warp devices to spread worlds over (default every local GPU, else the CPU);
    worlds: worlds per chunk (default ``default_worlds``); threads: host threads for the
    openings (default: Python's pool default).
    """

    def __init__(self, cfg: Config, *, devices: list[str] | None = None, worlds: int | None = None,
                 threads: int | None = None, approach: str = "device"):
        if approach not in APPROACHES:
            raise ValueError(f"approach {approach!r}: one of {APPROACHES}")
        self.cfg = cfg
        self.approach = approach
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

    # ---------------------------------------------------------------- rounds
    def _chunks(self, models, table, which):
        """Split worlds ``which`` (candidate indices) over the devices in chunks; returns
        [(slice, _Chunk)]."""
        out, start = [], 0
        per = [self.worlds or default_worlds(dev) for dev in self.devices]
        n = len(which)
        while start < n:
            for dev, size in zip(self.devices, per):
                if start >= n:
                    break
                stop = min(n, start + size)
                fields = {k: v[which[start:stop]] for k, v in self.fields.items()}
                out.append((slice(start, stop), _Chunk(models[0], table, fields, dev)))
                start = stop
        return out

    def _steps(self, chunks, n, healthy_state, before_step=None):
        """Step every chunk ``n`` times (lock-step), checking health every CHECK_EVERY steps;
        ``before_step(k)`` may change controls first."""
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
            if (k + 1) % CHECK_EVERY == 0 or k == n - 1:
                self._check(chunks, healthy_state)
        for _, ch in chunks:
            wp.synchronize_device(ch.device)
        self.step_seconds += time.perf_counter() - t
        self.world_steps += n * sum(ch.nworld for _, ch in chunks)

    def _check(self, chunks, bad):
        """bad[w] |= the state is not finite or anything moves faster than max_speed."""
        s, ids = self.cfg.sim, self.ids
        for sl, ch in chunks:
            qpos, qvel = ch.get("qpos"), ch.get("qvel")
            v = qvel[:, ids.object_dof: ids.object_dof + 6]
            speed = np.maximum.reduce([np.linalg.norm(v[:, :3], axis=1),
                                       np.linalg.norm(v[:, 3:], axis=1) * SPIN_RADIUS,
                                       np.abs(qvel[:, self._speed_dofs]).max(1)])
            finite = np.isfinite(qpos).all(1) & np.isfinite(qvel).all(1)
            # a world whose pairs, contacts or constraint rows overflowed their buffers lost some
            # of them: its physics is wrong, so it fails like an exploding one, and is counted
            overflow = (ch.get("overflow") & _LOST) != 0
            self.overflowed += int(np.count_nonzero(overflow & ~bad[sl]))
            bad[sl] |= ~finite | ~(speed <= s.max_speed) | overflow
            self.peak_pairs = max(self.peak_pairs, int(ch.get("ncollision")[0]) / ch.nworld)
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
            pair = _finger_object(geom, ids.all_finger_geoms, ids.object_geoms)
            hit = world[pair & (dist < 0)]
            touching[sl.start + np.unique(hit)] = True
        return (rise >= s.success_min_height) & touching, rise

    # ---------------------------------------------------------------- programs
    def _device_openings(self, ch: _Chunk) -> np.ndarray:
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
        self._steps(chunks, self.n_settle, bad)
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
        self._steps(chunks, self.n_close, bad)

        def lift(k):
            for _, ch in chunks:
                ch.set_column("ctrl", ids.lift_act, self.lift_ctrl[k])

        self._steps(chunks, len(self.lift_ctrl), bad, lift)
        for _, ch in chunks:
            ch.set_column("ctrl", ids.lift_act, 0.0)
        self._steps(chunks, self.n_hold, bad)
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
        self._steps(chunks, self.n_push, bad)
        for sl, ch in chunks:
            ch.set_state(xfrc_applied=np.zeros((sl.stop - sl.start, nbody, 6)))
        self._steps(chunks, self.n_push_hold, bad)
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
        pairs per world, most in one chunk), peak_rows)."""
        if self.cfg.sim.push_point != "com":
            raise ValueError("the warp backend pushes at the centre of mass; push_point="
                             "'origin' is plain MuJoCo's (backend='mujoco')")
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
        steps += self.grasp_steps
        held = np.nonzero(ok)[0]
        if len(held):
            idx = np.repeat(held, n_push)
            dirs = np.tile(np.asarray(s.stability_directions, np.float64), (len(held), 1))
            st = {k: v[idx] for k, v in state.items()}
            pok, _, pbad = self._push(models, table, idx, st, z_start[idx], dirs)
            outcome[held, 1: 1 + n_push] = pok.reshape(len(held), n_push)
            unstable[held] += pbad.reshape(len(held), n_push).sum(1)
            idx = np.repeat(held, n_rob)
            yaws = np.tile(np.deg2rad(np.asarray(s.robustness_angles_deg, np.float64)), len(held))
            rok, _, rbad, _, _ = self._grasp(models, table, idx, yaws, openers)
            outcome[held, 1 + n_push:] = rok.reshape(len(held), n_rob)
            unstable[held] += rbad.reshape(len(held), n_rob).sum(1)
            steps[held] += n_push * self.push_steps + n_rob * self.grasp_steps
        if self.overflowed:
            log.warning("warp backend: %d worlds overflowed a buffer and were failed (broad-phase "
                        "pairs per world up to %.0f of %d slots)", self.overflowed,
                        self.peak_pairs, CONTACTS_PER_WORLD)
        return dict(outcome=outcome, unstable=unstable, steps=steps,
                    compile_seconds=self.compile_seconds, step_seconds=self.step_seconds,
                    world_steps=self.world_steps, approach_seconds=self.approach_seconds,
                    devices=list(self.devices),
                    overflowed=self.overflowed, peak_pairs=self.peak_pairs,
                    peak_rows=self.peak_rows)


def evaluate_models(models: list[mujoco.MjModel], cfg: Config, **kwargs) -> dict:
    """The 11 trials of compiled candidate models (``build_model(..., pad_collides=True)``, one
    layout) on MuJoCo Warp.  See WarpGraspSimulator.run; kwargs go to its constructor."""
    return WarpGraspSimulator(cfg, **kwargs).run(models)
