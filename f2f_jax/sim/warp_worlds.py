"""MuJoCo Warp worlds with per-world geometry: the mesh table, each world's fields, the kernels
of the approach's opening rule, and a chunk of worlds on one device (``warp_batch`` runs the
protocol on them).

Needs the ``warp`` extra; importing this module without it raises ``errors.MissingExtraError``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import mujoco
import numpy as np

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
# Overflows that lose pairs, contacts or constraint rows: the world's physics is wrong.  The
# solver's iteration limits (ITERATIONS, LS_ITERATIONS) are not among them: plain MuJoCo stops
# at the same limits without a word.
_OT = mjw.OverflowType
LOST_OVERFLOWS = int(_OT.NEFC | _OT.NJMAX_NNZ | _OT.BROADPHASE | _OT.NARROWPHASE | _OT.CCD
            | _OT.EPA_HORIZON | _OT.NVMAX)


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


# Gap (m) below which two pieces on opposite jaws count as able to meet across the jaws' shared
# (y, z): rounding of float32 poses is ~1e-8 m, so 0.1 mm keeps every pair that could touch.
PAIR_SLACK = 1.0e-4


def reachable_pairs(template: mujoco.MjModel, table: MeshTable, fields: dict, jaws, pairs,
                    slack: float = PAIR_SLACK) -> np.ndarray:
    """[P] bool: which geom pairs [P, 2] of the model's pair list can make a contact in some world
    of ``fields`` (rows of ``candidate_fields``).  Dropped are pairs with a mesh geom that is a
    placeholder (geom_dataid -1) in every world, which the broad phase already skips world by
    world, and pairs of one piece on each jaw (``jaws``: two arrays of geom ids) whose extents
    across the closing axis are apart by more than ``slack`` plus their margins in every world.
    The jaws' bodies share a parent and slide along its x axis without turning, so a piece's
    (y, z) extent in the parent's frame is the same at every opening: two convex pieces whose
    (y, z) extents never overlap never touch, however far the jaws travel.  Nothing else is
    dropped: the object is free, and the floor meets only the object."""
    ids = np.asarray(fields["geom_dataid"])  # [W, G]
    present = (ids >= 0).any(0) | (np.asarray(template.geom_type) != mujoco.mjtGeom.mjGEOM_MESH)
    keep = present[pairs[:, 0]] & present[pairs[:, 1]]
    bodies = [int(template.geom_bodyid[g[0]]) for g in jaws if len(g)]
    if len(bodies) != 2 or not _slides_along_x(template, bodies):
        return keep
    lo, hi = _jaw_extents(table, fields, np.concatenate(jaws), bodies, template)
    side = np.full(template.ngeom, -1)
    side[jaws[0]], side[jaws[1]] = 0, 1
    a, b = pairs[:, 0], pairs[:, 1]
    across = (side[a] >= 0) & (side[b] >= 0) & (side[a] != side[b])
    gap = np.maximum(lo[:, a] - hi[:, b], lo[:, b] - hi[:, a]).max(-1)  # [C, P], the larger axis
    margin = (np.asarray(template.geom_margin) + np.asarray(template.geom_gap))[pairs].sum(1)
    meets = (gap <= slack + margin).any(0)
    return keep & (~across | meets)


def _slides_along_x(m: mujoco.MjModel, bodies) -> bool:
    """Both bodies children of one body, unturned in it, each moved by one slide along x."""
    if m.body_parentid[bodies[0]] != m.body_parentid[bodies[1]]:
        return False
    for b in bodies:
        j = int(m.body_jntadr[b])
        if (m.body_jntnum[b] != 1 or m.jnt_type[j] != mujoco.mjtJoint.mjJNT_SLIDE
                or not np.allclose(np.abs(m.jnt_axis[j]), [1, 0, 0])
                or not np.allclose(m.body_quat[b], [1, 0, 0, 0])):
            return False
    return True


def _jaw_extents(table: MeshTable, fields: dict, geoms, bodies, m) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [C, G, 2]: the (y, z) extent of geoms ``geoms`` (mesh pieces on the jaws) in the
    jaws' parent frame, per distinct candidate among the worlds of ``fields`` (worlds of one
    candidate share their meshes); other geoms get (+inf, -inf), which meet nothing."""
    _, rows = np.unique(fields["geom_dataid"], axis=0, return_index=True)
    ngeom = fields["geom_dataid"].shape[1]
    lo, hi = np.full((len(rows), ngeom, 2), np.inf), np.full((len(rows), ngeom, 2), -np.inf)
    f = table.fields
    rot = np.empty(9)
    for c, w in enumerate(rows):
        for g in geoms:
            mesh, body = int(fields["geom_dataid"][w, g]), int(m.geom_bodyid[g])
            if mesh < 0 or body not in bodies:
                continue
            start = f["mesh_vertadr"][mesh]
            v = f["mesh_vert"][start: start + f["mesh_vertnum"][mesh]].astype(np.float64)
            mujoco.mju_quat2Mat(rot, np.asarray(fields["geom_quat"][w, g], np.float64))
            p = v @ rot.reshape(3, 3).T + fields["geom_pos"][w, g] + fields["body_pos"][w, body]
            lo[c, g], hi[c, g] = p[:, 1:].min(0), p[:, 1:].max(0)
    return lo, hi


def finger_object_pairs(geom: np.ndarray, fingers, obj) -> np.ndarray:
    """[C] bool: contacts (geom pairs [C, 2]) between one of ``fingers`` and one of ``obj``."""
    return ((np.isin(geom[:, 0], fingers) & np.isin(geom[:, 1], obj))
            | (np.isin(geom[:, 1], fingers) & np.isin(geom[:, 0], obj)))


class WorldChunk:
    """One device's share of a round: its model, data and host-side view of the worlds."""

    def __init__(self, template: mujoco.MjModel, table: MeshTable, fields: dict, device: str,
                 jaws=None):
        """jaws: the geom ids of each jaw's pieces, to leave out of the pair list the pairs that
        cannot touch in any of these worlds (``reachable_pairs``); None keeps MuJoCo Warp's list."""
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
            m.opt.warn_overflow = LOST_OVERFLOWS  # printed from the device; iteration limits are not
            for k, v in table.sizes.items():
                setattr(m, k, v)
            self.m = m
            self.listed_pairs = self.all_pairs = len(m.nxn_geom_pair_filtered)
            if jaws is not None:
                self._drop_pairs(template, table, fields, jaws)
            self.d = mjw.put_data(template, mujoco.MjData(template), nworld=nworld,
                                  nconmax=CONTACTS_PER_WORLD, njmax=ROWS_PER_WORLD)
            self.planes = wp.array(table.planes.astype(np.float32), dtype=wp.vec4)
            self.nplane = wp.array(table.fields["mesh_polynum"].astype(np.int32), dtype=int)
            self.finger_xpos = self.finger_xmat = None
            self._reach = None  # (reach, the fingers' margins for finger_distance's pass)

    def _drop_pairs(self, template, table, fields, jaws):
        """Leave the pairs that cannot touch (``reachable_pairs``) out of the broad phase's list
        (and mark them excluded in the full table, which the sweep-and-prune broad phase reads)."""
        m = self.m
        pairs = m.nxn_geom_pair_filtered.numpy()
        keep = reachable_pairs(template, table, fields, jaws, pairs)
        if keep.all():
            return
        pairid = m.nxn_pairid_filtered.numpy()
        m.nxn_geom_pair_filtered = wp.array(pairs[keep], dtype=wp.vec2i)
        m.nxn_pairid_filtered = wp.array(pairid[keep], dtype=wp.vec2i)
        full = m.nxn_pairid.numpy()
        i, j, n = pairs[~keep, 0], pairs[~keep, 1], template.ngeom
        full[(i * (2 * n - i - 3)) // 2 + j - 1, 0] = -2  # i < j: the upper triangle's index
        m.nxn_pairid = wp.array(full, dtype=wp.vec2i)
        self.listed_pairs = int(keep.sum())

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
            pair = finger_object_pairs(geom, ids.finger_geoms[side], ids.object_geoms)
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
