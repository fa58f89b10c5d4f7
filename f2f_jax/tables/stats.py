"""Statistics behind the tables: how well a fitness net ranks one object's designs, how the
outcomes of neighbouring designs agree, and paired bootstrap gains."""

from __future__ import annotations

import dataclasses

import numpy as np

from f2f_jax.config import Config
from f2f_jax.designer import simulate_candidates
from f2f_jax.geometry import postprocess
from f2f_jax.nets.inference import LATENT_NOISE, predict, propose, within_object_spearman  # noqa: F401
from f2f_jax.tables.designers import objects_array


def ranking_stats(predicted: np.ndarray, simulated: np.ndarray) -> dict[str, float]:
    """How well predicted success ranks several candidate designs of the same objects.

    predicted: [N, K, 11] fitness-net probabilities; simulated: [N, K, 11] 0/1 outcomes of the
    same candidates.  A candidate's score is its mean predicted probability, its value the number
    of trials it passed.  Returns:

    - ``spearman``: Spearman rank correlation of score and value within each object, averaged over
      the objects whose candidates differ in value (nan when none do); ``objects_ranked`` counts them.
    - ``trials_first``, ``trials_mean``, ``trials_picked``, ``trials_best``, ``trials_worst``:
      trials passed (of 11) by candidate 0, by the average candidate, by the one the fitness net
      scores highest, by the best and the worst simulated one (means over objects).
    - ``grasp_auc``: AUC of the predicted grasp probability for the simulated grasp over all
      N x K candidates pooled (nan when every grasp succeeded or every one failed); it rewards
      telling easy objects from hard ones too, which ``spearman`` does not.

    The gap between ``trials_picked`` and ``trials_mean`` is what the fitness net's guidance is
    worth to a generator that climbs it; ``trials_best`` - ``trials_first`` is the room there is.
    """
    from scipy.stats import rankdata

    p = np.asarray(predicted, np.float64)
    s = np.asarray(simulated, np.float64)
    if p.shape != s.shape or p.ndim != 3:
        raise ValueError(f"predicted {p.shape} and simulated {s.shape}: expected two [N, K, 11] arrays")
    score, value = p.mean(-1), s.sum(-1)
    rhos = within_object_spearman(p, s)
    rhos = rhos[~np.isnan(rhos)]
    rows = np.arange(len(score))
    grasp, prob = s[..., 0].ravel(), p[..., 0].ravel()
    pos, neg = prob[grasp == 1], prob[grasp == 0]
    if len(pos) and len(neg):  # Mann-Whitney: P(score of a held grasp > score of a failed one)
        ranks = rankdata(np.concatenate([pos, neg]))
        auc = (ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg))
    else:
        auc = float("nan")
    return {
        "spearman": float(np.mean(rhos)) if len(rhos) else float("nan"),
        "objects_ranked": len(rhos),
        "trials_first": float(value[:, 0].mean()),
        "trials_mean": float(value.mean()),
        "trials_picked": float(value[rows, score.argmax(1)].mean()),
        "trials_best": float(value.max(1).mean()),
        "trials_worst": float(value.min(1).mean()),
        "grasp_auc": float(auc),
    }


def candidate_designs(nets, objects, cfg: Config | None = None, *, candidates: int = 8,
                      noise: float | None = None, key=0):
    """``candidate_outcomes``' designs without simulating them (the same for the same nets, key
    and noise): lefts, rights [N, K, 40, 40, 40] post-processed, feasible [N, K]."""
    if candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    cfg = cfg or nets.config
    objs = objects_array(objects, cfg.geometry.resolution)
    lefts, rights = propose(nets, objs, key, candidates, LATENT_NOISE if noise is None else noise)
    feasible = postprocess(lefts, rights, cfg.geometry)
    return lefts, rights, feasible


def candidate_outcomes(nets, objects, cfg: Config | None = None, *, candidates: int = 8,
                       noise: float | None = None, key=0, backend: str = "mujoco",
                       object_hulls=None, progress: bool | None = None,
                       executor: str = "threads"):
    """``f2f_jax.design``'s candidates for every object, all simulated.

    Per object the generator's own output and ``candidates - 1`` latent perturbations (``noise``,
    default ``nets.inference.LATENT_NOISE``), post-processed; infeasible ones score 0 by the protocol.
    objects: [N, 40, 40, 40]; object_hulls: optional, one per object; executor: as in
    ``sim.evaluate``.
    Returns (lefts, rights [N, K, 40, 40, 40], feasible [N, K], simulated [N, K, T] uint8; T = 11
    for the whole protocol, 1 for a ``grasp_only`` config).
    """
    cfg = cfg or nets.config
    objs = objects_array(objects, cfg.geometry.resolution)
    lefts, rights, feasible = candidate_designs(nets, objs, cfg, candidates=candidates, noise=noise, key=key)
    simulated = simulate_candidates(dataclasses.replace(nets, config=cfg), objs, lefts, rights,
                                    feasible, backend, progress, object_hulls, executor=executor)
    return lefts, rights, feasible, simulated


def fitness_ranking(nets, objects, cfg: Config | None = None, *, candidates: int = 16,
                    noise: float | None = None, key=0, backend: str = "mujoco",
                    object_hulls=None, progress: bool | None = None,
                    executor: str = "threads", judges=None) -> dict:
    """``ranking_stats`` of a trained run's fitness net on ``candidates`` designs per object.

    The candidates are ``candidate_outcomes``' (the generator's own output and K - 1 latent
    perturbations), all simulated and scored by the fitness net.  This is the measurement behind
    the co-training's premise: a generator that climbs the fitness net can only improve on what
    the net ranks right.  objects: [N, 40, 40, 40]; object_hulls: one per object; judges: other
    runs' nets whose fitness nets score the same candidates (``ranking_report``).
    """
    if candidates < 2:
        raise ValueError(f"candidates must be >= 2 to rank anything, got {candidates}")
    cfg = cfg or nets.config
    objs = objects_array(objects, cfg.geometry.resolution)
    lefts, rights, feasible, simulated = candidate_outcomes(
        nets, objs, cfg, candidates=candidates, noise=noise, key=key, backend=backend,
        object_hulls=object_hulls, progress=progress, executor=executor)
    return ranking_report(nets, objs, lefts, rights, feasible, simulated, judges=judges)


def nearest_own_scores(lefts: np.ndarray, rights: np.ndarray) -> np.ndarray:
    """The ranking a fitness net has to beat: each candidate scored by how close it lies to the
    generator's own design (candidate 0), minus the mean absolute difference of both finger
    volumes.  It knows nothing of the object or the simulator; it ranks well exactly as far as a
    trained generator's output beats its own latent perturbations, the more so the further they
    stray.  Its pick is always the own design.

    lefts, rights: [N, K, R, R, R].  Returns [N, K] float64, 0 for candidate 0, negative after."""
    lefts, rights = np.asarray(lefts), np.asarray(rights)
    if lefts.ndim != 5 or lefts.shape != rights.shape:
        raise ValueError(f"lefts {lefts.shape} and rights {rights.shape}: expected two [N, K, R, R, R] arrays")
    out = np.empty(lefts.shape[:2])
    for i in range(len(lefts)):  # one object at a time: no second [N, K, R^3] array in memory
        a, b = lefts[i].astype(np.float32), rights[i].astype(np.float32)
        out[i] = -(np.abs(a - a[:1]).mean((1, 2, 3)) + np.abs(b - b[:1]).mean((1, 2, 3)))
    return out


def ranking_report(nets, objects, lefts, rights, feasible, simulated, *, judges=None) -> dict:
    """``ranking_stats`` of ``nets``' fitness net on simulated candidates (``candidate_outcomes``'
    lefts, rights [N, K, R, R, R], feasible [N, K], simulated [N, K, 11]), with ``objects``,
    ``candidates`` and ``feasible`` (the feasible share).  judges: {name: TrainedNets} whose
    fitness nets score the same candidates: under "judges", each one's ``ranking_stats`` and
    ``spearman_gain`` (``nets``' within-object Spearman minus the judge's, paired over objects:
    ``paired_spearman``).  "nearest_own": the same for the ranking by closeness to the own design
    (``nearest_own_scores``), the baseline a fitness net's ranking is worth something above."""
    objs = np.asarray(objects, np.float32)
    predicted = predict(nets, objs, lefts, rights)
    n, k = feasible.shape
    out = ranking_stats(predicted, simulated)
    out.update(objects=n, candidates=k, feasible=float(feasible.mean()))
    # ranking_stats scores by the mean over the outcomes: the one score repeated in each
    prior = np.repeat(nearest_own_scores(lefts, rights)[..., None], simulated.shape[-1], -1)
    out["nearest_own"] = {**ranking_stats(prior, simulated),
                          "spearman_gain": paired_spearman(predicted, prior, simulated)}
    if judges:
        out["judges"] = {}
        for name, judge in judges.items():
            theirs = predict(judge, objs, lefts, rights)
            out["judges"][name] = {**ranking_stats(theirs, simulated),
                                   "spearman_gain": paired_spearman(predicted, theirs, simulated)}
    return out


def paired_spearman(predicted_a: np.ndarray, predicted_b: np.ndarray, simulated: np.ndarray, *,
                    n_boot: int = 10000, seed: int = 0) -> dict[str, float]:
    """How much better fitness net a ranks one object's candidates than fitness net b, on the same
    simulated candidates ([N, K, 11] each): the within-object Spearman of a minus b's, averaged
    over the objects both can rank (``within_object_spearman``), with a 95% percentile bootstrap
    interval over those objects; ``objects`` counts them, ``better`` / ``worse`` those where a
    ranks better / worse.  All nan (objects 0) when no object can be ranked by both."""
    d = within_object_spearman(predicted_a, simulated) - within_object_spearman(predicted_b, simulated)
    d = d[~np.isnan(d)]
    if not len(d):
        return {"diff": float("nan"), "ci_low": float("nan"), "ci_high": float("nan"), "objects": 0,
                "better": 0, "worse": 0}
    boot = d[np.random.default_rng(seed).integers(0, len(d), (n_boot, len(d)))].mean(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return {"diff": float(d.mean()), "ci_low": float(lo), "ci_high": float(hi), "objects": int(len(d)),
            "better": int((d > 0).sum()), "worse": int((d < 0).sum())}


# --------------------------------------------------------------------------------------------
# Is one generator better than another?  Paired over objects, on each one's design neighbourhood.
# --------------------------------------------------------------------------------------------

def neighbourhood_stats(simulated: np.ndarray) -> dict[str, float]:
    """Summary of [N, K, 11] outcomes of K candidates per object (candidate 0: the generator's own).

    ``trials_own`` / ``grasp_own``: trials passed (of 11) and grasp success of the own designs;
    ``trials_mean`` / ``grasp_mean``: the same over all K candidates.  The K-candidate means score
    the generator's output and its latent neighbourhood, not one 0/1 draw per object, so they
    separate two generators with far fewer objects than the own designs alone do.
    """
    s = np.asarray(simulated, np.float64)
    if s.ndim != 3:
        raise ValueError(f"simulated {s.shape}: expected [N, K, 11]")
    return {"trials_own": float(s[:, 0].sum(-1).mean()), "grasp_own": float(s[:, 0, 0].mean()),
            "trials_mean": float(s.sum(-1).mean()), "grasp_mean": float(s[..., 0].mean()),
            "objects": s.shape[0], "candidates": s.shape[1]}


# paired_gain's measures: per object, from its [N, K, 11] simulated outcomes.
PAIRED_MEASURES = {
    "trials_mean": lambda s: s.sum(-1).mean(1), "grasp_mean": lambda s: s[..., 0].mean(1),
    "trials_own": lambda s: s[:, 0].sum(-1), "grasp_own": lambda s: s[:, 0, 0],
}


def paired_gain(after: np.ndarray, before: np.ndarray, *, n_boot: int = 10000,
                seed: int = 0) -> dict[str, dict[str, float]]:
    """How much ``after`` beats ``before`` on the same objects, with a bootstrap over objects.

    after, before: [N, K, 11] simulated outcomes of two generators' K candidates on the same N
    objects (K may differ).  For each measure (``trials_mean``, ``grasp_mean``, ``trials_own``,
    ``grasp_own``, as in ``neighbourhood_stats``) the per-object difference is averaged; returned
    per measure: before, after, diff, ci_low / ci_high (95% percentile bootstrap of the mean
    difference, objects resampled ``n_boot`` times), better / worse (objects that moved).
    """
    a, b = np.asarray(after, np.float64), np.asarray(before, np.float64)
    if a.ndim != 3 or b.ndim != 3 or a.shape[0] != b.shape[0] or a.shape[2] != b.shape[2]:
        raise ValueError(f"after {a.shape} and before {b.shape}: expected [N, K, 11] outcomes of "
                         "the same N objects")
    return {name: {"before": float(f(b).mean()), "after": float(f(a).mean()),
                   **difference_interval(f(a) - f(b), n_boot=n_boot, seed=seed)}
            for name, f in PAIRED_MEASURES.items()}


def difference_interval(d: np.ndarray, *, n_boot: int = 10000, seed: int = 0,
                        rng: np.random.Generator | None = None) -> dict[str, float]:
    """Per-object differences d [N] (N >= 1): their mean, its 95% percentile bootstrap interval
    (objects resampled ``n_boot`` times, drawn from ``rng`` or else a fresh generator of ``seed``,
    so one seed resamples every d of one N alike), and how many objects moved up or down."""
    d = np.asarray(d, np.float64)
    resample = (rng or np.random.default_rng(seed)).integers(0, len(d), (n_boot, len(d)))
    lo, hi = np.percentile(d[resample].mean(1), [2.5, 97.5])
    return {"diff": float(d.mean()), "ci_low": float(lo), "ci_high": float(hi),
            "better": int((d > 0).sum()), "worse": int((d < 0).sum())}

