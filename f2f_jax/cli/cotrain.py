"""Fit2Form end to end: objects, grasp dataset, pretraining, then co-training cycles.

    python experiments/cotrain.py --cycles 20                  # CPU-sized default, built-in objects
    python experiments/cotrain.py --config paper --objects ~/shapenet --run-dir runs/paper
    python experiments/cotrain.py --cycles 20 --objectives GS --from-pretrained runs/cotrain \
        --run-dir runs/cotrain-GS                                # an ablation on the same pretraining
    python experiments/cotrain.py --cycles 20 --export f2f_jax/weights/default
                                                # the model the package ships, rebuilt
    python experiments/cotrain.py --cycles 20 --executor ray   # simulation on a Ray cluster
    python experiments/cotrain.py --cycles 20 --config workstation --xla-threads 0 --run-dir runs/ws
                                                # 100x the simulations: a many-core machine

Kill it at any moment and rerun the same command: it resumes from the last complete checkpoint
(and the grasp store keeps every finished simulation).  The run directory holds the object set,
the extra imprint objects (imprint_objects/), the store, checkpoints, log.jsonl, curves.png and
summary.json.  It ends by printing the held-out grasp success of the generator after cycle 0 and
after the last cycle beside the imprint and WSG50 baselines.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from f2f_jax import config, run_plan  # no JAX here: the XLA flags set in main still take effect
from f2f_jax.cli import reproducible, sim_options
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.data.sources import mesh_files
from f2f_jax.errors import F2FError
from f2f_jax.cli import overrides


def _default_backend() -> str:
    import jax  # after the XLA flags

    return "mjx" if jax.default_backend() in ("gpu", "tpu") else "mujoco"


def _table(summary: dict) -> str:
    lines = ["| designer (held-out objects: %d) | grasp | S avg | R avg |" % summary["held_out_objects"],
             "|---|---|---|---|"]
    for name, s in summary["success"].items():
        if s is None:
            continue
        g = s[0]
        sa = sum(s[1:5]) / 4
        ra = sum(s[5:]) / (len(TRIAL_NAMES) - 5)
        lines.append(f"| {name} | {g:.3f} | {sa:.3f} | {ra:.3f} |")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cycles", type=int, default=None, help="co-training cycles (default: the config's)")
    p.add_argument("--config", default="default",
                   help="tiny | default (CPU, 2 cores) | workstation (the default's nets on 100x its "
                        "simulations: many cores, a cluster or --backend warp) | paper (GPU sizes)")
    p.add_argument("--objects", default="builtin",
                   help="builtin (procedural, no download) | pybullet | a directory of meshes")
    p.add_argument("--n-objects", type=int, default=None, help="built-in objects to make (default: config)")
    p.add_argument("--run-dir", default="runs/cotrain")
    p.add_argument("--backend", choices=list(config.BACKENDS), default=None,
                   help="simulator (default: mjx on an accelerator, mujoco on a CPU)")
    p.add_argument("--objectives", choices=["GS", "GS+R", "GS+S", "full"], default=None,
                   help="fitness outputs the generator maximises (Table 1 ablations)")
    p.add_argument("--from-pretrained", metavar="RUN_DIR", default=None,
                   help="start the cycles from another run's pretraining (objects, dataset, models); "
                        "only co-training settings (--objectives, train.cycle_candidates, ...) may differ")
    p.add_argument("--sim-preset", default=None, choices=["fast", "reference"],
                   help="simulation preset (config.SIM_PRESETS): fast (default) or reference (coacd "
                        "objects, every phase at full length)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="any config field, after the flags above (repeatable), e.g. "
                        "--set train.generator_lr=3e-4 --set sim.timestep=0.002; recorded in the "
                        "run directory's run.json, which a resumed run must match")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--export", metavar="PATH", default=None,
                   help="when the run ends, write its nets as PATH.npz with PATH.json (config, seed, "
                        "objects, held-out table, commit): the file design() loads; "
                        "f2f_jax/weights/default is the model the package ships")
    reproducible.add_cli_argument(p)
    sim_options.add_cli_arguments(p)
    return p


def _run_config(args):
    """The run's Config from the flags (--config, then the train flags, then every --set), and the
    object source resolved; raises ValueError with the message for a bad flag."""
    if args.config not in config.CONFIGS:
        raise ValueError(f"unknown --config {args.config!r}; choose one of {', '.join(config.CONFIGS)}")
    if args.cycles is not None and args.cycles < 1:
        raise ValueError(f"--cycles must be at least 1, got {args.cycles}")
    if args.objects not in ("builtin", "pybullet"):
        d = Path(args.objects).expanduser()
        if not d.is_dir():
            raise ValueError(f"--objects {args.objects}: no such directory")
        if not mesh_files(d):
            raise ValueError(f"--objects {args.objects}: no mesh files (.obj/.stl/.ply/.off/.glb) in it")
        args.objects = str(d.resolve())
    cfg = config.get(args.config)
    if args.sim_preset is not None:
        cfg = config.with_sim_preset(cfg, args.sim_preset)
    changes = {}
    if args.n_objects is not None:
        if args.objects != "builtin":
            raise ValueError("--n-objects applies to the built-in objects only (a directory is used whole)")
        if args.n_objects < 4:
            raise ValueError("--n-objects must be at least 4")
        changes["n_objects"] = args.n_objects
    if args.objectives is not None:
        changes["objectives"] = args.objectives
    if args.seed is not None:
        if args.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
        changes["seed"] = args.seed
    if args.cycles is not None:
        changes["cycles"] = args.cycles
    if changes:
        cfg = cfg.replace(train=dataclasses.replace(cfg.train, **changes))
    return overrides.override(cfg, args.set)


def _plan(cfg, config_name: str, memory: int | None) -> tuple[str, str | None]:
    """What a run on built-in objects will simulate and hold (``run_plan.planned_simulations``), and
    a warning when its rows would fill over 80% of ``memory`` bytes (None: unknown)."""
    plan, rows = run_plan.planned_simulations(cfg), run_plan.planned_row_bytes(cfg)
    text = (f"cotrain: {config_name} on {cfg.train.n_objects} built-in objects simulates about "
            f"{plan['total']:,} grasp evaluations (dataset {plan['dataset']:,}, cycles {plan['cycles']:,}, "
            f"held-out {plan['baselines'] + plan['heldout']:,}); its grasp rows take {rows / 2**30:.1f} GiB "
            "of memory by the last cycle")
    warning = None
    if memory and rows > 0.8 * memory:
        warning = (f"cotrain: warning: that is over 80% of this machine's {memory / 2**30:.0f} GiB: the run "
                   "would run out of memory in its later cycles (lower train.cycle_candidates or "
                   "train.objects_per_cycle with --set, or use a larger machine)")
    return text, warning


def _machine_memory() -> int | None:
    """This machine's physical memory in bytes, or None where the OS does not say."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def main(argv=None) -> int:
    args = _parser().parse_args(argv)

    def fail(msg: str) -> int:
        print(f"cotrain: error: {msg}", file=sys.stderr)
        return 2

    if args.xla_threads < 0:
        return fail(f"--xla-threads must be >= 0, got {args.xla_threads}")
    reproducible.reproducible_xla(args.xla_threads)  # before JAX starts: same numbers everywhere

    try:
        cfg = _run_config(args)
    except ValueError as exc:
        return fail(str(exc))

    from f2f_jax.train.cotrain import CoTrainRun  # JAX: imported after the XLA flags are set

    if args.objects == "builtin":
        plan, warning = _plan(cfg, args.config, _machine_memory())
        if not args.quiet:
            print(plan, flush=True)
        if warning:
            print(warning, file=sys.stderr, flush=True)

    if problem := sim_options.backend_problem(args, args.backend):
        return fail(problem)
    backend = "mujoco" if args.executor == "ray" else args.backend or _default_backend()
    try:
        executor = sim_options.executor_from_cli(args)
        # an existing run goes on with its own simulator unless --sim-preset says otherwise
        settings = dict(config_name=args.config, objects=args.objects, backend=backend,
                        progress=not args.quiet, executor=executor,
                        keep_simulator=args.sim_preset is None and not any(
                            a.startswith(("sim.", "geometry.")) for a in args.set))
        if args.from_pretrained:  # a new run directory is made from the source's pretraining
            run = CoTrainRun.from_pretrained(args.run_dir, args.from_pretrained, cfg, **settings)
        else:
            run = CoTrainRun(args.run_dir, cfg, **settings)
        summary = run.run(cfg.train.cycles)
    except (F2FError, ValueError) as exc:  # ValueError: an object set made from other settings
        return fail(str(exc))
    print(_table(summary))
    print(f"AE held-out IoU: {summary['ae_heldout_iou']:.3f}; curves: {Path(args.run_dir) / 'curves.png'}")
    out = {"summary": str(Path(args.run_dir) / "summary.json")}
    if args.export:
        from f2f_jax.train.weights import export_run

        argv_text = " ".join(sys.argv[1:] if argv is None else argv)
        npz, meta = export_run(args.run_dir, args.export,
                               command=f"python experiments/cotrain.py {argv_text}")
        print(f"weights: {npz} ({npz.stat().st_size / 2**20:.1f} MB) and {meta}")
        out["weights"] = str(npz)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
