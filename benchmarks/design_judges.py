"""Each mode of ``design()`` judged by two simulators: MuJoCo, by which the verified pool picks, and
the PyBullet peer with Bullet's step split in 4 (an independent judge: a pick chosen by MuJoCo
can win only in MuJoCo).

    python benchmarks/design_judges.py --run-dir runs/cotrain --fresh 48 --seed 7 --out runs/judges
    python benchmarks/design_judges.py --fresh 8 --out /tmp/judges     # the shipped weights, 8 objects
    python benchmarks/design_judges.py --run-dir runs/teacher --fresh 48 --seed 7 --out runs/judges-teacher \
        --nets teacher=runs/teacher control=runs/teacher-control ImpGN=runs/teacher/pretrained
                                      # several generators' own designs, each against the others

Objects: the run's held-out objects (``--run-dir``) and ``--fresh N`` new built-in objects of
``--seed``.  Nets: the run's newest checkpoint, else the weights the package ships.  Modes:

- ``Imprint``: the object's imprint pair (no net);
- ``net``: ``design(obj, candidates=1, verify=False)``, the generator's own design;
- ``net 16``: 16 candidates ranked by the fitness net, ``verify=False``;
- ``default``: ``design(obj)``, 16 candidates + the imprint pair and two variants, the best
  simulated in MuJoCo.

``--nets NAME=DIR ...`` judges, instead of those modes, the own design (``net``) of each run's or
checkpoint's generator, named NAME, and prints each one minus every later one, paired.

Every pair is simulated by our ``fast`` preset (for ``default`` that is the outcome that chose
it) and by the PyBullet peer (``numSubSteps`` 4, 1/960 s, the original's protocol otherwise) on the
same coacd object pieces and height-map finger hulls, in ``--workers`` processes.  Printed per
judge and mode: trials of 11, grasp success, and each mode minus Imprint, paired over the objects
with a 95% bootstrap interval.  Each mode's designs and each judge's outcomes are saved in
``--out`` as they finish: rerun the same command after a kill and only what was left runs.
Needs the ``pybullet`` extra.

    python benchmarks/design_judges.py --pool runs/judges1 runs/judges2

pools the saved outcomes of several ``--out`` folders (different objects, the same names): the
designs both judges hold in every folder, their objects put together, printed as above.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

MODES = {
    "net": dict(candidates=1, verify=False),
    "net 16": dict(candidates=16, verify=False),
    "default": dict(),
}
JUDGES = ("mujoco", "pybullet")


def _objects(args, g):
    from f2f_jax.data import builtin_objects
    from f2f_jax.data.object_set import held_out_objects
    from f2f_jax.geometry import mesh_to_tsdf

    objs, names = [], []
    if args.run_dir:
        held, held_names = held_out_objects(args.run_dir, g)
        objs += list(held)
        names += list(held_names)
    if args.fresh:
        meshes = builtin_objects(args.fresh, seed=args.seed)
        objs += [mesh_to_tsdf(m, g) for m in meshes]
        names += [f"fresh/{m.metadata.get('name', i)}" for i, m in enumerate(meshes)]
    if not objs:
        raise SystemExit("design_judges: no objects: give --run-dir and/or --fresh N")
    return np.stack(objs).astype(np.float32), names


def _nets(run_dir):
    if run_dir:
        from f2f_jax.train.checkpoint import load_trained_nets

        return load_trained_nets(run_dir)
    from f2f_jax.train.weights import load_weights

    return load_weights()


def _saved(path: Path, fn):
    """np.load of ``path`` when a finished step left it there, else ``fn()`` saved there."""
    if path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    out = fn()
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **out)
    os.replace(tmp, path)
    return out


def _judge_file(folder: Path, judge: str, mode: str) -> Path:
    """Where ``--out`` keeps one judge's outcomes of one mode or net."""
    return folder / f"judge-{judge}-{mode.replace(' ', '_')}.npz"


def judge_tables(results: dict, modes: list[str], nets: list[str]) -> dict:
    """Print, and return as ``{"judges": ..., "paired": ...}``, each judge's trials of 11, grasp
    success and gain over Imprint per mode (``results[(judge, mode)]``: outcomes [objects, 11]),
    and each net in ``nets`` minus every later one, paired over the objects (95% bootstrap)."""
    from f2f_jax.tables.stats import paired_gain

    n = len(results[(JUDGES[0], "Imprint")])
    out = {"judges": {}}
    print(f"\n{n} objects; trials of 11 (grasp %); minus Imprint: trials of 11, paired, 95% "
          "bootstrap interval")
    print(f"| mode | {' | '.join(f'{j}: trials (grasp) | {j}: minus Imprint' for j in JUDGES)} |")
    print("|---|" + "---|---|" * len(JUDGES))
    for mode in modes:
        cells = []
        for j in JUDGES:
            a, b = results[(j, mode)], results[(j, "Imprint")]
            g = paired_gain(a[:, None], b[:, None])["trials_own"]
            out["judges"].setdefault(j, {})[mode] = dict(
                trials=float(a.sum(1).mean()), grasp=float(a[:, 0].mean()), minus_imprint=g)
            cells.append(f"{a.sum(1).mean():.2f} ({100 * a[:, 0].mean():.0f})")
            cells.append("–" if mode == "Imprint" else
                         f"{g['diff']:+.2f} [{g['ci_low']:+.2f}, {g['ci_high']:+.2f}]")
        print(f"| {mode} | " + " | ".join(cells) + " |")
    if len(nets) > 1:
        print("\nown designs, paired: trials of 11, 95% bootstrap interval")
        for i, a in enumerate(nets):
            for b in nets[i + 1:]:
                cells = []
                for j in JUDGES:
                    g = paired_gain(results[(j, a)][:, None], results[(j, b)][:, None])["trials_own"]
                    out.setdefault("paired", {}).setdefault(j, {})[f"{a} minus {b}"] = g
                    cells.append(f"{j} {g['diff']:+.2f} [{g['ci_low']:+.2f}, {g['ci_high']:+.2f}] "
                                 f"(better {g['better']}, worse {g['worse']})")
                print(f"{a} minus {b}: " + "; ".join(cells))
    return out


def pool_main(folders: list[str]) -> dict:
    """``--pool``: the outcomes saved in several ``--out`` folders, objects put together, for the
    designs that both judges hold in every folder (in the first folder's order); printed, and
    returned as ``judge_tables`` returns them."""
    dirs = [Path(f) for f in folders]
    missing = [str(d) for d in dirs if not (d / "judges.json").is_file()]
    if len(dirs) < 2 or missing:
        raise SystemExit("design_judges --pool: give two or more finished --out folders (with judges.json)"
                         + (f"; none in {', '.join(missing)}" if missing else ""))

    held = [json.loads((d / "judges.json").read_text())["judges"] for d in dirs]
    names = [m for m in held[0][JUDGES[0]] if all(m in h[j] for h in held for j in JUDGES)]
    if "Imprint" not in names:
        raise SystemExit("design_judges --pool: the folders share no Imprint outcomes")
    parts = {}
    for j in JUDGES:
        for m in names:
            for d in dirs:
                with np.load(_judge_file(d, j, m)) as z:
                    parts.setdefault((j, m), []).append(z["outcome"].astype(np.uint8))
    results = {k: np.concatenate(v) for k, v in parts.items()}
    sizes = [len(o) for o in parts[(JUDGES[0], "Imprint")]]
    print(f"pooled: {', '.join(f'{d} ({k} objects)' for d, k in zip(folders, sizes))}")
    nets = [m for m in names if m != "Imprint" and m not in MODES]
    return judge_tables(results, names, nets)


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--pool"]:
        pool_main(argv[1:])
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", default=None, help="a run: its held-out objects and newest checkpoint")
    p.add_argument("--fresh", type=int, default=0, help="new built-in objects of --seed")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--modes", nargs="+", default=None, choices=list(MODES),
                   help="design() modes to judge (default: all of them, or none with --nets)")
    p.add_argument("--nets", nargs="+", default=[], metavar="NAME=DIR",
                   help="generators (a run, or its pretrained/) whose own designs are judged")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--out", required=True, help="folder for the designs, outcomes and judges.json")
    args = p.parse_args(argv)
    if args.fresh < 0 or args.workers < 1:
        p.error("--fresh must be >= 0 and --workers >= 1")
    named = {}
    for item in args.nets:
        name, sep, path = item.partition("=")
        if not sep or not name or not Path(path).is_dir() or name in named or name in MODES:
            p.error(f"--nets takes NAME=DIR with a new name and an existing directory, got {item!r}")
        named[name] = path
    modes = args.modes if args.modes is not None else ([] if named else list(MODES))
    try:
        import pybullet  # noqa: F401
    except ImportError:
        p.error("the PyBullet judge needs the pybullet extra: pip install -e '.[pybullet]'")

    from f2f_jax import config, sim
    from f2f_jax.bench.pybullet_runs import JUDGE_SUBSTEPS, judge_designs
    from f2f_jax import designer as design_module
    from f2f_jax.geometry import imprint_fingers
    from f2f_jax.geometry.pieces import object_pieces_many
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    nets = _nets(args.run_dir)
    cfg = config.with_sim_preset(nets.config, "fast")
    objs, names = _objects(args, cfg.geometry)
    t0 = time.perf_counter()
    pieces = object_pieces_many(list(objs), cfg, workers=args.workers, progress=True)
    bad = [n for n, h in zip(names, pieces) if isinstance(h, str)]
    if bad:
        raise SystemExit(f"design_judges: no pieces for {bad}")
    held = f"{args.run_dir}'s held-out + " if args.run_dir else ""
    print(f"{len(objs)} objects ({held}{args.fresh} fresh of seed {args.seed}); pieces in "
          f"{time.perf_counter() - t0:.0f} s; nets: {nets.source}", flush=True)

    def imprint():
        pairs = [imprint_fingers(o, cfg.geometry) for o in objs]
        return dict(left=np.stack([a for a, _ in pairs]), right=np.stack([b for _, b in pairs]))

    def designed(mode, params=nets):
        def fn():
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", design_module.InfeasibleDesignWarning)
                pairs = design_module.design(objs, params=params, **MODES.get(mode, MODES["net"]))
            return dict(left=np.stack([q.left for q in pairs]), right=np.stack([q.right for q in pairs]),
                        origin=np.array([q.origin for q in pairs]),
                        seconds=np.float64(time.perf_counter() - t))
        return fn

    designs = {"Imprint": _saved(out / "design-Imprint.npz", imprint)}
    for mode in modes:
        designs[mode] = _saved(out / f"design-{mode.replace(' ', '_')}.npz", designed(mode))
        print(f"designed: {mode} ({float(designs[mode]['seconds']):.0f} s)", flush=True)
    for name, path in named.items():
        from f2f_jax.train.checkpoint import load_trained_nets

        designs[name] = _saved(out / f"design-net-{name.replace(' ', '_')}.npz",
                               designed(name, load_trained_nets(path)))
        print(f"designed: {name}, the own design of {path} ({float(designs[name]['seconds']):.0f} s)",
              flush=True)

    def judge(name, d):
        def fn():
            t = time.perf_counter()
            if name == "mujoco":
                res = sim.evaluate(objs, d["left"], d["right"], cfg=cfg, threads=args.workers,
                                   object_hulls=pieces, progress=True)
            else:
                res = judge_designs(pieces, d["left"], d["right"], cfg, args.workers)
            return dict(outcome=np.asarray(res, np.uint8), seconds=np.float64(time.perf_counter() - t))
        return fn

    results = {}
    for j in JUDGES:
        for mode, d in designs.items():
            r = _saved(_judge_file(out, j, mode), judge(j, d))
            results[(j, mode)] = r["outcome"].astype(np.uint8)
            print(f"judged: {j} {mode} ({float(r['seconds']):.0f} s)", flush=True)

    summary = {"objects": len(objs), "run_dir": args.run_dir, "fresh": args.fresh, "seed": args.seed,
               "nets": nets.source, "peer_substeps": JUDGE_SUBSTEPS,
               **judge_tables(results, list(designs), list(named))}
    summary["nets_judged"] = named
    origins = {m: dict(zip(*np.unique(designs[m]["origin"], return_counts=True)))
               for m in designs if "origin" in designs[m]}
    summary["origins"] = {m: {str(k): int(v) for k, v in o.items()} for m, o in origins.items()}
    print("picks by origin: " + "; ".join(f"{m}: " + ", ".join(f"{k} {v}" for k, v in o.items())
                                          for m, o in summary["origins"].items()))
    (out / "judges.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    print(f"wrote {out / 'judges.json'}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    sys.exit(main())
