"""Does a verified design survive printing? Picks by the exact outcome against picks by the mean
over moved copies (``design(..., tolerance=...)``), both re-simulated on fresh moved copies.

    python research/design_tolerance.py --run-dir runs/cotrain --fresh 48 --seed 7 \\
        --candidates 16 --tolerance 0.3 --copies 3 --fresh-copies 4 --json OUT.json

One trial of a design turns on tenths of a millimetre of finger (``research/sim_retest.py
--perturb heights``), so the verified design pool's pick (the best of K + 3 simulated candidates) reports
more trials than its printed fingers will pass: part of its lead is luck of the draw. Here, on the
run's held-out objects (and ``--fresh N`` new built-in objects drawn with ``--seed``), the pool of
``design(candidates=K, verify=True)`` (the generator's K candidates drawn with ``--key``, then the
three imprint candidates) is simulated once exactly and ``--copies`` times with both fingers'
height maps moved by a smooth field of ``--tolerance`` mm (``perturbed_heights``; the default 0.3
moves the fingers' surface by ~0.15 mm on average). Each object's pick is made two ways: by the
exact outcome (``design``'s default) and by the mean over the exact pair and its copies
(``design(..., tolerance=, copies=)``), whose fields are one per object, copy and side, shared by
all of the object's candidates (``--fields shared``, design's: the candidates are compared under
the same printing errors), or every candidate's own (``--fields own``; ``both``: the two picks side
by side). The picks, the generator's own design and the imprint pair are then simulated on
``--fresh-copies`` new moved copies, one field per object and copy shared by all of them (paired;
a candidate two picks share is simulated once): what the printed fingers would pass.

Printed per pick: trials of 11 as reported (its score when picked), on fresh copies, and the
paired gain on fresh copies over the exact-outcome pick and over Imprint with 95% bootstrap
intervals over objects.  Cost: (K + 3) x (1 + copies) evaluations per object (copies twice with
``both``), plus at most one per pick and fresh copy (about 25 minutes for 61 objects, K 16, 3
copies on 2 cores; 40 with ``both``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def pick_table(picks: dict[str, np.ndarray], reported: dict[str, np.ndarray],
               fresh: dict[str, np.ndarray], *, base: str, imprint: str, seed: int = 0) -> dict:
    """Per pick: trials as reported, on fresh copies (``fresh``), objects picked as ``base`` picks,
    and the paired gains on fresh copies over ``base`` and ``imprint``: [mean, 95% interval low,
    high] (``tables.stats.paired_gain``, objects resampled).  picks: name -> [N] candidate index;
    reported: name -> [N] trials when picked; fresh: name -> [N, J, 11] outcomes on fresh copies."""
    from f2f_jax.tables.stats import paired_gain

    out = {}
    for name, ks in picks.items():
        row = dict(reported=float(np.mean(reported[name])), fresh=float(fresh[name].sum(-1).mean()),
                   same_pick_as_base=int(np.sum(ks == picks[base])))
        for what, other in (("gain_over_base", base), ("gain_over_imprint", imprint)):
            g = paired_gain(fresh[name], fresh[other], seed=seed)["trials_mean"]
            row[what] = [g["diff"], g["ci_low"], g["ci_high"]]
        out[name] = row
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-dir", required=True, type=Path, help="a co-training run (its newest checkpoint)")
    ap.add_argument("--fresh", type=int, default=0, help="also N new built-in objects, drawn with --seed "
                    "(use a seed other than the run's)")
    ap.add_argument("--seed", type=int, default=7, help="seed of the fresh objects and the moved copies")
    ap.add_argument("--objects", type=int, default=None, help="only the first N held-out objects")
    ap.add_argument("--candidates", type=int, default=16, help="the generator's candidates K")
    ap.add_argument("--key", type=int, default=7, help="key of the candidates' noise (design's key)")
    ap.add_argument("--tolerance", type=float, default=0.3, help="sd of the moving field at its grid "
                    "points, mm (0.3: the fingers' surface moves ~0.15 mm on average)")
    ap.add_argument("--copies", type=int, default=3, help="moved copies per candidate for the pick")
    ap.add_argument("--fresh-copies", type=int, default=4, help="new moved copies per pick for the score")
    ap.add_argument("--fields", choices=("own", "shared", "both"), default="shared",
                    help="the pick's moved copies: every candidate its own fields, one field per "
                    "object, copy and side shared by its candidates (design's), or both picks side by side")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if not args.tolerance > 0 or args.copies < 1 or args.fresh_copies < 1 or args.candidates < 1:
        ap.error("--tolerance must be > 0, --copies, --fresh-copies and --candidates >= 1")

    from f2f_jax import sim
    from f2f_jax.data import builtin_objects, held_out_objects
    from f2f_jax.designer import (
        imprint_candidates,
        printed_copies,
        rank_candidates,
        simulate_candidates,
        simulate_moved,
        tolerance_voxels,
    )
    from f2f_jax.geometry import mesh_to_tsdf, postprocess
    from f2f_jax.nets.inference import predict, propose
    from f2f_jax.train.checkpoint import load_trained_nets

    nets = load_trained_nets(args.run_dir)
    cfg, g = nets.config, nets.config.geometry
    objs, names = held_out_objects(args.run_dir, g)
    objs, names = objs[: args.objects], names[: args.objects]
    if args.fresh:
        meshes = builtin_objects(args.fresh, seed=args.seed)
        objs = np.concatenate([objs, np.stack([mesh_to_tsdf(m, g) for m in meshes])])
    n = len(objs)
    lefts, rights = propose(nets, objs, args.key, args.candidates)
    il, ir, made = imprint_candidates(objs, g)
    lefts, rights = np.concatenate([lefts, il], 1), np.concatenate([rights, ir], 1)
    feasible = postprocess(lefts, rights, g)
    feasible[:, args.candidates:] &= made  # a variant that cannot be made is never picked
    predicted = predict(nets, objs, lefts, rights)
    sd = tolerance_voxels(args.tolerance, g)
    print(f"{n} objects x {lefts.shape[1]} candidates ({int(feasible.sum())} feasible), "
          f"{args.copies} copies moved by {args.tolerance} mm = {sd:.3f} voxels", flush=True)
    t0 = time.time()
    exact = simulate_candidates(nets, objs, lefts, rights, feasible, "mujoco", progress=True)
    rows = np.arange(n)
    trials_exact = exact.sum(-1).astype(float)
    imprint = args.candidates  # IMPRINT_VARIANTS[0], the plain imprint pair
    picks = {"exact outcome": rank_candidates(feasible, predicted, exact)[:, 0]}
    reported = {"exact outcome": trials_exact[rows, picks["exact outcome"]]}
    for shared in {"own": [False], "shared": [True], "both": [False, True]}[args.fields]:
        moved = simulate_moved(nets, objs, lefts, rights, feasible, "mujoco", sd, args.copies,
                               np.random.default_rng([args.seed, 1]), progress=True, shared=shared)
        name = (f"mean over it and {args.copies} moved copies"
                + (", fields shared" if shared else ", own fields"))
        picks[name] = rank_candidates(feasible, predicted, exact, moved)[:, 0]
        reported[name] = ((trials_exact + moved.sum(-1).sum(0)) / (1 + args.copies))[rows, picks[name]]
    picks.update({"own design": np.zeros(n, int), "imprint": np.full(n, imprint)})
    reported.update({name: trials_exact[rows, picks[name]] for name in ("own design", "imprint")})

    # fresh copies: one field per object, copy and side, shared by every pick (paired); a
    # candidate two picks share is simulated once
    j = args.fresh_copies
    fresh, done = {}, {}
    for name, ks in picks.items():
        new = [i for i in rows if (i, ks[i]) not in done]
        if new:  # the fields depend on every row's index, so all rows are moved, the new simulated
            ml, mr = printed_copies(lefts[rows, ks], rights[rows, ks], args.tolerance, g, j,
                                    [args.seed, 2])
            idx = np.array([[c * n + i for i in new] for c in range(j)]).ravel()
            out = sim.evaluate(objs[np.tile(new, j)], ml[idx], mr[idx], cfg=cfg, progress=False)
            out = out.reshape(j, len(new), -1)
            for m, i in enumerate(new):
                done[(i, ks[i])] = out[:, m]
        fresh[name] = np.stack([done[(i, ks[i])] for i in rows])  # [N, J, 11]
        print(f"  {name}: {len(new)} of {n} picks new, x {j} fresh copies simulated", flush=True)
    table = pick_table(picks, reported, fresh, base="exact outcome", imprint="imprint")
    print(f"\n{'pick by':<52}{'reported':>9}{'fresh':>7}  {'minus exact-outcome pick':<26}"
          f"{'minus imprint':<26}same pick")
    for name, row in table.items():
        a, b = row["gain_over_base"], row["gain_over_imprint"]
        gains = "".join(f"{f'{d[0]:+.2f} [{d[1]:+.2f}, {d[2]:+.2f}]':<26}" for d in (a, b))
        print(f"{name:<52}{row['reported']:>9.2f}{row['fresh']:>7.2f}  {gains}"
              f"{row['same_pick_as_base']}/{n}")
    print(f"({n} objects, trials of 11; {time.time() - t0:.0f} s of simulation)")
    if args.json:
        args.json.write_text(json.dumps(dict(
            n_objects=n, candidates=int(lefts.shape[1]), tolerance_mm=args.tolerance,
            copies=args.copies, fresh_copies=args.fresh_copies, picks=table,
            command=" ".join(sys.argv)), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
