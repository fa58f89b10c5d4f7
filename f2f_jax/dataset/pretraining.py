"""The pretraining grasp dataset (paper section 3.2): imprint, WSG50 and cut-from-shape finger
pairs for every object, simulated and appended to a GraspStore in resumable batches; optionally
(``TrainConfig.perturbed_pairs``) perturbed imprint pairs too, designs of one object that differ a
little, from which a fitness net can learn what separates one object's good fingers from its bad.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from tqdm.auto import tqdm

from f2f_jax import sim
from f2f_jax.config import Config, default
from f2f_jax.geometry import finger_from_shape, imprint_fingers, is_feasible, largest_component, wsg50_fingers
from f2f_jax.sim import ray_executor

KINDS = ("imprint", "wsg50", "cut")
PERTURBED = "perturbed"  # the kind of a perturbed imprint pair
PERTURB_GRID = 5  # the random field's coarse grid, per side, upsampled to the volume
# The largest field's peak, as a share of the TSDF range [-1, 1] (the k-th of K pairs gets k / K of it):
# at 0.3, 5 of 16 builtin objects' imprint + 6 perturbed pairs differ in any trial; at 0.6, 8
# (docs/learning.md, benchmarks/RESULTS.md).
PERTURB_AMPLITUDE = 0.3
PERTURB_TRIES = 10  # draws per finger before a perturbed pair is skipped


def perturbed_finger(finger: np.ndarray, rng: np.random.Generator, geometry,
                     *, amplitude: float = PERTURB_AMPLITUDE, tries: int = PERTURB_TRIES):
    """A designed-looking variant of ``finger`` [R, R, R]: plus a smooth random field, or None.

    The field is Gaussian noise on a ``PERTURB_GRID``^3 grid, upsampled to R^3 (cubic spline)
    and scaled to a peak of ``amplitude`` x 2 (the TSDF range); the sum is clipped to [-1, 1]
    and reduced to its largest component.  Up to ``tries`` draws are made until one is feasible
    (``geometry.is_feasible``); None when none is.
    """
    r = geometry.resolution
    for _ in range(tries):
        field = ndimage.zoom(rng.standard_normal((PERTURB_GRID,) * 3), r / PERTURB_GRID, order=3)
        field *= 2 * amplitude / np.abs(field).max()
        out = largest_component(np.clip(finger + field, -1.0, 1.0).astype(np.float32))
        if is_feasible(out, geometry):
            return out
    return None


def perturbed_pairs(left: np.ndarray, right: np.ndarray, n: int, rng: np.random.Generator,
                    geometry) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """``n`` perturbed variants of the pair (``left``, ``right``), at peaks rising evenly to
    ``PERTURB_AMPLITUDE`` (k / n of it for the k-th): from nearly the pair itself to clearly another
    design of the same object.  A pair whose fingers cannot be perturbed feasibly is skipped, so
    fewer than ``n`` may come back."""
    pairs = []
    for k in range(1, n + 1):
        amplitude = PERTURB_AMPLITUDE * k / n
        new_left = perturbed_finger(left, rng, geometry, amplitude=amplitude)
        new_right = perturbed_finger(right, rng, geometry, amplitude=amplitude)
        if new_left is not None and new_right is not None:
            pairs.append((new_left, new_right, PERTURBED))
    return pairs


def pretraining_pairs(object_tsdfs: np.ndarray, index: int, rng: np.random.Generator, cfg: Config,
                      n_cut: int = 2, max_tries: int = 20, n_perturbed: int = 0,
                      perturb_rng: np.random.Generator | None = None) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """Finger pairs to simulate on object ``index``: its imprint pair, the WSG50 pair, ``n_cut``
    pairs cut from two other random shapes each (left and right from different shapes, as the
    original did; shapes that give no feasible finger are skipped, up to ``max_tries``), then
    ``n_perturbed`` perturbed imprint pairs (``perturbed_pairs``) drawn from ``perturb_rng``, a
    stream of their own so that the other pairs are the same with or without them."""
    pairs = []
    left, right = imprint_fingers(object_tsdfs[index], cfg.geometry)
    pairs.append((left, right, "imprint"))
    left, right = wsg50_fingers(cfg.geometry)
    pairs.append((left, right, "wsg50"))
    others = [i for i in range(len(object_tsdfs)) if i != index] or [index]
    for _ in range(n_cut):
        cut = []
        for _ in range(max_tries):
            finger = finger_from_shape(object_tsdfs[rng.choice(others)], cfg.geometry)
            if finger is not None:
                cut.append(finger)
                if len(cut) == 2:
                    break
        if len(cut) == 2:
            pairs.append((cut[0], cut[1], "cut"))
    if n_perturbed:
        if perturb_rng is None:
            raise ValueError("n_perturbed > 0 needs a perturb_rng")
        pairs += perturbed_pairs(pairs[0][0], pairs[0][1], n_perturbed, perturb_rng, cfg.geometry)
    return pairs


def build_grasp_dataset(object_tsdfs: np.ndarray, names, store, *, cfg: Config | None = None,
                        seed: int = 0, batch_objects: int | None = None, n_cut: int = 2,
                        n_perturbed: int = 0, backend: str = "mujoco",
                        progress: bool = True, executor: str = "threads") -> dict:
    """Simulate the pretraining pairs of every object into ``store``; resumable.

    object_tsdfs: [N, R, R, R]; names: N object names.  Work goes in batches of ``batch_objects``
    objects (default 8; with executor "ray", 2 per cluster CPU and at least 8, so that every CPU
    of a cluster has work in each batch), each batch one atomic chunk keyed by its object names, so a killed run loses at most
    the batch in flight and a rerun skips finished objects.  The finger pairs of object i depend
    only on (seed, i), never on what was already done; ``n_perturbed`` perturbed imprint pairs per
    object (``pretraining_pairs``) come from ``default_rng([seed, i, 1])``.  executor: ``sim.evaluate``'s ("threads",
    or "ray": each batch's simulation in Ray tasks; the store is still written here, by the
    driver only).
    Returns counts and grasp success per kind for what this call simulated.
    """
    cfg = cfg or default()
    if batch_objects is None:
        batch_objects = 8
        if executor == "ray":
            batch_objects = max(8, 2 * ray_executor.cluster_cpus(ray_executor.connect()))
    if batch_objects < 1:
        raise ValueError(f"batch_objects must be >= 1, got {batch_objects}")
    object_tsdfs = np.asarray(object_tsdfs, np.float32)
    names = [str(n) for n in names]
    done = store.done_keys()
    todo = [i for i in range(len(names)) if names[i] not in done]
    if n_cut < 0 or n_perturbed < 0:
        raise ValueError(f"n_cut and n_perturbed must be >= 0, got {n_cut} and {n_perturbed}")
    stats = {k: [0, 0] for k in (*KINDS, PERTURBED)}
    bar = tqdm(total=len(todo), desc="grasp dataset", unit="obj", disable=not progress)
    for start in range(0, len(todo), batch_objects):
        batch = todo[start:start + batch_objects]
        rows = []
        for i in batch:
            rng = np.random.default_rng([seed, i])
            for left, right, kind in pretraining_pairs(object_tsdfs, i, rng, cfg, n_cut=n_cut,
                                                       n_perturbed=n_perturbed,
                                                       perturb_rng=np.random.default_rng([seed, i, 1])):
                rows.append((i, left, right, kind))
        objs = np.stack([object_tsdfs[i] for i, *_ in rows])
        lefts = np.stack([r[1] for r in rows])
        rights = np.stack([r[2] for r in rows])
        outcomes = sim.evaluate(objs, lefts, rights, backend=backend, cfg=cfg, progress=False,
                                executor=executor)
        kinds = [r[3] for r in rows]
        store.append(objs, lefts, rights, outcomes, kind=kinds, names=[names[r[0]] for r in rows],
                     keys=[names[i] for i in batch])
        for kind, out in zip(kinds, outcomes):
            stats[kind][0] += 1
            stats[kind][1] += int(out[0])
        bar.update(len(batch))
        bar.set_postfix({k: f"{v[1]}/{v[0]}" for k, v in stats.items() if v[0]})
    bar.close()
    return {k: {"pairs": v[0], "grasp_success": (v[1] / v[0]) if v[0] else float("nan")}
            for k, v in stats.items() if k in KINDS or v[0]}
