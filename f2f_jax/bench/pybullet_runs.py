"""Runs of the PyBullet peer (``pybullet_peer``): a run that records the poses our viewer
draws, one triple simulated or rendered, many triples timed, and a convex stand-in for object
pieces; ``run_peer``: many triples in worker processes, one client each.  ``render_original``
keeps a triple's poses for ``f2f_jax.sim.view.draw_strips``: the same panels as our own viewer,
so one triple can be seen as both simulators ran it."""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np
from scipy.spatial import ConvexHull

from f2f_jax.bench.pybullet_peer import N_TRIALS, PROTOCOL, OriginalProtocol, OriginalSession
from f2f_jax.config import Config, default
from f2f_jax.geometry import finger_pose, tsdf_to_mesh
from f2f_jax.geometry.hulls import Hulls, pad_hulls


class RecordingSession(OriginalSession):
    """An OriginalSession that keeps the pieces' poses at the panels ``f2f_jax.sim.view`` draws:
    after settling, after closing, and at the end of every trial (after its success check)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frames: list[tuple[str, object]] = []
        self._bodies = None  # (object, gripper) of the triple being simulated
        self._pieces: list[tuple[int, int, np.ndarray]] = []  # (body, link, vertices in metres)

    def add_object(self, hulls):
        body = super().add_object(hulls)
        self._pieces = [(body, -1, piece.astype(np.float64)) for piece in hulls.pieces()]
        return body

    def add_gripper(self, left, right):
        g = super().add_gripper(left, right)
        for side, hulls, link in (("left", left, 2), ("right", right, 5)):
            rot = finger_pose(side, 0.0, self.cfg)[:3, :3]
            self._pieces += [(g.body, link, piece.astype(np.float64) @ rot.T)
                             for piece in hulls.pieces()]
        return g

    def snapshot(self, label: str):
        from f2f_jax.sim.view import Frame

        s = self.proto.world_scale
        pos, mat = [], []
        for body, link, _ in self._pieces:
            if link < 0:  # the base reports its centre of mass: back to its link frame
                com, quat = self.api.getBasePositionAndOrientation(body)
                rot = np.reshape(self.api.getMatrixFromQuaternion(quat), (3, 3))
                origin = np.asarray(com) - rot @ self.object_com
            else:
                state = self.api.getLinkState(body, link, computeForwardKinematics=1)
                origin = np.asarray(state[4])
                rot = np.reshape(self.api.getMatrixFromQuaternion(state[5]), (3, 3))
            pos.append(origin / s)
            mat.append(rot.reshape(9))
        self.frames.append((label, Frame(label, np.array(pos), np.array(mat))))

    def _settle(self, obj):
        settled = super()._settle(obj)
        if not self.frames:
            self.snapshot("settled")
        return settled

    def _jaws(self, g, targets):
        super()._jaws(g, targets)
        if len(self.frames) == 1 and any(t > 0 for t in targets):
            self.snapshot("closed")

    def _grasp(self, g):
        moved = super()._grasp(g)
        if not moved:  # a move gave up: the trial ends here, without a success check
            self.snapshot("end")
        return moved

    def _held(self, g, obj):
        held = super()._held(g, obj)
        self.snapshot("end")
        return held


def render_original(object_hulls: Hulls, left_hulls: Hulls, right_hulls: Hulls, *,
                    cfg: Config | None = None, label: str = "PyBullet original"):
    """One triple through the original protocol, kept for drawing: an ``f2f_jax.sim.view.Strip``
    (draw it with ``view.draw_strips``, beside our own ``view.trial_strip``)."""
    from scipy.spatial import QhullError

    from f2f_jax.config import TRIAL_NAMES
    from f2f_jax.sim.view import FINGER_COLOUR, OBJECT_COLOUR, Strip

    with RecordingSession(cfg) as world:
        outcome = world.simulate(object_hulls, left_hulls, right_hulls)
        steps = world.steps
        faces, colours = {}, {}
        for k, (_, link, vertices) in enumerate(world._pieces):
            try:
                faces[k] = vertices[ConvexHull(vertices).simplices]
            except QhullError:  # a flat placeholder is not drawn
                continue
            colours[k] = OBJECT_COLOUR if link < 0 else FINGER_COLOUR
        frames = world.frames
    panels = [(f, name) for name, f in frames if name != "end"]
    trials = [f for name, f in frames if name == "end"]
    ran = [i for i in range(N_TRIALS) if i == 0 or outcome[0]]  # a dropped grasp ends the triple
    for i, frame in zip(ran, trials):
        verdict = ("held" if outcome[0] else "dropped") if i == 0 else (
            "held" if outcome[i] else "failed")
        panels.append((frame, f"{TRIAL_NAMES[i]}: {verdict}"))
    scores = "".join(map(str, outcome))
    return Strip(f"{label}: {scores[0]} {scores[1:5]} {scores[5:]} ({steps} steps)", panels,
                 faces, colours, outcome)


def simulate_original(object_hulls: Hulls, left_hulls: Hulls, right_hulls: Hulls, *,
                      gui: bool = False, cfg: Config | None = None) -> np.ndarray:
    """One triple through the original Fit2Form protocol in its own PyBullet client.

    object_hulls, left_hulls, right_hulls: convex pieces in metres, each in its volume's local
    frame (``f2f_jax.geometry.hulls``, frames in config.py).  Returns [11] uint8 outcomes
    (config.TRIAL_NAMES order).  ``gui`` opens a PyBullet window and runs in real time.
    """
    with OriginalSession(cfg, gui=gui) as world:
        return world.simulate(object_hulls, left_hulls, right_hulls)


def evaluate_original(objects_hulls, lefts_hulls, rights_hulls, *, cfg: Config | None = None,
                      protocol: OriginalProtocol = PROTOCOL) -> tuple[np.ndarray, dict]:
    """Many triples through the original protocol, one after another in one client and process.

    objects_hulls, lefts_hulls, rights_hulls: sequences of N ``Hulls``.  Returns outcomes [N, 11]
    uint8 and stats: ``evaluations``, ``steps`` (total ``stepSimulation`` calls),
    ``steps_per_evaluation`` [N] int64, ``seconds`` (wall time of the whole loop, building
    bodies included), ``seconds_per_evaluation`` [N] float64, ``build_seconds`` (the part spent
    building bodies), ``evaluations_per_second``, ``steps_per_second``, ``unstable`` (trials ended
    by a non-finite state).
    """
    triples = list(zip(objects_hulls, lefts_hulls, rights_hulls, strict=True))
    outcomes = np.zeros((len(triples), N_TRIALS), np.uint8)
    per_eval = np.zeros(len(triples), np.int64)
    per_eval_s = np.zeros(len(triples), np.float64)
    with OriginalSession(cfg, protocol) as world:
        start = time.perf_counter()
        for i, (obj, left, right) in enumerate(triples):
            before, t0 = world.steps, time.perf_counter()
            outcomes[i] = world.simulate(obj, left, right)
            per_eval[i] = world.steps - before
            per_eval_s[i] = time.perf_counter() - t0
        seconds = time.perf_counter() - start
        unstable, build = world.unstable, world.build_seconds
    n, steps = len(triples), int(per_eval.sum())
    stats = dict(evaluations=n, steps=steps, steps_per_evaluation=per_eval, seconds=seconds,
                 seconds_per_evaluation=per_eval_s, build_seconds=build,
                 evaluations_per_second=n / seconds if seconds > 0 else float("nan"),
                 steps_per_second=steps / seconds if seconds > 0 else float("nan"),
                 unstable=unstable)
    return outcomes, stats


def convex_object_hulls(obj_tsdf, cfg: Config | None = None) -> Hulls:
    """One convex piece around the object's marching-cubes surface, in the object layout.

    Exact (up to the layout's vertex budget) for convex objects; a stand-in for the coacd pieces
    of ``coacd_pieces.object_hulls`` where those are too slow to make or not wanted.
    """
    g = (cfg or default()).geometry
    mesh = tsdf_to_mesh(obj_tsdf, g)
    return pad_hulls([np.asarray(mesh.vertices)], g.object_hulls, g.hull_vertices)


# A change to the peer whose key has this prefix changes the SimConfig both protocols read (the
# object's friction, its mass); any other key is an ``OriginalProtocol`` field.  Some names exist
# in both (push_point, grip_force, timestep), so the prefix, not a lookup, decides.
SIM_PREFIX = "sim."


def peer_chunk(args):
    """Worker process: one PyBullet client over a chunk of (objects, lefts, rights, cfg, changes)."""
    objects, lefts, rights, cfg, changes = args
    protocol = dataclasses.replace(PROTOCOL, **{k: v for k, v in changes.items()
                                                if not k.startswith(SIM_PREFIX)})
    sim_changes = {k[len(SIM_PREFIX):]: v for k, v in changes.items() if k.startswith(SIM_PREFIX)}
    if sim_changes:
        cfg = cfg.replace(sim=dataclasses.replace(cfg.sim, **sim_changes))
    out, stats = evaluate_original(objects, lefts, rights, cfg=cfg, protocol=protocol)
    return out, int(stats["steps"])


def run_peer(objects, lefts, rights, cfg, workers: int, changes: dict | None = None):
    """The PyBullet original on every triple (sequences of ``Hulls``), in ``workers`` spawned
    processes, one client each: ([N, 11] uint8 outcomes, total steps).

    changes: ``OriginalProtocol`` fields to change (e.g. ``substeps=4``), and ``SimConfig`` fields
        (the settings both protocols share: masses, friction) as "sim.FIELD".
    """
    n = len(objects)
    bounds = np.linspace(0, n, max(1, min(workers, n)) + 1).astype(int)
    chunks = [(objects[a:b], lefts[a:b], rights[a:b], cfg, dict(changes or {}))
              for a, b in zip(bounds[:-1], bounds[1:])]
    with ProcessPoolExecutor(len(chunks), mp_context=get_context("spawn")) as pool:
        parts = list(pool.map(peer_chunk, chunks))
    return np.concatenate([p[0] for p in parts]), sum(p[1] for p in parts)


JUDGE_SUBSTEPS = 4  # the peer as a second judge: Bullet's 1/240 s step split in 4 (1/960 s)


def judge_designs(object_pieces, lefts, rights, cfg: Config, workers: int) -> np.ndarray:
    """The PyBullet peer as an independent judge of N designs: each object's pieces (``Hulls``)
    with its left and right finger volumes [N, R, R, R], the fingers meshed as the ``reference``
    preset meshes them, Bullet's step split in ``JUDGE_SUBSTEPS``, the original's protocol
    otherwise.  Returns [N, 11] uint8 outcomes."""
    from f2f_jax.config import with_sim_preset
    from f2f_jax.geometry.finger_tiling import finger_hulls

    ref = with_sim_preset(cfg, "reference")
    out, _ = run_peer(object_pieces, [finger_hulls(f, ref) for f in lefts],
                      [finger_hulls(f, ref) for f in rights], ref, workers, dict(substeps=JUDGE_SUBSTEPS))
    return np.asarray(out, np.uint8)

