"""What a co-training run of a config simulates and holds in memory, planned before it starts
(no JAX: ``experiments/cotrain.py`` prints it before the XLA flags are set)."""

from __future__ import annotations

from f2f_jax.config import Config, held_out_count


def planned_simulations(cfg: Config, n_objects: int | None = None) -> dict[str, int]:
    """How many 11-trial evaluations a run of ``cfg`` simulates, by stage, on ``n_objects`` objects
    (default: the config's built-in ``n_objects``): the pretraining dataset (at most: cut and
    perturbed pairs that cannot be made feasibly are skipped), the held-out baselines (imprint
    and flat pads; WSG-FMF with the pybullet extra adds one per held-out object), the co-training
    cycles' designs and the two held-out evaluations of the generator; "total" sums them.  A run
    taught by the simulator (``train.teacher``) designs ``teacher_candidates`` per teacher object
    and cycle, and 3 imprint variants more in cycle 1 (at most: a variant that cannot be made is
    skipped); one taught by the imprints simulates nothing in its cycles.  Not counted: the
    confirmations of ``train.teacher_copies`` (``teacher_copies`` evaluations per new target and
    as many per object's imprint, once), since how many objects improve is not known before."""
    t = cfg.train
    n = t.n_objects if n_objects is None else n_objects
    n_test = held_out_count(n, t.test_fraction)
    if t.teacher == "simulator":
        designs = (n - n_test + t.teacher_objects) * (t.cycles * t.teacher_candidates + 3 * (t.cycles > 0))
    elif t.teacher == "imprint":
        designs = 0
    else:
        designs = t.cycles * t.objects_per_cycle * t.cycle_candidates
    out = {"dataset": (n - n_test) * (2 + t.cut_pairs + t.perturbed_pairs), "baselines": 2 * n_test,
           "cycles": designs,
           "heldout": 2 * min(t.eval_objects, n_test)}
    out["total"] = sum(out.values())
    return out


def planned_row_bytes(cfg: Config, n_objects: int | None = None) -> int:
    """Bytes of the grasp rows a run of ``cfg`` holds in memory by its last cycle: the pretraining
    dataset and every cycle's designs, two float16 finger volumes each, and one float16 volume per
    object (rows share their object's: ``train.run_data.SharedVolumes``)."""
    plan = planned_simulations(cfg, n_objects)
    n = cfg.train.n_objects if n_objects is None else n_objects
    return (2 * (plan["dataset"] + plan["cycles"]) + n) * 2 * cfg.geometry.resolution ** 3
