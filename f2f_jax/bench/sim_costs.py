"""Where the time of a plain-MuJoCo evaluation goes, on designs the simulator has not seen.

``unique_triples``: each object's imprint pair with both fingers moved by their own smooth random
field (``nets.inference.perturbed_heights``), so that no finger repeats and the simulator's finger
memo (``geometry.finger_tiling.remembered_finger_hulls``) never hits: what a design pool or a
co-training cycle asks of it.  ``cost_breakdown``: those triples' evaluations on this thread with
the simulator's parts timed (each part's own time, nested parts subtracted): finger pieces, the
object pieces' lookup (the disk cache or the shipped pieces), the input checks, model building,
the runner's set-up, the jaw opener, the trials' checks (health, rest, drop, held), ``mj_step``,
``mj_forward`` and the rest.  Outcomes are those of ``sim.evaluate``: only clocks are added.
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import ExitStack, contextmanager

import numpy as np

from f2f_jax import sim
from f2f_jax.geometry import finger_tiling, imprint_fingers
from f2f_jax.geometry.fingers import is_feasible
from f2f_jax.geometry.pieces import object_pieces_many
from f2f_jax.nets.inference import perturbed_heights
from f2f_jax.sim import mujoco_cpu, opening, protocol

# The breakdown's parts, in the order printed.
PARTS = ("finger pieces", "object pieces lookup", "input checks", "model building",
         "runner set-up", "jaw opener", "trial checks", "mj_step", "mj_forward", "other")


def unique_triples(tsdfs: np.ndarray, cfg, *, sd_voxels: float = 0.5, seed: int = 0,
                   tries: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, R, R, R] objects -> (objects, lefts, rights): each object's imprint pair, each finger
    moved by its own field of ``sd_voxels`` at the grid points (a field that leaves a finger
    infeasible is drawn again, up to ``tries`` times, then the imprint finger is kept)."""
    g = cfg.geometry
    rng = np.random.default_rng([seed, 1])
    lefts, rights = [], []
    for tsdf in tsdfs:
        pair = imprint_fingers(tsdf, g)
        for finger, out in zip(pair, (lefts, rights)):
            moved = np.asarray(finger, np.float32)
            for _ in range(tries):
                candidate = perturbed_heights(finger[None], sd_voxels, g.truncation_voxels, rng)[0]
                if is_feasible(candidate, g):
                    moved = candidate
                    break
            out.append(moved)
    return np.asarray(tsdfs), np.stack(lefts), np.stack(rights)


def forget_finger_pieces() -> None:
    """Empty the simulator's finger memo, so that the next row meshes every finger again (the
    presets share the geometry, so a second row on the same designs would find them there)."""
    memo = getattr(finger_tiling, "_memo", None)
    if memo is not None:
        with finger_tiling._memo_lock:
            memo.clear()


def unique_rows(objs, lefts, rights, pieces: dict, presets: dict, *, pybullet: bool) -> dict:
    """One-thread evaluations of unique designs under each preset of ``presets`` ({name: Config},
    ``pieces`` {name: object Hulls per triple}), every finger meshed inside the timed call (the
    memo emptied first), and with ``pybullet`` the PyBullet original protocol on the same triples
    (``bench.pybullet_runs``), its finger pieces (``finger_hulls``) made inside its time too.
    Returns {label: dict(evals, seconds, steps, workers=1, grasp_rate, outcomes)}."""
    rows = {}
    for name, cfg in presets.items():
        forget_finger_pieces()
        start = time.perf_counter()
        out, info = sim.evaluate_with_info(objs, lefts, rights, cfg=cfg, threads=1,
                                           object_hulls=pieces[name], progress=False)
        rows[f"{name} unique 1 thread"] = dict(
            evals=len(objs), seconds=time.perf_counter() - start, steps=info.total_steps,
            workers=1, grasp_rate=float(out[:, 0].mean()), outcomes=out)
    if pybullet:
        from f2f_jax.bench import pybullet_runs

        ref = presets["reference"]
        start = time.perf_counter()
        lh = [finger_tiling.finger_hulls(f, ref) for f in lefts]
        rh = [finger_tiling.finger_hulls(f, ref) for f in rights]
        out, stats = pybullet_runs.evaluate_original(pieces["reference"], lh, rh, cfg=ref)
        rows["pybullet unique"] = dict(evals=len(objs), seconds=time.perf_counter() - start,
                                       steps=int(stats["steps"]), workers=1,
                                       grasp_rate=float(out[:, 0].mean()), outcomes=out)
    return rows


def unique_report(objs, pieces: dict, presets: dict, *, sd_voxels: float, seed: int,
                  breakdown_n: int, pybullet: bool) -> dict:
    """``benchmarks/sim_throughput.py``'s unique rows: the objects' unique designs
    (``unique_triples``) through ``unique_rows``, then ``cost_breakdown`` of the first
    ``breakdown_n`` under presets["fast"].  Returns dict(rows (``unique_rows``'), result (its
    JSON keys), lines (what it prints after the rows' table))."""
    unique = unique_triples(objs, presets["fast"], sd_voxels=sd_voxels, seed=seed)
    rows = unique_rows(*unique, pieces, presets, pybullet=pybullet)

    def rate(label):
        return rows[label]["evals"] / rows[label]["seconds"]

    result = {f"unique_{name}_evals_per_s": rate(f"{name} unique 1 thread") for name in presets}
    ratios = []
    for key, label in (("reference", "reference unique 1 thread"), ("pybullet", "pybullet unique")):
        if label in rows:
            result[f"unique_ratio_fast_vs_{key}"] = rate("fast unique 1 thread") / rate(label)
            ratios.append(f"fast / {label.split()[0]} = {result[f'unique_ratio_fast_vs_{key}']:.2f}x")
    lines = [f"\nper core, the same {len(objs)} unique designs (every finger meshed inside its "
             f"row, {sd_voxels:g}-voxel fields): " + "; ".join(ratios)]
    b = min(breakdown_n, len(objs))
    if b > 0:
        costs = cost_breakdown(*(a[:b] for a in unique), presets["fast"])
        result["unique_fast_breakdown_ms"] = dict(costs["ms"], total=costs["total_ms"])
        lines.append(f"\nwhere a fast evaluation of a unique design goes, one thread, {b} designs, "
                     f"{costs['steps']:.0f} steps each: {costs['total_ms']:.0f} ms per evaluation "
                     f"(the clocks' own {costs['overhead_ms']:.1f} ms left out)")
        lines += [f"  {part:22s} {ms:7.1f} ms {100 * ms / costs['total_ms']:5.1f}%"
                  for part, ms in costs["ms"].items()]
    return dict(rows=rows, result=result, lines=lines)


class _Clock:
    """Exclusive times of wrapped callables: a call's time less that of the wrapped calls inside."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._inner: list[float] = []

    def wrap(self, part: str, fn):
        def timed(*args, **kwargs):
            self._inner.append(0.0)
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent = time.perf_counter() - start
                self.seconds[part] += spent - self._inner.pop()
                self.calls[part] += 1
                if self._inner:
                    self._inner[-1] += spent
        return timed


class _TimedMujoco:
    """The ``mujoco`` module as ``protocol`` sees it, with mj_step and mj_forward timed."""

    def __init__(self, module, clock: _Clock):
        self._module = module
        self.mj_step = clock.wrap("mj_step", module.mj_step)
        self.mj_forward = clock.wrap("mj_forward", module.mj_forward)

    def __getattr__(self, name):
        return getattr(self._module, name)


@contextmanager
def _patched(owner, name, value):
    old = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, old)


def _wrapper_seconds(n: int = 20000) -> float:
    """What one timed call adds to a call's time (s), from a wrapped and a bare no-op."""
    def bare():
        return None

    timed = _Clock().wrap("x", bare)
    start = time.perf_counter()
    for _ in range(n):
        bare()
    mid = time.perf_counter()
    for _ in range(n):
        timed()
    return max(0.0, (time.perf_counter() - mid) - (mid - start)) / n


def cost_breakdown(objs, lefts, rights, cfg) -> dict:
    """Evaluate the triples one after another on this thread with the parts timed, the finger
    memo emptied first.  Returns dict(evaluations, steps (per evaluation), ms: {part: ms per
    evaluation}, total_ms, overhead_ms (what the clocks themselves added, left out of "other"),
    outcomes).  Not thread-safe: it patches the simulator's modules while it runs."""
    forget_finger_pieces()
    overhead = _wrapper_seconds()
    clock = _Clock()
    runner = protocol.GraspRunner
    plan = [(protocol, "remembered_finger_hulls", "finger pieces"),
            (protocol, "build_model", "model building"),
            (protocol, "finger_object_contacts", "trial checks"),
            (runner, "__init__", "runner set-up"),
            (opening.JawOpener, "__init__", "jaw opener"),
            (opening.JawOpener, "__call__", "jaw opener")]
    plan += [(runner, name, "trial checks")
             for name in ("_finite", "_checked_speed", "speed", "dropped", "held", "object_height")
             if hasattr(runner, name)]
    n = len(objs)
    start = time.perf_counter()
    check = clock.wrap("input checks", mujoco_cpu._checked_triples)
    _, _, _, feasible = check(list(objs), list(lefts), list(rights), cfg.geometry)
    pieces = clock.wrap("object pieces lookup", object_pieces_many)(list(objs), cfg, progress=False)
    results = []
    with ExitStack() as stack:
        for owner, name, part in plan:
            stack.enter_context(_patched(owner, name, clock.wrap(part, getattr(owner, name))))
        stack.enter_context(_patched(protocol, "mujoco", _TimedMujoco(protocol.mujoco, clock)))
        for i in range(n):
            if feasible[i]:
                results.append(protocol.simulate_candidate(pieces[i], lefts[i], rights[i], cfg))
    total = time.perf_counter() - start
    ms = {part: 1e3 * clock.seconds.get(part, 0.0) / n for part in PARTS}
    overhead_ms = 1e3 * overhead * sum(clock.calls.values()) / n
    ms["other"] = 1e3 * total / n - sum(ms.values()) - overhead_ms
    return dict(evaluations=n, steps=float(np.mean([r.steps for r in results] or [0])), ms=ms,
                total_ms=1e3 * total / n - overhead_ms, overhead_ms=overhead_ms,
                outcomes=np.stack([r.outcome for r in results]))
