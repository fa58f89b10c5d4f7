"""Do the simulator-as-teacher's targets hold when their fingers are printed?

    python research/teacher_retest.py --run-dir runs/teacher0 --tolerance 0.3 --copies 4 --json OUT.json

A teacher run (``cotrain.py --config teacher``) regresses its generator onto each teacher object's
best-simulated pair, where that pair passes strictly more trials than the object's imprint.  The
best of several designs, each simulated once, is partly luck: one trial turns on tenths of a
millimetre of finger (``research/sim_retest.py --perturb heights``).  Here every object whose target
beat its imprint (over the cycles up to ``--cycle``, default the last simulated) has both pairs
simulated again: once exactly (from the store's float16 volumes, which reproduce most but not all
of the stored outcomes: the designs were simulated at float32) and on ``--copies`` moved copies,
both fingers' height maps moved by a smooth field of ``--tolerance`` mm, one field per object, copy
and side shared by the target and the imprint (``design_pool.printed_copies``: paired, as
``design(tolerance=)`` compares candidates).

Printed: the targets' and imprints' trials of 11 exactly and over the moved copies, the paired
gain of target over imprint on the copies with a 95% bootstrap interval over objects, and how many
objects keep a lead.  A target whose lead vanishes on moved copies is one the generator was taught
from the simulator's noise.  Cost: 2 x (1 + copies) evaluations per improved object (~6 minutes for
79 objects and 4 copies on 2 cores).  ``--json`` keeps each object's trials too, so two judges'
retests of one run join object by object: ``teacher_retest.py --join MOVED.json PEER.json`` prints
the peer's gain over the targets whose lead held on the moved copies.

``--judge pybullet`` simulates the same pairs with the PyBullet peer instead (Bullet's step split
in 4, as ``benchmarks/design_judges.py`` judges; needs the ``pybullet`` extra): does a target chosen
by MuJoCo's outcomes beat its imprint under an independent simulator too?  ``--copies 0`` then
judges the exact pairs only (79 objects' 158 evaluations took 37 min on 2 cores that two other
jobs shared).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def retest_table(exact: np.ndarray, moved: np.ndarray, stored: np.ndarray, origins) -> dict:
    """The retest's figures: exact [n, 2, T] (target, imprint) re-simulated, moved [C, n, 2, T] on
    C moved copies (C may be 0), stored [n, 2, T] the store's outcomes, origins [n] the targets'
    kinds.  Trials of 11 exactly and over the copies, the paired gain of target over imprint
    exactly and on the copies (``paired_gain``'s trials_mean), the objects whose lead holds or
    turns on the copies, per origin.  Without copies the moved figures are None."""
    from f2f_jax.tables.stats import paired_gain

    trials = exact.sum(-1).astype(float)  # [n, 2]
    origins = np.asarray(origins).astype(str)
    out = {"exact_reproduced": int((exact == stored).all((1, 2)).sum()),
           "exact": {"target": float(trials[:, 0].mean()), "imprint": float(trials[:, 1].mean())},
           "exact_gain": paired_gain(exact[:, None, 0], exact[:, None, 1])["trials_mean"],
           "moved": None, "moved_gain": None, "lead_kept": None, "lead_lost": None, "by_origin": {}}
    copies = moved.sum(-1).astype(float).mean(0) if len(moved) else None  # [n, 2]
    if copies is not None:
        out.update(moved={"target": float(copies[:, 0].mean()), "imprint": float(copies[:, 1].mean())},
                   moved_gain=paired_gain(moved[:, :, 0].transpose(1, 0, 2),
                                          moved[:, :, 1].transpose(1, 0, 2))["trials_mean"],
                   lead_kept=int((copies[:, 0] > copies[:, 1]).sum()),
                   lead_lost=int((copies[:, 0] < copies[:, 1]).sum()))
    for o in sorted(set(origins)):
        m = origins == o
        out["by_origin"][o] = {"objects": int(m.sum()),
                               "exact_gain": float((trials[m, 0] - trials[m, 1]).mean()),
                               "moved_gain": None if copies is None
                               else float((copies[m, 0] - copies[m, 1]).mean())}
    return out


def join_table(moved_trials: np.ndarray, peer_trials: np.ndarray, n_boot: int = 10000,
               seed: int = 0, n_trials: int = 11) -> dict:
    """Two judges' retests of one run's targets, object by object: moved_trials [C, n, 2] (target,
    imprint) on one judge's moved copies, peer_trials [n, 2] the other judge's exact trials.  The
    second judge's gain of target over imprint (mean, 95% bootstrap interval, objects better and
    worse) over every object, over those whose lead held on the copies (the targets a teacher
    picking by the mean over moved copies would keep), over those leading there by >= 1 and
    >= 2 trials, and over those whose imprint misses a trial under the second judge."""
    from f2f_jax.tables.stats import difference_interval

    moved = np.asarray(moved_trials, float).mean(0)  # [n, 2]
    d = np.asarray(peer_trials, float) @ np.array([1.0, -1.0])
    lead = moved[:, 0] - moved[:, 1]
    rng = np.random.default_rng(seed)  # one stream over the subsets, in their order
    out = {}
    subsets = (("all", np.ones(len(d), bool)), ("lead kept on the copies", lead > 0),
               ("lead >= 1 trial on the copies", lead >= 1), ("lead >= 2 trials on the copies", lead >= 2),
               ("the peer's imprint misses a trial", np.asarray(peer_trials)[:, 1] < n_trials))
    for name, m in subsets:
        out[name] = {"objects": int(m.sum()),
                     **(difference_interval(d[m], n_boot=n_boot, rng=rng) if m.any() else {})}
    return out


def join_main(moved_json: Path, peer_json: Path) -> int:
    """``--join``: read two ``--json`` retests of one run (moved copies, then the exact peer) and
    print ``join_table``."""
    a, b = (json.loads(Path(f).read_text()) for f in (moved_json, peer_json))
    if "per_object" not in a or "per_object" not in b:
        raise SystemExit("teacher_retest --join: both files need per-object trials (made by --json)")
    a, b = a["per_object"], b["per_object"]
    if a["name"] != b["name"] or not a["moved_trials"]:
        raise SystemExit("teacher_retest --join: the first file needs moved copies, and both the same "
                         "run's targets")
    print(f"{peer_json}'s exact gain of target over imprint, trials of 11, by the lead on "
          f"{moved_json}'s copies")
    for name, v in join_table(np.array(a["moved_trials"]), np.array(b["exact_trials"])).items():
        print(f"  {name}: {v['objects']} objects" + ("" if not v["objects"] else
              f", {v['diff']:+.2f} [{v['ci_low']:+.2f}, {v['ci_high']:+.2f}] (better {v['better']}, "
              f"worse {v['worse']})"))
    return 0


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--join"]:
        if len(argv) != 3:
            raise SystemExit("usage: teacher_retest.py --join MOVED.json PEER.json")
        return join_main(Path(argv[1]), Path(argv[2]))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", required=True, type=Path, help="a run made with train.teacher=simulator")
    p.add_argument("--cycle", type=int, default=None, help="targets over cycles 1..CYCLE (default: all)")
    p.add_argument("--tolerance", type=float, default=0.3, help="printing tolerance, mm")
    p.add_argument("--copies", type=int, default=4, help="moved copies (0: exact only, --judge pybullet)")
    p.add_argument("--seed", type=int, default=0, help="the moved copies' fields")
    p.add_argument("--judge", choices=("mujoco", "pybullet"), default="mujoco",
                   help="the run's own MuJoCo config, or the PyBullet peer (4 substeps)")
    p.add_argument("--workers", type=int, default=2, help="processes (threads for MuJoCo)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    fewest = 0 if args.judge == "pybullet" else 1  # MuJoCo's exact outcomes are the store's own
    if args.copies < fewest or args.tolerance <= 0 or (args.cycle is not None and args.cycle < 1):
        p.error(f"--copies must be >= {fewest} with --judge {args.judge}, --cycle >= 1 and --tolerance > 0")
    if args.workers < 1:
        p.error("--workers must be >= 1")
    if not (args.run_dir / "run.json").exists() or not (args.run_dir / "store").is_dir():
        p.error(f"{args.run_dir} is not a run directory (no run.json or store)")
    if args.judge == "pybullet":
        try:
            import pybullet  # noqa: F401
        except ImportError:
            p.error("--judge pybullet needs the pybullet extra: pip install -e '.[pybullet]'")

    from f2f_jax import sim
    from f2f_jax.dataset.store import GraspStore
    from f2f_jax.design_pool import printed_copies
    from f2f_jax.train.run_data import read_rows
    from f2f_jax.train.run_dir import read_record
    from f2f_jax.train.teacher import IMPRINT, best_rows

    _, cfg = read_record(json.loads((args.run_dir / "run.json").read_text()), 0)
    if cfg is None:
        p.error(f"{args.run_dir}/run.json holds no readable config")
    store = GraspStore(args.run_dir / "store")
    cycles = store.read(("cycle",))["cycle"]
    cycle = (int(cycles.max()) if len(cycles) else 0) if args.cycle is None else args.cycle
    rows = read_rows(store, lambda cyc, kind: 1 <= cyc <= cycle)
    if not (rows["kind"] == IMPRINT).any():
        p.error(f"{args.run_dir} has no teacher rows in cycles 1..{cycle}: was it taught by the simulator?")
    names = sorted({str(n) for n in rows["name"]})
    best, passed, imprint = best_rows(rows, names)
    improved = np.flatnonzero((best >= 0) & (imprint >= 0) & (passed > imprint))
    at = {(str(n), str(k)): i for i, (n, k) in enumerate(zip(rows["name"], rows["kind"]))}
    imp = np.array([at[(names[o], IMPRINT)] for o in improved])
    tgt = best[improved]
    n = len(improved)
    print(f"{args.run_dir}: cycles 1..{cycle}, {len(names)} teacher objects, {n} whose target beats its "
          f"imprint; simulating 2 x (1 + {args.copies}) x {n} = {2 * (1 + args.copies) * n} evaluations "
          f"({args.judge})", flush=True)
    if n == 0:
        return 0
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    objs = f32(rows["object"][tgt])
    lefts = f32(np.stack([rows["left"][tgt], rows["left"][imp]], 1))  # [n, 2, R, R, R]: target, imprint
    rights = f32(np.stack([rows["right"][tgt], rows["right"][imp]], 1))
    t0 = time.perf_counter()
    if args.judge == "pybullet":
        from f2f_jax.bench.pybullet_runs import judge_designs
        from f2f_jax.geometry.pieces import object_pieces_many

        pieces = object_pieces_many(list(objs), cfg, workers=args.workers, progress=True)
        bad = [names[o] for o, h in zip(improved, pieces) if isinstance(h, str)]
        if bad:
            raise SystemExit(f"teacher_retest: no pieces for {bad}")
        pieces2 = [h for h in pieces for _ in range(2)]

    def run(l2, r2, what):
        l2, r2 = l2.reshape(-1, *l2.shape[2:]), r2.reshape(-1, *r2.shape[2:])
        if args.judge == "pybullet":
            out = judge_designs(pieces2, l2, r2, cfg, args.workers)
        else:
            out = sim.evaluate(np.repeat(objs, 2, 0), l2, r2, cfg=cfg, threads=args.workers, progress=True)
        print(f"simulated {what} ({time.perf_counter() - t0:.0f} s)", flush=True)
        return np.asarray(out, np.uint8).reshape(n, 2, -1)

    exact = run(lefts, rights, "exact")
    stored = np.stack([rows["outcome"][tgt], rows["outcome"][imp]], 1)
    moved = []
    for c in range(args.copies):  # one field per object, copy and side, shared by target and imprint
        ml = [printed_copies(lefts[:, j], rights[:, j], args.tolerance, cfg.geometry, 1, [args.seed, c])
              for j in range(2)]
        moved.append(run(np.stack([m[0] for m in ml], 1), np.stack([m[1] for m in ml], 1), f"copy {c + 1}"))
    moved = np.stack(moved) if moved else np.zeros((0, *exact.shape), np.uint8)  # [C, n, 2, 11]
    summary = {"run_dir": str(args.run_dir), "cycle": cycle, "teacher_objects": len(names), "improved": n,
               "judge": args.judge, "tolerance_mm": args.tolerance, "copies": args.copies, "seed": args.seed,
               **retest_table(exact, moved, stored, rows["kind"][tgt].astype(str)),
               "seconds": round(time.perf_counter() - t0, 1),
               # per object, so two judges' retests of one run can be joined object by object
               "per_object": {"name": [names[o] for o in improved],
                              "exact_trials": exact.sum(-1).tolist(),  # [n, 2]: target, imprint
                              "moved_trials": moved.sum(-1).tolist()}}  # [C, n, 2]
    gain, same, eg = summary["moved_gain"], summary["exact_reproduced"], summary["exact_gain"]
    print(f"\n{n} improved targets, judged by {args.judge}; trials of 11, target / imprint (the exact "
          f"pairs' outcomes equal the store's for {same} of {n})")
    print(f"exact: {summary['exact']['target']:.2f} / {summary['exact']['imprint']:.2f}; target minus "
          f"imprint {eg['diff']:+.2f} [{eg['ci_low']:+.2f}, {eg['ci_high']:+.2f}] (better {eg['better']}, "
          f"worse {eg['worse']})")
    if gain is not None:
        print(f"{args.copies} moved copies at {args.tolerance} mm: {summary['moved']['target']:.2f} / "
              f"{summary['moved']['imprint']:.2f}; target minus imprint {gain['diff']:+.2f} "
              f"[{gain['ci_low']:+.2f}, {gain['ci_high']:+.2f}]; lead kept on {summary['lead_kept']}, "
              f"lost on {summary['lead_lost']}")
    for o, v in summary["by_origin"].items():
        moved_txt = "" if v["moved_gain"] is None else f", moved {v['moved_gain']:+.2f}"
        print(f"  {o}: {v['objects']} objects, gain exact {v['exact_gain']:+.2f}{moved_txt}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
