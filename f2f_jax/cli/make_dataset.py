"""Simulate the pretraining grasp dataset (imprint, WSG50, cut-from-shape and, with
``--perturbed-pairs``, perturbed imprint finger pairs).

    python experiments/make_dataset.py --objects builtin --n 64 --out runs/dataset
    python experiments/make_dataset.py ... --executor ray [--ray-address HOST:PORT]   # a cluster

Kill it at any moment and rerun the same command: it continues where it stopped (``OUT/dataset.json``
keeps the settings; a rerun with other ones is refused, naming the flags that go on with it).  With
``--executor ray`` the simulation runs in Ray tasks and this process alone writes the store.
"""

import argparse
import json
import sys
from pathlib import Path

from f2f_jax import config
from f2f_jax.cli import sim_options
from f2f_jax.data import load_or_make_objects
from f2f_jax.dataset.pretraining import PERTURB_AMPLITUDE, build_grasp_dataset
from f2f_jax.dataset.store import GraspStore
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path

RECORD = "dataset.json"  # the settings a dataset directory's rows were made with
FLAGS = {"config": "--config", "seed": "--seed", "sim_preset": "--sim-preset", "cut_pairs": "--cut-pairs",
         "perturbed_pairs": "--perturbed-pairs", "backend": "--backend"}


def check_record(out: Path, record: dict) -> None:
    """Refuse to add rows to ``out`` made with other settings than its ``dataset.json`` records
    (the finger pairs of an object depend on all of them: a mixed store would hold some objects'
    pairs of one kind and others' of another); name the flags that resume it."""
    path = out / RECORD
    if not path.exists():
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise F2FError(f"{path}: unreadable ({exc}); move it away to start the dataset again") from exc
    peak = old.get("perturbed_peak", PERTURB_AMPLITUDE)  # a flag up to commit dd4f091
    if peak != PERTURB_AMPLITUDE:
        raise F2FError(f"{out} holds perturbed pairs of peak {peak}, which this version no longer makes "
                       f"(only {PERTURB_AMPLITUDE}); make it with f2f_jax at commit dd4f091, or choose "
                       "another --out (nothing was changed)")
    differ = [k for k in FLAGS if k in old and old[k] != record[k]]
    if differ:
        resume = " ".join(f"{FLAGS[k]} {old[k]}" for k in differ)
        raise F2FError(f"{out} holds a dataset made with {resume}; this run asks for "
                       + " ".join(f"{FLAGS[k]} {record[k]}" for k in differ)
                       + f". Rerun with {resume} to go on with it, or choose another --out (nothing was changed)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", default="builtin", help="builtin | pybullet | a mesh directory")
    p.add_argument("--n", type=int, default=64, help="number of objects (builtin: generated)")
    p.add_argument("--out", default="runs/dataset", help="run directory (objects + store)")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sim-preset", default=None, choices=["fast", "reference"],
                   help="simulation preset (config.SIM_PRESETS): fast (default) or reference (coacd "
                        "objects, every phase at full length)")
    p.add_argument("--cut-pairs", type=int, default=2, help="pairs cut from other shapes per object")
    p.add_argument("--perturbed-pairs", type=int, default=None,
                   help="perturbed imprint pairs per object (one object's designs that differ a little; "
                        "default: the config's train.perturbed_pairs)")
    p.add_argument("--batch", type=int, default=None,
                   help="objects per stored chunk (default 8; with --executor ray, 2 per cluster "
                        "CPU, at least 8, so every CPU has work)")
    p.add_argument("--backend", default="mujoco", choices=list(config.BACKENDS))
    sim_options.add_cli_arguments(p)
    args = p.parse_args(argv)
    if args.n <= 0:
        p.error("--n must be positive")
    if args.batch is not None and args.batch <= 0:
        p.error("--batch must be positive")
    if args.cut_pairs < 0 or (args.perturbed_pairs is not None and args.perturbed_pairs < 0):
        p.error("--cut-pairs and --perturbed-pairs must be >= 0")
    if problem := sim_options.backend_problem(args, args.backend):
        p.error(problem)
    try:
        executor = sim_options.executor_from_cli(args)
    except F2FError as exc:  # the extra missing, or no cluster at --ray-address
        p.error(str(exc))
    cfg = config.get(args.config)
    if args.sim_preset is not None:
        cfg = config.with_sim_preset(cfg, args.sim_preset)
    out = Path(args.out)
    n_perturbed = cfg.train.perturbed_pairs if args.perturbed_pairs is None else args.perturbed_pairs
    record = {"config": args.config, "seed": args.seed, "sim_preset": config.sim_preset_name(cfg),
              "cut_pairs": args.cut_pairs, "perturbed_pairs": n_perturbed, "backend": args.backend}
    try:
        check_record(out, record)
    except F2FError as exc:
        p.error(str(exc))
    tsdfs, names = load_or_make_objects(args.objects, args.n, args.seed, out / "objects", cfg.geometry)
    store = GraspStore(out / "store")
    store.clean_temporary()
    with atomic_path(out / RECORD) as tmp:
        tmp.write_text(json.dumps(record, indent=1))
    summary = build_grasp_dataset(tsdfs, names, store, cfg=cfg, seed=args.seed, batch_objects=args.batch,
                                  n_cut=args.cut_pairs, n_perturbed=n_perturbed, backend=args.backend,
                                  executor=executor)
    print(json.dumps({"rows": len(store), "this_run": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
