"""``sim.evaluate(..., executor="ray")``: the candidates' trials as Ray tasks, on one machine's
cores or a cluster's.

One call goes like this, all of it driven from the calling process (the driver):

* **Objects.**  Each distinct object's pieces are made once.  Cached coacd pieces are read here;
  the others are made by one Ray task per object (coacd takes 7-32 s an object, so a new object
  set is where a cluster pays first), and the driver caches each as it comes back, so a killed
  run keeps every object it finished.  Either way the pieces sit once in Ray's object store and
  every task that needs them reads them from there.
* **Candidates.**  Consecutive candidates are grouped into tasks of ``task_size`` (default: about
  four tasks per cluster CPU, 1 to 8 candidates each: an evaluation is 0.2-1 s of one core and a
  Ray task costs ~1 ms, so the size is set by load balance, not overhead).  A task simulates its
  candidates one after another on one CPU, exactly as a worker thread of the threaded run does,
  and at most four tasks per CPU are in flight, so the fingers held in the object store stay
  bounded on any N.
* **Results** are put back in input order.  A candidate's outcome depends only on its inputs
  (``mujoco_cpu``), so they are bit-identical to the threaded run's.
* **Faults.**  Ray reruns a task whose worker process died (``TASK_RETRIES`` times); a task that
  still fails is split into one task per candidate, and only the candidates that fail alone are
  reported (``EvaluationInfo.failed`` / ``errors``, zeros in the outcomes), the way the threaded
  run reports a candidate whose hulls or model cannot be built.  The rest of the batch goes on.

``ray.init`` is called only when no Ray session exists: with ``address`` (``"auto"``, or
``host:port`` of a cluster's head), else Ray's own default, which joins a cluster started on this
machine by ``ray start`` and otherwise starts a local one over this machine's cores.
"""

from __future__ import annotations

import hashlib
import logging
import math
import warnings
from collections.abc import Sequence

import numpy as np
from tqdm.auto import tqdm

from f2f_jax.config import Config
from f2f_jax.errors import F2FError, MissingExtraError
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.geometry.pieces import cached_pieces, keep_pieces, object_pieces
from f2f_jax.sim.protocol import TrialResult, simulate_candidate

log = logging.getLogger(__name__)

RAY_INSTALL = 'pip install -e ".[ray]"'
# Ray reruns a task this often when its worker process dies (Ray's own default is 3).
TASK_RETRIES = 3
MAX_TASK_SIZE = 8
TASKS_PER_CPU = 4  # tasks aimed at per cluster CPU (balance), and the in-flight bound


def require_ray():
    """The ray module, or MissingExtraError naming the install command."""
    try:
        import ray
    except ImportError as exc:
        raise MissingExtraError(
            f"executor='ray' needs Ray, an optional extra of f2f_jax: {RAY_INSTALL} "
            f"(from a checkout; or pip install 'f2f_jax[ray]')") from exc
    return ray


def connect(address: str | None = None):
    """Join or start a Ray session unless one exists; returns the ray module.

    address: None (Ray's default: $RAY_ADDRESS, else a cluster started on this machine by
    ``ray start``, else a new local one), "auto", or a head node's "host:port".  Every node must
    have f2f_jax and its dependencies installed, the same version as the driver's.
    """
    ray = require_ray()
    if ray.is_initialized():
        return ray
    try:
        with warnings.catch_warnings():
            # Ray starts its processes with subprocess (fork + exec at once), which JAX's
            # "os.fork() was called" warning cannot tell from a bare fork: nothing is shared.
            warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=True)
    except ConnectionError as exc:
        raise F2FError(
            f"no Ray cluster answers at {address!r} ({exc}). Start one with `ray start --head` on "
            "the head node, or leave the address out to run on this machine. A cluster started "
            "with token authentication (the default of `ray start` since Ray 2.59) also needs "
            "RAY_AUTH_MODE=token here and the head's token (its ~/.ray/auth_token, or "
            "RAY_AUTH_TOKEN)") from exc
    return ray


def cluster_cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


def default_task_size(n: int, cpus: int) -> int:
    """Candidates per task: about TASKS_PER_CPU tasks per CPU, 1 to MAX_TASK_SIZE candidates."""
    return int(min(MAX_TASK_SIZE, max(1, math.ceil(n / (TASKS_PER_CPU * cpus)))))


# -- what runs on the workers --------------------------------------------------------------------
def pieces_task(obj: np.ndarray, geometry) -> Hulls | str:
    """One object's collision pieces (no cache on the worker: the driver keeps them), or the
    error message of an object that cannot be decomposed."""
    try:
        return object_pieces(obj, geometry, cache_dir=False)
    except (F2FError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"


def trials_task(cfg: Config, candidates: list, *pieces) -> list[TrialResult]:
    """The 11 trials of each candidate (slot, left, right, object_xy or None) in turn; slot
    indexes ``pieces``, the task's objects (Hulls, or a hull error message).  A candidate that
    raises is a failed candidate, not a failed task."""
    out = []
    for slot, left, right, xy in candidates:
        try:
            out.append(simulate_candidate(pieces[slot], left, right, cfg, xy))
        except Exception as exc:  # noqa: BLE001 - reported per candidate, the batch goes on
            out.append(TrialResult.zeros(cfg.sim.n_trials, error=f"{type(exc).__name__}: {exc}"))
    return out


_REMOTE: dict = {}


def _remote(ray, fn):
    if fn.__name__ not in _REMOTE:
        _REMOTE[fn.__name__] = ray.remote(num_cpus=1)(fn)
    return _REMOTE[fn.__name__].options(max_retries=TASK_RETRIES)


# -- the driver ----------------------------------------------------------------------------------
def run(objs: Sequence[np.ndarray], lefts, rights, todo: np.ndarray, cfg: Config, *,
        hull_list=None, offsets=None, cache_dir=None, progress: bool = False,
        address: str | None = None, task_size: int | None = None) -> dict[int, TrialResult]:
    """TrialResults of the candidates ``todo`` (indices into objs/lefts/rights) simulated in Ray
    tasks.  hull_list: per candidate Hulls (or a hull error message) given by the caller, else
    None: pieces are made here by ``cfg.geometry.object_method``.  Returns {index: result}."""
    if task_size is not None and int(task_size) < 1:
        raise ValueError(f"task_size must be >= 1, got {task_size}")
    ray = connect(address)
    todo = [int(i) for i in todo]
    results: dict[int, TrialResult] = {}
    if not todo:
        return results
    g = cfg.geometry
    cpus = cluster_cpus(ray)
    size = default_task_size(len(todo), cpus) if task_size is None else int(task_size)
    pieces_remote, trials_remote = _remote(ray, pieces_task), _remote(ray, trials_task)
    cfg_ref = ray.put(cfg)

    refs, key_of, making = _object_refs(ray, pieces_remote, objs, todo, hull_list, g, cache_dir)

    def submit(chunk: list[int]):
        keys = list(dict.fromkeys(key_of[i] for i in chunk))
        slot = {k: j for j, k in enumerate(keys)}
        cands = [(slot[key_of[i]], lefts[i], rights[i],
                  None if offsets is None else offsets[i]) for i in chunk]
        return trials_remote.remote(cfg_ref, cands, *[refs[k] for k in keys])

    queue = [todo[s:s + size] for s in range(0, len(todo), size)]
    queue.reverse()  # popped from the end: input order
    pending: dict = dict.fromkeys(making, None)  # ref -> chunk (None: a pieces task)
    limit = TASKS_PER_CPU * cpus
    bar = None
    if progress:
        bar = tqdm(total=len(todo), desc=f"grasp trials (ray, {cpus} CPUs)", unit="cand")
    try:
        while queue or pending:
            while queue and sum(c is not None for c in pending.values()) < limit:
                chunk = queue.pop()
                pending[submit(chunk)] = chunk
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                chunk = pending.pop(ref)
                if chunk is None:  # an object's pieces: cache them on the driver now
                    key, i = making[ref]
                    try:
                        hulls = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        log.warning("object pieces task failed: %s", exc)
                        continue  # the trials that need it fail and are reported per candidate
                    if isinstance(hulls, Hulls):
                        keep_pieces(objs[i], hulls, g, cache_dir=cache_dir)
                    continue
                try:
                    got = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    if len(chunk) > 1:
                        log.warning("ray task of candidates %d-%d failed after %d retries (%s); "
                                    "retrying them one by one", chunk[0], chunk[-1], TASK_RETRIES,
                                    type(exc).__name__)
                        queue.extend([i] for i in reversed(chunk))
                        continue
                    got = [TrialResult.zeros(cfg.sim.n_trials,
                                             error=f"ray task failed: {type(exc).__name__}: "
                                                   f"{_first_line(exc)}")]
                for i, res in zip(chunk, got):
                    results[i] = res
                if bar is not None:
                    bar.update(len(chunk))
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    return results


def _object_refs(ray, pieces_remote, objs, todo: list[int], hull_list, g, cache_dir):
    """One object-store entry per distinct object: the caller's pieces, cached ones, or a pieces
    task.  Returns (refs: key -> ObjectRef of Hulls | error string, key_of: candidate -> key,
    making: ObjectRef of a pieces task -> (key, a candidate index of that object))."""
    refs: dict = {}
    key_of: dict[int, object] = {}
    making: dict = {}
    for i in todo:
        if hull_list is not None:
            key = id(hull_list[i])
            if key not in refs:
                refs[key] = ray.put(hull_list[i])
        else:
            key = hashlib.sha1(np.ascontiguousarray(objs[i], np.float32).tobytes()).hexdigest()
            if key not in refs:
                try:
                    hit = cached_pieces(objs[i], g, cache_dir=cache_dir)
                except (F2FError, ValueError) as exc:
                    hit = f"{type(exc).__name__}: {exc}"
                if hit is not None:
                    refs[key] = ray.put(hit)
                else:
                    refs[key] = pieces_remote.remote(objs[i], g)
                    making[refs[key]] = (key, i)
        key_of[i] = key
    return refs, key_of, making


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:300] if text else ""
