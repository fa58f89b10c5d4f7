"""A run's generator on many candidates per object, all simulated: does its fitness net rank them
as the simulator does, and is it better than another run's generator?

    python research/generator_candidates.py --run-dir runs/a --extra "b=runs/b" --fitness-ranking 16 \
        --fresh 48 --seed 7          # does run a's fitness net rank better than b's?
    python research/generator_candidates.py --run-dir runs/cotrain \
        --extra "cycle 0=runs/cotrain/pretrained" --fresh 48 --seed 7 --neighbourhood 8
                                     # did co-training help? (seed_table.py --paired pools it)

The objects, rows and saved steps are those of ``experiments/evaluate.py`` with the same flags
(``--run-dir``, ``--checkpoint``, ``--extra``, ``--objects``, ``--fresh``, ``--seed``, the
simulator's): the same command after a kill, or after an evaluate.py call into the same --out,
simulates only what is missing.

--fitness-ranking K simulates K candidates per object of the run's generator (its own design and
K - 1 latent perturbations) and asks whether its fitness net ranks them as the simulator does:
within-object Spearman, grasp AUC, trials passed by its pick against the generator's own design,
the average candidate, the best and the worst; the candidates ranked by closeness to the own
design (no fitness net) as a baseline; every --extra's fitness net scores the same candidates,
and the run's Spearman minus each one's is printed paired over objects (95% bootstrap).

--neighbourhood K simulates K candidates per object of the run's generator and of every --extra's
and prints each one's trials passed and grasp success (own design, all candidates), and the run's
paired gain over each --extra with a 95% bootstrap interval over objects.

Writes OUT/candidates.json (default OUT: RUN_DIR/eval): objects, names, source, and the
``fitness_ranking`` and ``neighbourhood`` figures (the latter with every candidate's outcomes);
``experiments/seed_table.py OUT ... --paired "A minus B"`` reads them beside OUT/results.json.
Results: docs/learning.md (the fitness net does not rank one object's designs; co-training adds
nothing measurable over its control).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from f2f_jax import tables as E
from f2f_jax.cli import evaluate as ev
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.tables import rows as R


def _say(msg: str) -> None:
    print(f"generator_candidates: {msg}", file=sys.stderr, flush=True)


def fitness_ranking(args, setup, row: str, nets, judges: dict) -> tuple[dict, str]:
    """The run's K candidates per object, all simulated (kept in the step store), scored by the
    run's fitness net and by every judge's (--extra) on the same candidates."""
    k, store = args.fitness_ranking, setup.store
    step = f"fitness ranking {k}"
    got = store.load(step, row)
    if got is not None and "outcomes" in got:  # the designs are made again (deterministic), not simulated
        lefts, rights, feasible = E.candidate_designs(nets, setup.objs, setup.cfg, candidates=k,
                                                      key=args.seed)
        simulated = got["outcomes"]
    else:
        _say(f"fitness ranking: {k} candidates per object, all simulated")
        lefts, rights, feasible, simulated = E.candidate_outcomes(
            nets, setup.objs, setup.cfg, candidates=k, key=args.seed, backend=args.backend,
            object_hulls=setup.hulls, progress=not args.quiet, executor=args.executor)
        store.save(step, row, outcomes=simulated)
    rk = E.ranking_report(nets, setup.objs, lefts, rights, feasible, simulated, judges=judges)
    lines = [f"Fitness net ranking ({rk['candidates']} candidates x {rk['objects']} objects): "
             f"within-object Spearman {rk['spearman']:.2f} ({rk['objects_ranked']} objects with "
             f"differing candidates), grasp AUC {rk['grasp_auc']:.2f}; trials passed of 11: "
             f"generator's own {rk['trials_first']:.2f}, average candidate {rk['trials_mean']:.2f}, "
             f"fitness net's pick {rk['trials_picked']:.2f}, best {rk['trials_best']:.2f}, "
             f"worst {rk['trials_worst']:.2f}"]
    near = rk["nearest_own"]
    g = near["spearman_gain"]
    lines.append(f"  no fitness net, the candidates ranked by closeness to the generator's own design (its "
                 f"pick: the own design): Spearman {near['spearman']:.2f}; {row}'s net minus it, paired over "
                 f"{g['objects']} objects: {g['diff']:+.3f} [{g['ci_low']:+.3f}, {g['ci_high']:+.3f}] "
                 f"(better / worse {g['better']} / {g['worse']})")
    for name, j in rk.get("judges", {}).items():
        g = j["spearman_gain"]
        lines.append(f"  {name}'s fitness net on the same candidates: Spearman {j['spearman']:.2f}, grasp "
                     f"AUC {j['grasp_auc']:.2f}, its pick {j['trials_picked']:.2f} trials; {row} minus "
                     f"{name}, Spearman paired over {g['objects']} objects: {g['diff']:+.3f} "
                     f"[{g['ci_low']:+.3f}, {g['ci_high']:+.3f}] (95% bootstrap; better / worse "
                     f"{g['better']} / {g['worse']})")
    return rk, "\n".join(lines)


def neighbourhood(args, setup, generators: dict) -> tuple[dict, str]:
    """K candidates per object of every generator, all simulated (kept in the step store); each
    one's stats and the first's paired gain over each other."""
    k, store = args.neighbourhood, setup.store
    sims = {}
    for name, m in generators.items():
        got = store.load(f"neighbourhood {k}", name)
        if got is not None:
            sims[name] = got["outcomes"]
            continue
        _say(f"neighbourhood of {name}: {k} candidates per object, all simulated")
        sims[name] = E.candidate_outcomes(m, setup.objs, setup.cfg, candidates=k, key=args.seed,
                                          backend=args.backend, object_hulls=setup.hulls,
                                          progress=not args.quiet, executor=args.executor)[3]
        store.save(f"neighbourhood {k}", name, outcomes=sims[name])
    stats = {name: E.neighbourhood_stats(v) for name, v in sims.items()}
    first, *others = sims
    gains = {name: E.paired_gain(sims[first], sims[name], seed=args.seed) for name in others}
    lines = [f"Generators on {len(setup.objs)} objects, {k} candidates each (own design + {k - 1} "
             "latent perturbations), trials passed of 11 and grasp success:",
             "| generator | own design: trials | own: grasp | all candidates: trials | all: grasp |",
             "|---|---|---|---|---|"]
    lines += [f"| {n} | {s['trials_own']:.2f} | {s['grasp_own']:.3f} | {s['trials_mean']:.2f} | "
              f"{s['grasp_mean']:.3f} |" for n, s in stats.items()]
    for name, g in gains.items():
        lines.append(f"{first} minus {name}, paired over objects (95% bootstrap interval; "
                     "objects better / worse):")
        lines += [f"  {m:12s} {v['diff']:+.3f}  [{v['ci_low']:+.3f}, {v['ci_high']:+.3f}]  "
                  f"{v['better']} / {v['worse']}" for m, v in g.items()]
    result = {"stats": stats, "gains": gains, "outcomes": {n: v.tolist() for n, v in sims.items()}}
    return result, "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ev.add_run_arguments(p)
    p.add_argument("--fitness-ranking", type=int, default=None, metavar="K",
                   help="how well the run's fitness net ranks K candidate designs per object")
    p.add_argument("--neighbourhood", type=int, default=None, metavar="K",
                   help="K candidates per object of the run's generator and every --extra's")
    args = p.parse_args(argv)
    if not args.run_dir:
        p.error("--run-dir is needed: its generator's candidates are what is measured")
    if args.fitness_ranking is None and args.neighbourhood is None:
        p.error("ask for --fitness-ranking K, --neighbourhood K or both")
    if args.fitness_ranking is not None and args.fitness_ranking < 2:
        p.error("--fitness-ranking K needs K >= 2 candidates to rank")
    if args.neighbourhood is not None and args.neighbourhood < 1:
        p.error("--neighbourhood K needs K >= 1")
    try:
        setup, extras = ev.start_study(args, say=_say)
    except (F2FError, ValueError) as exc:
        p.error(str(exc))
    start = time.perf_counter()
    nets = setup.nets()
    if nets is None:
        p.error(f"no usable checkpoint in {args.checkpoint or args.run_dir}")
    rows = R.Rows()  # only for the rows' recipes: the steps are named as evaluate.py names them
    row = R.model_rows(rows, nets, seed=args.seed)
    others = R.extra_rows(rows, extras, say=_say)
    setup.prepare(rows)
    results = {"objects": len(setup.objs), "names": setup.names, "source": setup.what,
               "backend": args.backend, "config": setup.config_name}
    printed = []
    if args.fitness_ranking:
        results["fitness_ranking"], text = fitness_ranking(args, setup, row, nets, others)
        printed.append(text)
    if args.neighbourhood:
        results["neighbourhood"], text = neighbourhood(args, setup, {row: nets, **others})
        printed.append(text)
    if setup.store.loaded:
        _say(f"took up {setup.store.loaded} steps finished by an earlier call")
    results["seconds"] = round(time.perf_counter() - start, 1)
    with atomic_path(setup.out_dir / "candidates.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1))
    print("\n".join(printed))
    print(f"{len(setup.objs)} objects ({setup.what}); wall time {results['seconds']:.0f} s; "
          f"wrote {setup.out_dir / 'candidates.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
