"""Agreement of two simulation presets on the same (object, left finger, right finger) triples.

    python benchmarks/sim_agreement.py                                  # fast vs reference, 256 triples
    python benchmarks/sim_agreement.py --objects meshes/ --n-objects 32 --n 128 --json agree.json
    python benchmarks/sim_agreement.py --n 4 --n-objects 1 --config tiny --presets fast fast \\
        --threads 1                                                     # smoke run: agreement 1.0
    python benchmarks/sim_agreement.py --n 64 --render 1                # draw a disagreement
    python benchmarks/sim_agreement.py --object-method tiles            # fast with tiled objects
    python benchmarks/sim_agreement.py --presets fast fast --backends mjx mujoco --triples dataset \
        --n 256 --judged-runs 2 --json agreement.json                   # MJX on a GPU machine

``--presets JUDGED JUDGE`` (``config.SIM_PRESETS``; default ``fast reference``) names the preset
under test and the one it is judged against; ``--backends JUDGED JUDGE`` (default ``mujoco
mujoco``) the simulator of each side, e.g. ``--presets reference reference --backends warp
mujoco``: MuJoCo Warp against plain MuJoCo (labels become ``<preset>@<backend>``).  Both simulate the same triples with plain MuJoCo,
each with its own object pieces (``geometry.pieces.object_pieces`` under that preset's
``object_method``: coacd cached on disk, or tiles made in this process) and its own protocol
settings (early exits at rest or none).  Two equal presets give a determinism check:
their outcomes must agree exactly.

Objects: ``--n-objects`` builtin objects (``--seed``) or the first ``--n-objects`` readable meshes
of ``--objects DIR``.  Per object, four finger kinds, in this order: its imprint pair, the WSG50
pair, one pair cut from two other objects of the set (``dataset.pretraining_pairs``, seeded
by (seed, object)) and a "perturbed" pair, designed-looking fingers: the imprint pair plus a
smooth random field (``perturbed_finger``).  The first ``--n`` triples of objects x kinds are
simulated.  ``--triples dataset`` takes instead the triples of ``bench.agreement.builtin_triples``:
per builtin object of ``--seed`` its imprint pair, the WSG50 pair and one pair cut from two other
shapes (the pretraining dataset's kinds, filtered by ``--kinds``), the first ``--n``; on a CPU keep
``--n`` at a few triples for a batched backend, or pick ``--kinds wsg50`` (flat tips at mu 0.2
never lift, so only the grasp program runs).

``--judged-runs R`` evaluates the judged side R times on the same triples: the report is of the
first run, each run's seconds are printed (for a batched backend the first includes compiling its
programs, so first minus last is the compile time; MJX's first calls are also summed apart) and a
run that differs from the first is reported (nondeterminism).

Printed: each preset's object meshing cost per object (uncached, one thread; coacd presets are read from
their cache or decomposed in ``--threads`` processes and not timed per object), the wall time and
physics steps of each preset's evaluation, a table of rates per finger kind and preset (grasp
success, mean trials passed of 11, mean S1..S4 and R-30..R+30 success), agreement per trial
name (and over the triples both sides held: trials 1..10 agree trivially where a grasp failed),
each side's success rate per trial, per finger kind and overall, whole 11-vector agreement, the
grasp confusion counts, the largest rate gap over finger kinds and the first 10 differing
triples.  ``--render K`` draws the first K differing triples with both presets
(``sim.view.render_trials``) to ``--out`` (a drawing that fails is reported and skipped);
``--json PATH`` writes every figure: the keys of ``agreement_stats`` plus n, presets (the two
labels, "<name>-1" / "<name>-2" when both are the same preset), object_meshing_s ({mean, max} s
per object of the judged preset; null for coacd), steps_per_eval and seconds per preset,
per_trial_both_held, judged_runs (seconds and first_call_seconds of each run of the judged side), and
differing (index, object, kind and both outcome vectors of every differing triple).
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
from f2f_jax.bench.agreement import (
    FINGER_KINDS,
    agreement_report,
    agreement_stats,
    builtin_triples,
    load_objects,
    mixed_triples,
    preset_hulls,
    render_differing,
    vector_text,
)
from f2f_jax.config import SIM_PRESETS, TRIAL_NAMES
from f2f_jax.data import mesh_files
from f2f_jax.dataset.pretraining import KINDS
from f2f_jax.geometry.hulls import with_max_vertices
from f2f_jax.geometry.pieces import OBJECT_METHODS

SHOWN_DIFFERING = 10


def _first_call_seconds() -> float:
    """Seconds MJX has spent in the first call of each (program, batch size), compile plus one
    run, summed over every simulator made so far (0 before MJX is imported)."""
    mjx_batch = sys.modules.get("f2f_jax.sim.mjx_batch")
    return float(sum(getattr(s, "compile_seconds", 0.0)
                     for s in getattr(mjx_batch, "_SIMULATORS", {}).values()))


def _report_run(run: int, runs: list[dict], out: np.ndarray, first: np.ndarray) -> None:
    """A later run of the judged side: its time, the compile time it implies, whether it agrees."""
    print(f"judged run {run + 1}: {runs[-1]['seconds']:.1f} s ({runs[-1]['first_call_seconds']:.1f} s in "
          f"first calls of MJX programs); compile ~{runs[0]['seconds'] - runs[-1]['seconds']:.1f} s "
          "(first run minus this one)", flush=True)
    if not np.array_equal(out, first):
        print(f"judged run {run + 1} differs from run 1 on {int((out != first).any(1).sum())} triples "
              "(nondeterministic); the report uses run 1")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=256, help="triples simulated by both presets (default 256)")
    p.add_argument("--n-objects", type=int, default=64, help="objects the triples are made on (default 64)")
    p.add_argument("--objects", type=Path, default=None,
                   help="a directory of mesh files (default: builtin objects)")
    p.add_argument("--presets", nargs=2, default=["fast", "reference"], choices=sorted(SIM_PRESETS),
                   metavar=("JUDGED", "JUDGE"),
                   help=f"the preset under test and its judge, of {sorted(SIM_PRESETS)} (default: fast reference)")
    p.add_argument("--backends", nargs=2, default=["mujoco", "mujoco"], metavar=("JUDGED", "JUDGE"),
                   choices=list(sim.BACKENDS),
                   help="the simulator of each side, of mujoco, mjx, warp (default: mujoco mujoco)")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS),
                   help="the config both presets are applied to (default: default)")
    p.add_argument("--hull-vertices", type=int, default=None, metavar="V",
                   help="the judged side's pieces with at most V vertices each: its object pieces "
                        "reduced from the judge's cached ones, its finger hulls made with V")
    p.add_argument("--object-method", default=None, choices=OBJECT_METHODS,
                   help="the judged side's object pieces by this method instead of its preset's "
                        "(e.g. tiles: the fast preset's protocol with tiled objects)")
    p.add_argument("--seed", type=int, default=0, help="builtin objects, cut and perturbed fingers")
    p.add_argument("--threads", type=int, default=os.cpu_count(),
                   help="MuJoCo worker threads and coacd processes (default: all cores)")
    p.add_argument("--render", type=int, default=0, metavar="K",
                   help="draw the first K differing triples with both presets (default 0)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/out/agreement"),
                   help="folder for --render's PNGs (default benchmarks/out/agreement)")
    p.add_argument("--triples", choices=("mixed", "dataset"), default="mixed",
                   help="mixed: objects x four finger kinds (default); dataset: builtin objects "
                        "with the pretraining dataset's pairs (bench.agreement.builtin_triples)")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS,
                   help="--triples dataset: the pair kinds in the mix (default: all three)")
    p.add_argument("--judged-runs", type=int, default=1, metavar="R",
                   help="evaluate the judged side R times: compile time apart and a determinism "
                        "check (default 1)")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    if args.n < 1 or args.n_objects < 1 or args.threads < 1 or args.render < 0 or args.judged_runs < 1:
        p.error("--n, --n-objects, --threads and --judged-runs must be >= 1, --render >= 0")
    if args.triples == "dataset" and args.objects is not None:
        p.error("--triples dataset makes its triples of builtin objects: drop --objects")
    if args.hull_vertices is not None and args.hull_vertices < 4:
        p.error("--hull-vertices must be >= 4")
    if args.objects is not None:
        if not args.objects.is_dir():
            p.error(f"--objects {args.objects}: no such directory")
        if not mesh_files(args.objects):
            p.error(f"--objects {args.objects}: no mesh files in this directory")
    base = config.get(args.config)
    judged, judge = args.presets
    labels = tuple(name if backend == "mujoco" else f"{name}@{backend}"
                   for name, backend in zip(args.presets, args.backends))
    if args.hull_vertices is not None:
        labels = (f"{labels[0]}/v{args.hull_vertices}", labels[1])
    if args.object_method is not None:
        labels = (f"{labels[0]}/{args.object_method}", labels[1])
    if labels[0] == labels[1]:
        labels = (f"{labels[0]}-1", f"{labels[1]}-2")
    backend_of = dict(zip(labels, args.backends))

    t = time.perf_counter()
    if args.triples == "dataset":
        tsdfs, triples = builtin_triples(args.n, args.seed, base, args.kinds)
    else:
        tsdfs, names = load_objects(args.n_objects, args.seed, args.objects, base.geometry)
        if not len(tsdfs):
            p.error(f"--objects {args.objects}: none of its mesh files became an object volume")
        triples = mixed_triples(tsdfs, names, args.n, args.seed, base)
    names = {tr["object"]: tr["name"] for tr in triples}
    kinds = [tr["kind"] for tr in triples]
    counts = {k: kinds.count(k) for k in FINGER_KINDS if k in kinds}
    source = str(args.objects) if args.objects is not None else f"builtin (seed {args.seed})"
    print(f"{len(triples)} triples on {len(tsdfs)} objects of {source} "
          f"({', '.join(f'{v} {k}' for k, v in counts.items())}) in {time.perf_counter() - t:.1f} s; "
          f"config {args.config}, presets {judged} (judged) vs {judge} (judge)", flush=True)
    if len(triples) < args.n:
        print(f"note: only {len(triples)} of the {args.n} triples asked for: give more --n-objects")

    used = sorted({tr["object"] for tr in triples})
    presets, meshing = {}, None
    for side, (label, name) in enumerate(zip(labels, args.presets)):
        cfg = config.with_sim_preset(base, name)
        if side == 0 and args.object_method is not None:
            cfg = cfg.replace(geometry=dataclasses.replace(cfg.geometry, object_method=args.object_method))
        t = time.perf_counter()
        made, seconds = preset_hulls(tsdfs[used], cfg, args.threads)
        if side == 0 and args.hull_vertices is not None:
            v = args.hull_vertices
            made = [h if isinstance(h, str) else with_max_vertices(h, v) for h in made]
            cfg = cfg.replace(geometry=dataclasses.replace(cfg.geometry, hull_vertices=v))
        by_object = dict(zip(used, made))
        presets[label] = (cfg, by_object)
        how = (f"{cfg.geometry.object_method}, per object mean {seconds.mean():.3f} s, max {seconds.max():.3f} s"
               if seconds is not None else f"{cfg.geometry.object_method}, cached, {args.threads} processes")
        print(f"{label}: object hulls of {len(used)} objects in {time.perf_counter() - t:.1f} s ({how})", flush=True)
        for i, h in by_object.items():
            if isinstance(h, str):
                print(f"  {names[i]}: no object hulls ({h}); its triples score zeros")
        if label == labels[0] and seconds is not None:
            meshing = dict(mean=float(seconds.mean()), max=float(seconds.max()))

    objs = np.stack([tsdfs[tr["object"]] for tr in triples])
    lefts = np.stack([tr["left"] for tr in triples])
    rights = np.stack([tr["right"] for tr in triples])
    outcomes, seconds, steps, judged_runs = {}, {}, {}, []
    for label, (cfg, by_object) in presets.items():
        for run in range(args.judged_runs if label == labels[0] else 1):
            before, t = _first_call_seconds(), time.perf_counter()
            out, info = sim.evaluate_with_info(objs, lefts, rights, cfg=cfg, threads=args.threads,
                                               object_hulls=[by_object[tr["object"]] for tr in triples],
                                               progress=True,
                                               backend=backend_of[label])
            if label == labels[0]:
                judged_runs.append(dict(seconds=time.perf_counter() - t,
                                        first_call_seconds=_first_call_seconds() - before))
            if run:
                _report_run(run, judged_runs, out, outcomes[label])
                continue
            outcomes[label] = out
            seconds[label] = time.perf_counter() - t
            ran = ~(info.infeasible | info.failed)
            steps[label] = float(info.steps[ran].mean()) if ran.any() else 0.0
            where = f"{args.threads} threads" if backend_of[label] == "mujoco" else backend_of[label]
            print(f"{label}: {seconds[label]:.1f} s on {where}, {steps[label]:.0f} steps per "
                  f"evaluation; {int(info.infeasible.sum())} infeasible, {int(info.failed.sum())} failed, "
                  f"{int(info.unstable.sum())} unstable trials", flush=True)

    la, lb = labels
    stats = agreement_stats(outcomes[la], outcomes[lb], kinds, labels)
    print(f"\n{'rates':12s} {'n':>4s}  " + "  ".join(f"{label:^22s}" for label in labels))
    print(f"{'':12s} {'':4s}  " + "  ".join(f"{'grasp':>5s} {'trials':>6s} {'S':>4s} {'R':>4s}" for _ in labels))
    for kind, rates in stats["rates"].items():
        n_kind = len(kinds) if kind == "all" else counts[kind]
        print(f"{kind:12s} {n_kind:4d}  " + "  ".join(
            f"{r['grasp']:5.2f} {r['trials']:6.2f} {r['S']:4.2f} {r['R']:4.2f}" for r in rates.values()))
    print(f"\n{'trial':>8s} " + " ".join(f"{n:>5s}" for n in TRIAL_NAMES))
    print(f"{'agree':>8s} " + " ".join(f"{a:5.3f}" for a in stats["agreement_per_trial_kind"].values()))
    print("agreement per finger kind: " + ", ".join(f"{k} {a:.3f}" for k, a in stats["agreement_per_kind"].items()))
    both_held = agreement_report(outcomes[la], outcomes[lb])["per_trial_both_held"]
    if both_held is not None:
        print(f"{'held':>8s} " + " ".join(f"{a:5.3f}" for a in both_held) + "   (triples both sides held)")
    for label in labels:
        print(f"{'success':>8s} " + " ".join(f"{a:5.3f}" for a in outcomes[label].mean(0)) + f"   {label}")
    print(f"agreement {stats['agreement_per_trial']:.4f} over {outcomes[la].size} trials; whole vectors "
          f"{stats['agreement_vectors']:.3f}")
    (nn, nh), (hn, hh) = stats["grasp_confusion"]
    print(f"grasp: both hold {hh}, only {la} {hn}, only {lb} {nh}, neither {nn}")
    gap = stats["rate_gap_max"]
    print(f"largest gap over finger kinds: grasp success {gap['grasp']:.1f} points, trials passed / 11 "
          f"{gap['trials']:.1f} points")

    differing = [dict(index=int(i), object=triples[i]["name"], kind=triples[i]["kind"],
                      outcomes={label: outcomes[label][i].tolist() for label in labels})
                 for i in np.nonzero((outcomes[la] != outcomes[lb]).any(1))[0]]
    print(f"\n{len(differing)} differing triples" + (f", the first {SHOWN_DIFFERING}:" if differing else ""))
    for d in differing[:SHOWN_DIFFERING]:
        print(f"  #{d['index']:4d} {d['kind']:9s} {d['object']:28s} " + "  ".join(
            f"{label} {vector_text(v)}" for label, v in d["outcomes"].items()))
    if args.render and differing:
        try:
            render_differing(triples, differing[:args.render], presets, args.out)
        except Exception as exc:  # noqa: BLE001 - a drawing is optional; the figures above stand
            print(f"rendering skipped: {type(exc).__name__}: {exc}")

    if args.json:
        result = dict(n=len(triples), presets=list(labels), backends=list(args.backends),
                      hull_vertices=args.hull_vertices, object_method=args.object_method,
                      config=args.config, seed=args.seed, source=source,
                      kinds=counts, **stats, object_meshing_s=meshing, steps_per_eval=steps,
                      seconds=seconds, threads=args.threads, per_trial_both_held=both_held,
                      judged_runs=judged_runs, triples=args.triples, differing=differing)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
