"""The jaw opening before a grasp: one rule for every backend.

Each finger opens until it is ``margin`` from the object *along the closing axis*: on a grid of
lines parallel to x over the finger's (y, z) footprint (``line_grid``), every convex piece is cut
by the line (``x_extent``: its half-spaces give the piece's extent along x on each line), the
finger's reach and the object's near side are the unions of their pieces' extents, and the
opening is the largest reach-minus-near-side over all lines plus the margin.  Unlike a Euclidean
distance this is the gap along the closing motion, so parts that pass beside the object (an
imprint finger's rim) do not hold the jaws open.  Lines ``spacing`` apart can miss a thin spike,
so the host rule then backs off by what the exact distance lacks (``BACKOFF_ROUNDS``).

``JawOpener`` is the rule on the host (plain MuJoCo); ``mjx_batch`` runs ``x_extent`` in jnp on
lines ``MJX_LINE_SPACING`` apart, and ``warp_batch`` runs it as a kernel over ``JawOpener``'s lines.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from f2f_jax.config import Config
from f2f_jax.errors import DecompositionError
from f2f_jax.geometry import finger_pose
from f2f_jax.sim.scene import SceneIds, finger_object_distance

LINE_SPACING = 0.001  # m between the lines of the host's (and warp's) grid: 61 x 61 lines
# MJX traces every line into each step's program: 1.5 mm (41 x 41 lines) halves its cost, and its
# agreement with plain MuJoCo is measured with it (benchmarks/sim_agreement.py --backends mjx mujoco)
MJX_LINE_SPACING = 0.0015
BACKOFF_ROUNDS = 8  # exact-distance corrections after the line rule, at most
_PARALLEL = 1e-12  # |n_x| below this: a facet parallel to the lines
_PLANES_KEPT = 512  # object pieces' planes remembered (JawOpener._local_planes)
_planes: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_planes_lock = threading.Lock()


def line_axes(cfg: Config, spacing: float = LINE_SPACING) -> tuple[np.ndarray, np.ndarray]:
    """The grid's y and z coordinates (m, world): the shape cube's footprint at rest height."""
    h = cfg.geometry.cube_size / 2
    z0 = finger_pose("left", 0.0, cfg)[2, 3]  # the fingers' cube centre height, as mounted
    ys = np.arange(-h, h + spacing / 2, spacing)
    zs = np.arange(z0 - h, z0 + h + spacing / 2, spacing)
    return ys, zs


def line_grid(cfg: Config, spacing: float = LINE_SPACING) -> np.ndarray:
    """[L, 2] (y, z) of every line, y-major."""
    ys, zs = line_axes(cfg, spacing)
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    return np.stack([yy.ravel(), zz.ravel()], 1)


def x_extent(planes, rot, pos, y, z, xp=np):
    """A convex piece's extent along x on lines at (y, z): (lower, upper, hit).

    planes: [F, 4] facet planes (n, d) in the piece's frame, n . p + d <= 0 inside; rot [3, 3] and
    pos [3]: the piece's pose; y, z: line coordinates, broadcastable against each other.  Returns
    arrays of their broadcast shape; ``hit`` is False where the line misses the piece.  ``xp`` is
    numpy or jax.numpy: the same rule on the host and inside a jitted step.
    """
    n = planes[:, :3] @ rot.T  # world normals
    d = planes[:, 3] - n @ pos
    extra = (None,) * max(xp.ndim(y), xp.ndim(z))  # the lines' axes, after the facets'
    nx = n[(slice(None), 0, *extra)]
    # n_x x <= c on each line: [F, *lines]
    c = -(d[(slice(None), *extra)] + n[(slice(None), 1, *extra)] * y + n[(slice(None), 2, *extra)] * z)
    bound = c / xp.where(xp.abs(nx) > _PARALLEL, nx, 1.0)
    upper = xp.where(nx > _PARALLEL, bound, xp.inf).min(0)
    lower = xp.where(nx < -_PARALLEL, bound, -xp.inf).max(0)
    hit = xp.all((xp.abs(nx) > _PARALLEL) | (c >= 0), axis=0) & (lower <= upper)
    return lower, upper, hit


def _host_extent(planes, rot, pos, y, z):
    """``x_extent(planes, rot, pos, y, z, np)`` with the facets split by the sign of their world
    n_x first, so that each line meets only the facets that bound it: the same values bit for bit
    (each bound is the same quotient, -a / n_x = a / -n_x exactly, and a min or max over fewer
    entries that left out only infinities is the same), at a third of the array passes."""
    n = planes[:, :3] @ rot.T  # world normals, as x_extent computes them
    d = planes[:, 3] - n @ pos
    nx = n[:, 0]
    up, down = nx > _PARALLEL, nx < -_PARALLEL
    parallel = ~(up | down)
    order = np.concatenate([np.flatnonzero(up), np.flatnonzero(down), np.flatnonzero(parallel)])
    k_up, k_down = int(up.sum()), int(down.sum())
    n, d = n[order], d[order]
    # a = -c of x_extent, [F, Y, Z]: the same sums in the same order
    a = d[:, None, None] + n[:, 1, None, None] * y + n[:, 2, None, None] * z
    shape, k = a.shape[1:], k_up + k_down
    hit = (a[k:] <= 0).all(0)  # a line outside a parallel facet's half-space misses the piece
    bound = np.divide(a[:k], -n[:k, 0, None, None], out=a[:k])  # in place: c / n_x
    upper = bound[:k_up].min(0) if k_up else np.full(shape, np.inf)
    lower = bound[k_up:].max(0) if k_down else np.full(shape, -np.inf)
    hit &= lower <= upper
    return lower, upper, hit


def _geom_local_vertices(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """[n, 3] vertices of a convex geom in its own frame (meshes and boxes)."""
    gtype = model.geom_type[geom]
    if gtype == mujoco.mjtGeom.mjGEOM_MESH:
        mesh = model.geom_dataid[geom]
        adr, num = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        return np.asarray(model.mesh_vert[adr: adr + num], np.float64)
    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        return corners * model.geom_size[geom]
    raise ValueError(f"geom {geom}: only mesh and box geoms can be fingers or objects here")


class JawOpener:
    """Jaw openings that leave each finger ``margin`` from the object along the closing axis (the
    module's rule, on the host).  The finger's pieces are intersected once; only the object's move
    with its pose."""

    def __init__(self, model: mujoco.MjModel, ids: SceneIds, cfg: Config, *,
                 spacing: float = LINE_SPACING):
        self.model, self.ids = model, ids
        ys, zs = line_axes(cfg, spacing)
        self.lines = line_grid(cfg, spacing)  # [L, 2] (y, z) in world
        self._ys, self._zs, self._spacing = ys, zs, spacing
        self._local = {int(gid): self._local_planes(gid) for gid in ids.all_finger_geoms}
        # every candidate of one object has the same object pieces: their planes are remembered
        self._local.update({int(gid): self._local_planes(gid, remember=True)
                            for gid in ids.object_geoms})
        self._finger_reach: list[tuple[np.ndarray, np.ndarray]] | None = None

    def _local_planes(self, geom: int, remember: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """([F, 4] facet planes (n, d) with n . p + d <= 0 inside, [V, 3] hull vertices), in the
        geom's frame; ``remember``: kept for the last ``_PLANES_KEPT`` vertex sets seen so."""
        verts = _geom_local_vertices(self.model, geom)
        key = verts.tobytes() if remember else None
        if key is not None:
            with _planes_lock:
                hit = _planes.get(key)
                if hit is not None:
                    _planes.move_to_end(key)
                    return hit
        try:
            hull = ConvexHull(verts)
        except (QhullError, ValueError):
            raise DecompositionError(f"geom {geom}: its vertices span no volume") from None
        planes = (hull.equations, verts[hull.vertices])
        if key is not None:
            for arr in planes:
                arr.setflags(write=False)
            with _planes_lock:
                _planes[key] = planes
                while len(_planes) > _PLANES_KEPT:
                    _planes.popitem(last=False)
        return planes

    def _window(self, lo: float, hi: float, axis: np.ndarray) -> slice:
        """The lines of one grid axis whose coordinate lies in [lo, hi] (a little wider)."""
        pad = 1e-9 + 1e-6 * self._spacing
        start = int(np.searchsorted(axis, lo - pad, side="left"))
        stop = int(np.searchsorted(axis, hi + pad, side="right"))
        return slice(start, stop)

    def _intervals(self, data: mujoco.MjData, geoms) -> tuple[np.ndarray, np.ndarray]:
        """Union bounds along x of the pieces on every line: (lo [L], hi [L]); +inf / -inf where
        a line misses all of them.  Each piece is intersected only with the lines inside its
        (y, z) bounding box: a line outside it cannot meet the piece."""
        ny, nz = len(self._ys), len(self._zs)
        lo = np.full((ny, nz), np.inf)
        hi = np.full((ny, nz), -np.inf)
        for gid in geoms:
            planes, verts = self._local[int(gid)]
            rot = data.geom_xmat[gid].reshape(3, 3)
            world = verts @ rot.T + data.geom_xpos[gid]
            wy = self._window(world[:, 1].min(), world[:, 1].max(), self._ys)
            wz = self._window(world[:, 2].min(), world[:, 2].max(), self._zs)
            if wy.start >= wy.stop or wz.start >= wz.stop:
                continue
            y = self._ys[wy][:, None]  # [Y, 1]
            z = self._zs[wz][None, :]  # [1, Z]
            lower, upper, hit = _host_extent(planes, rot, data.geom_xpos[gid], y, z)
            lo[wy, wz] = np.where(hit, np.minimum(lo[wy, wz], lower), lo[wy, wz])
            hi[wy, wz] = np.where(hit, np.maximum(hi[wy, wz], upper), hi[wy, wz])
        return lo.ravel(), hi.ravel()

    def __call__(self, data: mujoco.MjData, margin: float) -> np.ndarray:
        """Openings [2] (m) for the object pose in ``data.qpos``; writes them into the jaws'
        qpos and grip controls and leaves ``data`` at those kinematics.  Clipped to the joint
        range; a finger that cannot clear the object even fully open stays fully open."""
        model, ids = self.model, self.ids
        if self._finger_reach is None:
            data.qpos[ids.jaw_qpos] = 0.0  # reach measured from the gripper's centre plane
            mujoco.mj_kinematics(model, data)
            self._finger_reach = [self._intervals(data, ids.finger_geoms[side]) for side in (0, 1)]
        else:
            mujoco.mj_kinematics(model, data)
        obj_lo, obj_hi = self._intervals(data, ids.object_geoms)
        openings = np.empty(2)
        (_, left_hi), (right_lo, _) = self._finger_reach
        # left finger at opening q spans x - q: clear when left_hi - q <= obj_lo - margin
        need = np.concatenate([[-np.inf], (left_hi - obj_lo)[np.isfinite(left_hi - obj_lo)]])
        openings[0] = need.max() + margin
        # right finger at opening q spans x + q: clear when right_lo + q >= obj_hi + margin
        need = np.concatenate([[-np.inf], (obj_hi - right_lo)[np.isfinite(obj_hi - right_lo)]])
        openings[1] = need.max() + margin
        low, high = ids.jaw_range[:, 0], ids.jaw_range[:, 1]
        # a finger that meets nothing closes from its lower limit's side of the joint range
        openings = np.where(np.isfinite(openings), openings, low)
        openings = np.clip(openings, low, high)
        data.qpos[ids.jaw_qpos] = openings
        mujoco.mj_kinematics(model, data)
        # Lines 1 mm apart can miss a thin spike: back off by what the exact distance lacks.
        for side in range(2):
            for _ in range(BACKOFF_ROUNDS):
                if len(ids.finger_geoms[side]) == 0 or len(ids.object_geoms) == 0:
                    break
                lack = margin / 2 - finger_object_distance(model, data, ids, side)
                if lack <= 0 or openings[side] >= high[side]:
                    break
                openings[side] = min(openings[side] + lack + margin / 2, high[side])
                data.qpos[ids.jaw_qpos[side]] = openings[side]
                mujoco.mj_kinematics(model, data)
        data.ctrl[ids.grip_act] = openings
        return openings
