"""Test-retest of simulated outcomes: how much of one trial's 0/1 is the design, how much the path.

    python research/sim_retest.py --n 64                                  # builtin triples
    python research/sim_retest.py --run-dir runs/cotrain --candidates 8   # a run's designs

The same (object, left, right) triples are simulated twice with plain MuJoCo: once as configured,
once with a physically negligible change (``--perturb``: object mass x1.01, finger friction x1.01,
a timestep 5% shorter, or ``pieces``: the objects' coacd pieces made again with coacd's seed + 1,
as good a decomposition as the first, to ~25 s of coacd per object and core, or ``heights``: each
finger's height map, which is all of a finger the simulator meshes, moved by a smooth random field
of ``--height-sd`` voxels, one rerun per value; several may be given, each a rerun).  ``pieces``
is the floor that any other object geometry is judged against (``benchmarks/sim_agreement.py``): no
decomposition can be asked to agree with coacd's more often than coacd's agrees with itself.  A
design whose outcome flips under a 1% change in mass is decided by the solver's path, not by its
shape: no fitness net can learn such a flip, and no backend (MJX included, ``benchmarks/
sim_agreement.py --backends mjx mujoco``) can be asked to agree with MuJoCo more often than
MuJoCo agrees with itself.

Two sources of triples:

* ``--n N``: builtin objects with the pretraining dataset's pairs (imprint, WSG50, one cut pair),
  as ``bench.agreement.builtin_triples`` makes them (same seed, same triples).
* ``--run-dir RUN --candidates K``: ``f2f_jax.design``'s K candidates (the generator's own output
  and K - 1 latent perturbations) on the run's held-out objects.  Also printed: the within-object
  test-retest Spearman of trials passed, and how the best candidate of the first run scores in
  the rerun against its first-run score (the part of best-of-K that is selection luck).

``heights`` asks how finely the outcomes depend on the fingers' shape: moved by a tenth of a
voxel on average (``--height-sd 0.2``: 0.15 mm, a printer's tolerance) or by half a voxel
(``--height-sd 1``), how often does a trial flip, and does one object's ranking of its candidates
survive?  ``--height-sd 0`` is the re-voxelisation alone (height map -> TSDF), the floor of the
others.  A ranking that a half-voxel change scrambles cannot be learnt by a fitness net that sees
the fingers at 40^3, nor trusted in a printed finger.

Printed per perturbation: agreement per trial and overall, whole 11-vectors, success rates of both
runs.  ``--json PATH`` writes the figures.  Cost: one MuJoCo evaluation per triple and run (about
0.7 s on 2 cores in the default config).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from f2f_jax import config, sim
from f2f_jax.bench.agreement import agreement_report, builtin_triples
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.geometry.coacd_pieces import CoacdSettings
from f2f_jax.nets.inference import perturbed_heights

PERTURBATIONS = {
    "mass": lambda s: dataclasses.replace(s, object_mass=s.object_mass * 1.01),
    "friction": lambda s: dataclasses.replace(s, finger_friction=s.finger_friction * 1.01),
    "timestep": lambda s: dataclasses.replace(s, timestep=s.timestep * 0.95),
}
PIECES = "pieces"  # the object pieces again, by coacd with these settings:
PIECES_SETTINGS = CoacdSettings(seed=CoacdSettings().seed + 1)
HEIGHTS = "heights"  # every finger's height map moved by a smooth field of --height-sd voxels


def retest_stats(first: np.ndarray, second: np.ndarray) -> dict:
    """Within-object test-retest of [N, K, 11] outcomes of the same N x K designs.

    spearman: mean over objects of the rank correlation of trials passed between the two runs
    (objects whose candidates tie in either run are left out); best_first / best_retest: trials
    passed by each object's best first-run candidate, in the first run and in the rerun; mean:
    trials passed by the average candidate in the first run.
    """
    from scipy.stats import spearmanr

    a = first.sum(-1).astype(float)
    b = second.sum(-1).astype(float)
    rho = [spearmanr(x, y).statistic for x, y in zip(a, b) if x.std() > 0 and y.std() > 0]
    best = a.argmax(1)
    rows = np.arange(len(a))
    return dict(spearman=float(np.mean(rho)) if rho else float("nan"), objects_ranked=len(rho),
                mean=float(a.mean()), best_first=float(a[rows, best].mean()),
                best_retest=float(b[rows, best].mean()))


def _run_candidates(run_dir: Path, k: int, seed: int, workers):
    """The run's held-out objects, K design candidates each, their feasibility and object hulls."""
    from f2f_jax.data import held_out_objects
    from f2f_jax.geometry import postprocess
    from f2f_jax.geometry.hull_pool import object_hulls_many
    from f2f_jax.nets.inference import propose
    from f2f_jax.train.checkpoint import load_trained_nets

    nets = load_trained_nets(run_dir)
    objs, names = held_out_objects(run_dir, nets.config.geometry)
    lefts, rights = propose(nets, objs, seed, k)
    feasible = postprocess(lefts, rights, nets.config.geometry)
    hulls = object_hulls_many(list(objs), nets.config, workers=workers)
    return nets, objs, names, lefts, rights, feasible, hulls


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=64, help="builtin triples (ignored with --run-dir)")
    p.add_argument("--run-dir", type=Path, default=None, help="a co-training run: its design candidates")
    p.add_argument("--candidates", type=int, default=8, help="candidates per held-out object (--run-dir)")
    p.add_argument("--perturb", nargs="+", default=["mass"],
                   choices=sorted([*PERTURBATIONS, PIECES, HEIGHTS]),
                   help="reruns, one per perturbation (default: mass)")
    p.add_argument("--height-sd", type=float, nargs="+", default=[0.2], metavar="VOXELS",
                   help="--perturb heights: the field's standard deviation in voxels (1.5 mm at the "
                        "default's 40^3 over 6 cm), one rerun per value (default 0.2; 0: the "
                        "re-voxelisation alone)")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS),
                   help="simulation phases of builtin triples (a run uses its own config)")
    p.add_argument("--seed", type=int, default=0, help="builtin triples / candidate noise")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="MuJoCo worker threads")
    p.add_argument("--workers", type=int, default=None, help="coacd processes for uncached hulls")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    if args.n < 1 or args.candidates < 2:
        p.error("--n must be >= 1 and --candidates >= 2")
    if any(sd < 0 for sd in args.height_sd):
        p.error("--height-sd must be >= 0 voxels")
    if args.run_dir is not None and not (args.run_dir / "run.json").exists():
        print(f"sim_retest: error: {args.run_dir} is not a co-training run directory (no run.json)",
              file=sys.stderr)
        return 2

    from f2f_jax.geometry.hull_pool import object_hulls_many

    t = time.perf_counter()
    if args.run_dir is not None:
        nets, objs, names, lefts, rights, feasible, hulls = _run_candidates(
            args.run_dir, args.candidates, args.seed, args.workers)
        cfg = nets.config
        n, k = feasible.shape
        ib, ik = np.nonzero(feasible)
        o, lft, rgt = objs[ib], lefts[ib, ik], rights[ib, ik]
        hl = [hulls[i] for i in ib]
        volumes, volume_of = list(objs), list(ib)
        what = f"{n} held-out objects x {k} candidates of {args.run_dir} ({len(ib)} feasible)"
    else:
        cfg = config.get(args.config)
        pool, triples = builtin_triples(args.n, args.seed, cfg)
        used = sorted({tr["object"] for tr in triples})
        by_object = dict(zip(used, object_hulls_many([pool[i] for i in used], cfg, workers=args.workers)))
        o = np.stack([pool[tr["object"]] for tr in triples])
        lft = np.stack([tr["left"] for tr in triples])
        rgt = np.stack([tr["right"] for tr in triples])
        hl = [by_object[tr["object"]] for tr in triples]
        volumes, volume_of = [pool[i] for i in used], [used.index(tr["object"]) for tr in triples]
        what = f"{len(triples)} builtin triples (seed {args.seed}, config {args.config})"
    print(f"prepared {what} in {time.perf_counter() - t:.1f} s", flush=True)
    if PIECES in args.perturb and cfg.geometry.object_method != "coacd":
        p.error(f"--perturb {PIECES} remakes coacd pieces; this config's objects are "
                f"{cfg.geometry.object_method!r}")

    def simulate(c, pieces=None, fingers=None):
        left, right = (lft, rgt) if fingers is None else fingers
        return sim.evaluate(o, left, right, backend="mujoco", cfg=c, threads=args.threads,
                            object_hulls=hl if pieces is None else pieces, progress=False)

    def moved_fingers(sd):
        """Every finger's height map moved by sd voxels (``perturbed_heights``), one seed per rerun."""
        rng = np.random.default_rng([args.seed, int(round(sd * 1000))])
        tr = cfg.geometry.truncation_voxels
        return perturbed_heights(lft, sd, tr, rng), perturbed_heights(rgt, sd, tr, rng)

    def reseeded_pieces():
        """Every object's pieces by coacd with seed + 1 (cached on disk like the first)."""
        made = object_hulls_many(volumes, cfg, workers=args.workers, settings=PIECES_SETTINGS,
                                 progress=True)
        return [made[i] for i in volume_of]

    t = time.perf_counter()
    base = simulate(cfg)
    print(f"first run: {time.perf_counter() - t:.1f} s", flush=True)
    results = {"source": what, "n_triples": len(o), "perturbations": {}}
    reruns = [(f"{HEIGHTS} {sd:g}" if name == HEIGHTS else name, name, sd)
              for name in args.perturb for sd in (args.height_sd if name == HEIGHTS else [None])]
    for label, name, sd in reruns:
        t = time.perf_counter()
        if name == PIECES:
            again = simulate(cfg, reseeded_pieces())
        elif name == HEIGHTS:
            again = simulate(cfg, fingers=moved_fingers(sd))
        else:
            again = simulate(cfg.replace(sim=PERTURBATIONS[name](cfg.sim)))
        rep = agreement_report(base, again)
        print(f"\n{label} rerun ({time.perf_counter() - t:.1f} s)")
        print(f"{'trial':>7s} " + " ".join(f"{n:>5s}" for n in TRIAL_NAMES))
        print(f"{'agree':>7s} " + " ".join(f"{a:5.3f}" for a in rep["per_trial"]))
        print(f"{'first':>7s} " + " ".join(f"{a:5.2f}" for a in base.mean(0)))
        print(f"{'rerun':>7s} " + " ".join(f"{a:5.2f}" for a in again.mean(0)))
        print(f"overall agreement {rep['agreement']:.4f} over {base.size} trials; whole vectors "
              f"{rep['whole_vectors']:.3f}")
        entry = dict(agreement=rep["agreement"], per_trial=rep["per_trial"],
                     whole_vectors=rep["whole_vectors"], grasp_confusion=rep["grasp_confusion"])
        if args.run_dir is not None:
            full = [np.zeros((n, k, len(TRIAL_NAMES)), np.uint8) for _ in range(2)]
            full[0][ib, ik], full[1][ib, ik] = base, again
            rs = retest_stats(*full)
            print(f"within-object test-retest Spearman of trials passed {rs['spearman']:.3f} "
                  f"({rs['objects_ranked']} objects); the best first-run candidate passes "
                  f"{rs['best_first']:.2f} trials, {rs['best_retest']:.2f} in the rerun (average "
                  f"candidate {rs['mean']:.2f})")
            entry.update(rs)
        results["perturbations"][label] = entry
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
