"""Agreement of the MJX backend with plain MuJoCo on the same grasp triples.

    python benchmarks/mjx_agreement.py --n 256 --mjx-runs 2 --json agreement.json   # GPU machine
    python benchmarks/mjx_agreement.py --n 2 --config tiny --kinds wsg50 --threads 1 --workers 1
                        # CPU smoke of the pipeline (~70 s on one core; nothing holds, so the
                        # agreement it prints is trivial)

N random builtin triples (object, left finger, right finger) are made the way the pretraining
dataset makes them (``dataset.pretraining_pairs``: per builtin object its imprint pair, the
WSG50 pair and one pair cut from two other shapes, in that order, seeded), their object hulls
decomposed once (``geometry.hull_pool.object_hulls_many``, coacd, cached on disk) and handed to both
backends, so both simulate identical geometry.  Then ``sim.evaluate(..., backend="mujoco")`` and
``sim.evaluate(..., backend="mjx")`` run the 11 trials of every triple, each timed.  MJX's first
run includes compiling its programs (one per program and power-of-two batch size); with
``--mjx-runs 2`` the second, compiled run is timed too and compile time is their difference.

Printed: agreement rate per trial (grasp, S1..S4, R-30..R+30), overall agreement over all N x 11
trials, whole-vector agreement, the confusion counts of the grasp trial (both hold / only MuJoCo /
only MJX / neither) and every differing triple (index, kind of pair, object, differing trials).
One differing triple (a grasp disagreement first) is drawn to ``OUT/disagreement.png`` with both
outcome vectors in its title; ``--json`` writes the figures.

The issue's target: at least 95% of the trials agree (overall agreement >= 0.95).

Cost: 256 triples is a GPU job.  MJX on a CPU runs only some tens of environment steps per second
(a `tiny` grasp trial is 550 steps; a triple that holds costs 7 grasps and 4 pushes, padded to
power-of-two batches), and the first call of each program and batch size compiles (25-70 s on a
CPU).  On a CPU keep N at a few triples, or pick ``--kinds wsg50`` (flat tips at mu 0.2 never lift,
so only the grasp program runs).  WSG50 pairs rarely hold, so in the default mix about a third of
the triples agree trivially (0 == 0); the "held" row gives the trials of triples both backends held.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from f2f_jax import config, sim
from f2f_jax.bench.agreement import agreement_report, builtin_triples
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.dataset.pretraining import KINDS
from f2f_jax.geometry.hull_pool import object_hulls_many


def _vector(row) -> str:
    return "".join(str(int(v)) for v in row)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=256, help="triples simulated by both backends (default 256)")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS),
                   help="simulation phases (tiny: 550-step grasps, for CPU smoke runs)")
    p.add_argument("--seed", type=int, default=0, help="builtin object set and cut-pair draws")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS,
                   help="finger pair kinds in the mix (default: all three)")
    p.add_argument("--out", type=Path, default=Path("runs/mjx_agreement"),
                   help="folder for disagreement.png (default runs/mjx_agreement)")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    p.add_argument("--threads", type=int, default=os.cpu_count(),
                   help="MuJoCo backend worker threads (default: all cores)")
    p.add_argument("--workers", type=int, default=None,
                   help="coacd processes for uncached object hulls (default: one per core)")
    p.add_argument("--mjx-runs", type=int, default=1,
                   help="MJX evaluations of the same triples; with 2 or more the last one is timed "
                        "compiled, giving compile time apart (first minus last), and runs are "
                        "checked to agree (default 1)")
    p.add_argument("--cache-dir", type=Path, default=None, help="object hull cache (default ~/.cache/f2f_jax)")
    args = p.parse_args(argv)
    if args.n < 1 or args.mjx_runs < 1:
        p.error("--n and --mjx-runs must be >= 1")
    cfg = config.get(args.config)

    import jax

    dev = jax.local_devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}); jax {jax.__version__}; config {args.config}; "
          f"{args.n} triples, kinds {' '.join(args.kinds)}, seed {args.seed}", flush=True)

    t = time.perf_counter()
    pool, triples = builtin_triples(args.n, args.seed, cfg, args.kinds)
    used = sorted({tr["object"] for tr in triples})
    made = object_hulls_many([pool[i] for i in used], cfg, cache_dir=args.cache_dir, workers=args.workers)
    by_object = dict(zip(used, made))
    for i, h in by_object.items():
        if isinstance(h, str):  # both backends score its triples as failed (zeros)
            print(f"object {i}: no hulls: {h}")
    objs = np.stack([pool[tr["object"]] for tr in triples])
    lefts = np.stack([tr["left"] for tr in triples])
    rights = np.stack([tr["right"] for tr in triples])
    hulls = [by_object[tr["object"]] for tr in triples]
    counts = {k: sum(tr["kind"] == k for tr in triples) for k in args.kinds}
    print(f"prepared {len(triples)} triples on {len(used)} objects "
          f"({', '.join(f'{v} {k}' for k, v in counts.items())}) in {time.perf_counter() - t:.1f} s "
          f"(not timed below)", flush=True)

    t = time.perf_counter()
    out_mj, info_mj = sim.evaluate(objs, lefts, rights, backend="mujoco", cfg=cfg, threads=args.threads,
                                   object_hulls=hulls, return_info=True, progress=False)
    mujoco_s = time.perf_counter() - t
    print(f"MuJoCo: {mujoco_s:.1f} s on {args.threads} threads ({info_mj.total_steps} steps)", flush=True)

    from f2f_jax.sim import mjx_batch

    def first_calls() -> float:
        # mjx_batch counts the whole first call of each (program, batch size) as compile time:
        # compile plus one run.  Summed over every simulator made so far (one per layout).
        return float(sum(getattr(s, "compile_seconds", 0.0)
                         for s in getattr(mjx_batch, "_SIMULATORS", {}).values()))

    mjx_runs = []
    for run in range(args.mjx_runs):
        before = first_calls()
        t = time.perf_counter()
        out, info_mx = sim.evaluate(objs, lefts, rights, backend="mjx", cfg=cfg, object_hulls=hulls,
                                    return_info=True, progress=False)
        mjx_runs.append(dict(seconds=time.perf_counter() - t, first_call_seconds=first_calls() - before))
        print(f"MJX run {run + 1}: {mjx_runs[-1]['seconds']:.1f} s in total, of which "
              f"{mjx_runs[-1]['first_call_seconds']:.1f} s in first calls of programs (compile + run); "
              f"{info_mx.total_steps} physics steps over all candidates", flush=True)
        if run == 0:
            out_mx = out
        elif not np.array_equal(out, out_mx):
            print(f"MJX run {run + 1} differs from run 1 on {int((out != out_mx).any(1).sum())} triples "
                  f"(nondeterministic); the report uses run 1")
    mjx_s = mjx_runs[0]["seconds"]
    mjx_warm_s = mjx_runs[-1]["seconds"] if len(mjx_runs) > 1 else None
    mjx_compile_s = mjx_s - mjx_warm_s if mjx_warm_s is not None else None
    if mjx_warm_s is not None:
        print(f"MJX compiled: {mjx_warm_s:.1f} s per run; compile ~{mjx_compile_s:.1f} s "
              f"(first run minus the last)", flush=True)

    rep = agreement_report(out_mj, out_mx)
    print(f"\n{'trial':>6s} " + " ".join(f"{n:>5s}" for n in TRIAL_NAMES))
    print(f"{'agree':>6s} " + " ".join(f"{a:5.2f}" for a in rep["per_trial"]))
    if rep["per_trial_both_held"] is not None:
        print(f"{'held':>6s} " + " ".join(f"{a:5.2f}" for a in rep["per_trial_both_held"])
              + "   (triples both backends held)")
    print("success rate  MuJoCo " + " ".join(f"{a:5.2f}" for a in out_mj.mean(0)))
    print("success rate  MJX    " + " ".join(f"{a:5.2f}" for a in out_mx.mean(0)))
    verdict = "meets" if rep["agreement"] >= 0.95 else "misses"
    print(f"\noverall agreement {rep['agreement']:.4f} over {out_mj.size} trials ({verdict} the >= 0.95 target); "
          f"whole vectors {rep['whole_vectors']:.3f}")
    c = rep["grasp_confusion"]
    print(f"grasp trial: both hold {c['both_hold']}, only MuJoCo {c['only_mujoco']}, only MJX {c['only_mjx']}, "
          f"neither {c['neither']}")
    for name, info in (("MuJoCo", info_mj), ("MJX", info_mx)):
        if info.infeasible.any() or info.failed.any() or info.unstable.any():
            print(f"{name}: {int(info.infeasible.sum())} infeasible, {int(info.failed.sum())} failed, "
                  f"{int(info.unstable.sum())} unstable trials")

    differing = []
    for i in np.nonzero((out_mj != out_mx).any(1))[0]:
        tr = triples[i]
        trials = [TRIAL_NAMES[k] for k in np.nonzero(out_mj[i] != out_mx[i])[0]]
        differing.append(dict(index=int(i), kind=tr["kind"], object=tr["name"], trials=trials,
                              mujoco=_vector(out_mj[i]), mjx=_vector(out_mx[i])))
    print(f"\n{len(differing)} differing triples" + (":" if differing else ""))
    for d in differing:
        print(f"  #{d['index']:4d} {d['kind']:8s} {d['object']:28s} MuJoCo {d['mujoco']} MJX {d['mjx']}  "
              f"differ: {' '.join(d['trials'])}")

    if differing:
        from f2f_jax.render import render_grasp

        pick = next((d for d in differing if "grasp" in d["trials"]), differing[0])
        i = pick["index"]
        args.out.mkdir(parents=True, exist_ok=True)
        path = render_grasp(args.out / "disagreement.png", objs[i], lefts[i], rights[i], cfg=cfg,
                            scores=out_mj[i],
                            title=f"#{i} {pick['kind']} {pick['object']}: MuJoCo {pick['mujoco']} / "
                                  f"MJX {pick['mjx']} (boxes: MuJoCo)")
        print(f"drew triple #{i} to {path}")

    if args.json:
        result = dict(agreement=rep["agreement"], per_trial=rep["per_trial"], trial_names=list(TRIAL_NAMES),
                      n=len(triples), device=dev.device_kind, platform=dev.platform, config=args.config,
                      seed=args.seed, kinds=counts, mjx_seconds=mjx_s, mjx_compile_seconds=mjx_compile_s,
                      mjx_warm_seconds=mjx_warm_s, mjx_runs=mjx_runs,
                      mujoco_seconds=mujoco_s, mujoco_threads=args.threads,
                      whole_vectors=rep["whole_vectors"], grasp_confusion=rep["grasp_confusion"],
                      per_trial_both_held=rep["per_trial_both_held"], differing=differing,
                      target=0.95, meets_target=rep["agreement"] >= 0.95)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
