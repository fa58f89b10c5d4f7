"""Reference backend: plain MuJoCo on CPUs, one model per candidate.

Each candidate (object, left finger, right finger) becomes its own compiled model
(``scene.build_model``) and runs the 11 trials in a worker thread (``protocol.simulate_candidate``);
MuJoCo releases the GIL inside ``mj_step``, so threads scale over cores.  Past one machine,
``executor="ray"`` runs the same per-candidate work in Ray tasks (``sim.ray_executor``).
Results depend only on the inputs: each candidate is simulated alone, single-threaded, from the
same initial state, so both executors give the same outcomes bit for bit.
"""

from __future__ import annotations

import importlib
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from f2f_jax.config import BACKENDS, Config, executor_problem, with_sim_preset
from f2f_jax.errors import F2FError, VolumeError
from f2f_jax.geometry.finger_tiling import remembered_finger_hulls
from f2f_jax.geometry.fingers import feasibility_report
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.geometry.pieces import object_pieces_many as make_object_hulls_many
from f2f_jax.geometry.tsdf import check_tsdf
from f2f_jax.sim import ray_executor  # imports Ray itself only when asked to run on it
from f2f_jax.sim.protocol import TrialResult, simulate_candidate
from f2f_jax.sim.scene import build_model

log = logging.getLogger(__name__)

# Above this many candidates a progress bar is shown when progress=None.
_AUTO_PROGRESS = 32


@dataclass
class EvaluationInfo:
    """Diagnostics of one ``evaluate`` call, per candidate where an array.

    steps: [N] int64 physics steps; unstable: [N] int64 trials ended by an exploding state;
    infeasible: [N] bool, a finger failed ``is_feasible`` (not simulated);
    failed: [N] bool, the candidate could not be simulated (hull or model build error);
    errors: {index: message} for failed candidates; initial_contacts: [N] int64 grasp set-ups
    where a finger touched the object at t = 0 (should be 0); seconds: wall time in total;
    results: [N] TrialResult or None for candidates not simulated.
    """

    steps: np.ndarray
    unstable: np.ndarray
    infeasible: np.ndarray
    failed: np.ndarray
    errors: dict
    initial_contacts: np.ndarray
    seconds: float
    results: list

    @property
    def total_steps(self) -> int:
        return int(self.steps.sum())


def _as_volumes(volumes, name: str, r: int) -> list[np.ndarray]:
    """A [N, R, R, R] array or a sequence of [R, R, R] arrays -> list of arrays (not copied)."""
    if isinstance(volumes, np.ndarray):
        if volumes.ndim != 4 or volumes.shape[1:] != (r, r, r):
            raise VolumeError(f"{name}: expected shape [N, {r}, {r}, {r}], got {volumes.shape}")
        return list(volumes)
    out = []
    for i, v in enumerate(volumes):
        arr = np.asarray(v)
        if arr.shape != (r, r, r):
            raise VolumeError(f"{name}[{i}]: expected shape ({r}, {r}, {r}), got {arr.shape}")
        out.append(arr)
    return out


def _object_offsets(object_xy, n: int) -> np.ndarray | None:
    """evaluate's ``object_xy``: None, one [2] offset or [N, 2] offsets (m) -> [N, 2] or None."""
    if object_xy is None:
        return None
    xy = np.asarray(object_xy, np.float64)
    if xy.shape == (2,):
        xy = np.broadcast_to(xy, (n, 2))
    if xy.shape != (n, 2):
        raise ValueError(f"object_xy: expected shape [2] or [{n}, 2] (metres), got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise ValueError("object_xy: contains NaN/inf values")
    return xy


# evaluate's keywords stay flat, the executor's options among them (executor, threads,
# ray_address, task_size): the tables, the dataset, co-training and design() pass
# ``executor="ray"`` through as one string, and an options object would only wrap it.
def evaluate(objects, lefts, rights, *, backend: str = "mujoco", cfg: Config | None = None,
             threads: int | None = None, progress: bool | None = None, object_hulls=None,
             cache_dir=None, object_xy=None, preset: str | None = None,
             executor: str = "threads", ray_address: str | None = None,
             task_size: int | None = None) -> np.ndarray:
    """Simulate the 11 trials of N (object, left finger, right finger) triples: outcomes [N, 11]
    uint8 in ``TRIAL_NAMES`` order.  ``evaluate_with_info`` takes the same arguments and also
    returns the call's EvaluationInfo.

    objects, lefts, rights: [N, 40, 40, 40] float32 TSDF arrays (or length-N sequences of
        [40, 40, 40]), negative inside, in the frames of config.py.
    backend: "mujoco" (this module: threads over candidates, the CPU default), "mjx" (all
        candidates batched in MJX, ``sim.mjx_batch``; any JAX device) or "warp" (every trial a
        MuJoCo Warp world with its own geometry, ``sim.warp_batch``, on every local GPU, else
        warp's slow CPU device; needs the ``warp`` extra).
    executor: where the "mujoco" backend's candidates run: "threads" (this process, ``threads``
        worker threads) or "ray" (Ray tasks on a local or remote cluster, ``sim.ray_executor``:
        needs the ``ray`` extra; same outcomes bit for bit).
    threads: worker threads of executor "threads" (default os.cpu_count()).
    ray_address: executor "ray": the cluster to join when no Ray session exists yet ("auto",
        "host:port"; default: a cluster started on this machine, else a new local one).
    task_size: executor "ray": candidates per Ray task (default: ~4 tasks per cluster CPU,
        at most 8 candidates each).
    progress: tqdm bars; None shows the trials bar when N > 32 and, with coacd objects, the
        object-hulls bar when more than one distinct object needs hulls (~15 s each, uncached).
    object_hulls: precomputed object pieces (Hulls), one for all or a length-N sequence; default
        makes them by ``cfg.geometry.object_method`` (``geometry.pieces.object_pieces``: coacd
        cached on disk in ``cache_dir``, or tiles in ~0.15 s), once per distinct object.
    preset: a simulation preset of ``config.SIM_PRESETS`` applied to cfg ("fast", the default
        of every config, or "reference"); None keeps cfg as it is.  The "mjx" and "warp"
        backends run every phase to its full length whatever the preset (their batches step all
        worlds in lock-step).
    object_xy: None (the object at the grasp location), one [2] or per-candidate [N, 2] float
        offsets (x, y) in metres that shift the object on the floor before every trial (x is
        the closing direction); the robustness grasps turn it about its shifted centre.  Only
        the "mujoco" backend; "mjx" and "warp" raise NotImplementedError.

    A candidate with an infeasible finger scores zeros without simulation; one whose hulls or
    model cannot be built scores zeros (``EvaluationInfo.failed``); the rest of the batch is
    still evaluated.  Raises VolumeError (naming the index) for volumes of the wrong shape, NaN
    values or an empty object, ValueError for inputs of different lengths.
    """
    return evaluate_with_info(objects, lefts, rights, backend=backend, cfg=cfg, threads=threads,
                              progress=progress, object_hulls=object_hulls, cache_dir=cache_dir,
                              object_xy=object_xy, preset=preset, executor=executor,
                              ray_address=ray_address, task_size=task_size)[0]


def evaluate_with_info(objects, lefts, rights, *, backend: str = "mujoco",
                       cfg: Config | None = None, threads: int | None = None,
                       progress: bool | None = None, object_hulls=None, cache_dir=None,
                       object_xy=None, preset: str | None = None, executor: str = "threads",
                       ray_address: str | None = None,
                       task_size: int | None = None) -> tuple[np.ndarray, EvaluationInfo]:
    """``evaluate``'s outcomes [N, 11] uint8 and the call's EvaluationInfo (steps, unstable
    trials, infeasible and failed candidates, ...); the arguments are ``evaluate``'s."""
    _check_choices(backend, executor)
    cfg = cfg or Config()
    if preset is not None:
        cfg = with_sim_preset(cfg, preset)
    objs, lefts, rights, feasible = _checked_triples(objects, lefts, rights, cfg.geometry)
    n = len(objs)
    offsets = _object_offsets(object_xy, n)
    if offsets is not None and backend != "mujoco":
        raise NotImplementedError("evaluate(object_xy=...) is implemented for backend='mujoco' "
                                  f"only; the {backend!r} batch places every object at the grasp "
                                  "location")
    hull_list = None  # None: made below by cfg.geometry.object_method
    if object_hulls is not None:
        hull_list = [object_hulls] * n if isinstance(object_hulls, Hulls) else list(object_hulls)
        if len(hull_list) != n:
            raise ValueError(f"object_hulls: expected one Hulls per candidate ({n}), got "
                             f"{len(hull_list)}")
    if backend != "mujoco":
        return _evaluate_batched(backend, objs, lefts, rights, feasible, cfg,
                                 object_hulls=object_hulls, cache_dir=cache_dir,
                                 progress=progress)
    start = time.perf_counter()
    todo = np.nonzero(feasible)[0]
    results: list[TrialResult | None] = [None] * n
    show = progress if progress is not None else len(todo) > _AUTO_PROGRESS
    if executor == "ray":
        done = ray_executor.run(objs, lefts, rights, todo, cfg, hull_list=hull_list,
                                offsets=offsets, cache_dir=cache_dir, progress=show,
                                address=ray_address, task_size=task_size)
        for i in todo:
            results[i] = done[int(i)]
    else:
        _run_threads(objs, lefts, rights, todo, cfg, results, threads=threads, show=show,
                     hull_list=hull_list, offsets=offsets,
                     cache_dir=cache_dir, progress=progress)
    return _gathered(results, todo, feasible, cfg.sim.n_trials, time.perf_counter() - start)


def _check_choices(backend: str, executor: str) -> None:
    """Refuse unknown or unsupported backend/executor choices, and a missing extra, before any work."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    problem = executor_problem(executor, backend)  # config.EXECUTORS: the names and their rules
    if problem is not None:
        raise ValueError(problem)
    if executor == "ray":
        ray_executor.require_ray()  # before any work: a missing extra is the first thing said
    if backend == "warp":  # before any work: importing it raises MissingExtraError without warp
        importlib.import_module("f2f_jax.sim.warp_batch")


def _checked_triples(objects, lefts, rights, g) -> tuple[list, list, list, np.ndarray]:
    """The triples as lists of [R, R, R] volumes, and which are feasible [N] bool.  Raises
    VolumeError (naming the index) for a bad volume, ValueError for lists of different lengths;
    an empty or disconnected finger is merely infeasible."""
    r = g.resolution
    objs = _as_volumes(objects, "objects", r)
    lefts = _as_volumes(lefts, "lefts", r)
    rights = _as_volumes(rights, "rights", r)
    n = len(objs)
    if not (len(lefts) == len(rights) == n):
        raise ValueError(f"objects, lefts and rights must have one entry per candidate; got "
                         f"{n}, {len(lefts)} and {len(rights)}")
    objs = [check_tsdf(o, f"objects[{i}]", g) for i, o in enumerate(objs)]
    feasible = np.ones(n, bool)
    for name, fingers in (("lefts", lefts), ("rights", rights)):
        for i, f in enumerate(fingers):
            try:
                feasible[i] &= feasibility_report(f, g)["feasible"]
            except VolumeError as exc:
                raise VolumeError(f"{name}[{i}]: {exc}") from None
    return objs, lefts, rights, feasible


def _gathered(results: list, todo: np.ndarray, feasible: np.ndarray, n_trials: int,
              seconds: float) -> tuple[np.ndarray, "EvaluationInfo"]:
    """Outcomes [N, 11] uint8 (zeros where nothing was simulated) and the EvaluationInfo."""
    n = len(results)
    errors: dict[int, str] = {}
    for i in todo:
        if results[i].error is not None:
            errors[int(i)] = results[i].error
            log.warning("candidate %d not simulated: %s", i, results[i].error)
    outcomes = np.zeros((n, n_trials), np.uint8)
    for i, res in enumerate(results):
        if res is not None:
            outcomes[i] = res.outcome

    def field(name):
        return np.array([getattr(res, name) if res is not None else 0 for res in results],
                        np.int64)

    info = EvaluationInfo(
        steps=field("steps"), unstable=field("unstable"), infeasible=~feasible,
        failed=np.array([i in errors for i in range(n)], bool), errors=errors,
        initial_contacts=field("initial_contacts"), seconds=seconds, results=results)
    return outcomes, info


def _run_threads(objs, lefts, rights, todo, cfg, results, *, threads, show, hull_list, offsets,
                 cache_dir, progress) -> None:
    """evaluate(executor="threads"): results[i] for i in todo, from a pool of worker threads."""
    threads = max(1, int(threads or os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        if hull_list is None:
            # each distinct object once, uncached ones by coacd in one process per core
            hull_list = [None] * len(objs)
            made = make_object_hulls_many([objs[i] for i in todo], cfg, cache_dir=cache_dir,
                                          workers=threads, progress=progress)
            for i, hulls in zip(todo, made):
                hull_list[i] = hulls

        def work(i):
            return simulate_candidate(hull_list[i], lefts[i], rights[i], cfg,
                                      None if offsets is None else offsets[i])

        done = pool.map(work, todo)
        if show:
            from tqdm.auto import tqdm

            done = tqdm(done, total=len(todo), desc="grasp trials", unit="cand")
        for i, res in zip(todo, done):
            results[i] = res


def batched_model_options(backend: str) -> dict:
    """``scene.build_model`` keywords of a batched backend's candidate models ("mjx" or
    "warp"): one layout for all (placeholders that collide), and MJX's contact caps."""
    options = dict(pad_collides=True)
    if backend == "mjx":
        from f2f_jax.sim import mjx_collision  # JAX: only for the MJX backend

        options.update(max_geom_pairs=mjx_collision.MAX_GEOM_PAIRS,
                       max_contact_points=mjx_collision.MAX_CONTACT_POINTS)
    return options


def _evaluate_batched(backend, objs, lefts, rights, feasible, cfg, *, object_hulls, cache_dir,
                      progress) -> tuple[np.ndarray, EvaluationInfo]:
    """evaluate(..., backend="mjx" | "warp"): models built here on the CPU, one layout, trials
    batched in MJX (``sim.mjx_batch``) or MuJoCo Warp (``sim.warp_batch``)."""
    batched = importlib.import_module(f"f2f_jax.sim.{backend}_batch")
    options = batched_model_options(backend)

    start = time.perf_counter()
    n, n_trials = len(objs), cfg.sim.n_trials
    if object_hulls is not None:
        hull_list = [object_hulls] * n if isinstance(object_hulls, Hulls) else list(object_hulls)
    else:
        hull_list = [None] * n
        todo = np.nonzero(feasible)[0]
        made = make_object_hulls_many([objs[i] for i in todo], cfg, cache_dir=cache_dir,
                                      progress=progress)
        for i, hulls in zip(todo, made):
            hull_list[i] = hulls
    models, index, errors = [], [], {}
    for i in np.nonzero(feasible)[0]:
        hulls = hull_list[i]
        try:
            if isinstance(hulls, str):
                raise F2FError(f"object hulls: {hulls}")
            models.append(build_model(hulls, remembered_finger_hulls(lefts[i], cfg),
                                      remembered_finger_hulls(rights[i], cfg), cfg, **options))
            index.append(i)
        except (F2FError, ValueError) as exc:
            errors[int(i)] = f"{type(exc).__name__}: {exc}"
            log.warning("candidate %d not simulated: %s", i, errors[int(i)])
    outcomes = np.zeros((n, n_trials), np.uint8)
    steps = np.zeros(n, np.int64)
    unstable = np.zeros(n, np.int64)
    if models:
        res = batched.evaluate_models(models, cfg)
        outcomes[index] = res["outcome"]
        steps[index] = res["steps"]
        unstable[index] = res["unstable"]
    info = EvaluationInfo(
        steps=steps, unstable=unstable, infeasible=~feasible,
        failed=np.array([i in errors for i in range(n)], bool), errors=errors,
        initial_contacts=np.zeros(n, np.int64), seconds=time.perf_counter() - start, results=[None] * n)
    return outcomes, info
