"""A run directory whose pretraining is another run's data with a weights file's nets, so that
cycles (co-training, the simulator as the generator's teacher, its control) start from a trained
model such as the one the package ships.

    python experiments/cotrain.py --cycles 1 --run-dir runs/s0            # any run of the default config
    python research/start_from_weights.py --data runs/s0 --out runs/ship0   # the shipped weights
    python experiments/cotrain.py --config teacher --from-pretrained runs/ship0 --run-dir runs/teacher0
    python experiments/cotrain.py --config teacher --set train.teacher=imprint \
        --from-pretrained runs/ship0 --run-dir runs/control0

Takes from ``--data`` (a run with its objects, pretraining dataset and baselines, and at least the
shape auto-encoder's pretraining) its objects, extra imprint objects, store and record; the
generator and the fitness net are the weights file's (``--weights``, default the shipped one),
with fresh optimiser states, saved as the end of the new directory's pretraining.  The weights'
config must be the run's, and the run must have simulated nothing in cycles.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, type=Path, help="a run directory (its objects, store, record)")
    p.add_argument("--weights", default=None, help="a weights file (default: the shipped weights)")
    p.add_argument("--out", required=True, type=Path, help="the new run directory")
    args = p.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        p.error(f"{args.out} is not empty")
    for part in ("objects", "store", "run.json", "checkpoints"):
        if not (args.data / part).exists():
            p.error(f"{args.data} holds no {part}: is it a run directory past its auto-encoder's pretraining?")

    from f2f_jax.dataset.store import GraspStore
    from f2f_jax.train.checkpoint import Checkpoints, config_to_dict
    from f2f_jax.train.run_dir import differing_fields, read_record
    from f2f_jax.train.state import fresh_run_state, generator_optimizer, new_state, optimizer
    from f2f_jax.train.weights import load_weights

    old, cfg = read_record(json.loads((args.data / "run.json").read_text()), 0)
    if cfg is None:
        p.error(f"{args.data}/run.json holds no readable config")
    weights = load_weights(args.weights)
    differ = differing_fields(config_to_dict(weights.config), config_to_dict(cfg))
    if [f for f in differ if f.split(".")[0] != "train"]:
        p.error(f"the weights were trained with other nets or physics ({', '.join(differ)})")
    store = GraspStore(args.data / "store")
    if (store.read(("cycle",))["cycle"] >= 1).any():
        p.error(f"{args.data} has simulated cycles; give a run that stopped at its pretraining")
    nets, meta = Checkpoints(args.data / "checkpoints").restore_like(fresh_run_state(cfg, cfg.train.seed))
    if meta is None:
        p.error(f"{args.data} has no checkpoint")
    nets["gn"] = new_state(weights.generator, generator_optimizer(cfg))
    nets["fn"] = new_state(weights.fitness, optimizer(cfg.train))
    models = {"generator": weights.generator, "fitness": weights.fitness}
    end = {"stage": "gn", "epoch": cfg.train.gn_epochs, "cycle": 0, "store_rows": len(store),
           "config_name": old.get("config_name", "custom"), "config": config_to_dict(cfg),
           "objectives": weights.objectives, "start_weights": weights.source}
    stage = args.out.with_name(f".{args.out.name}.making")
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    for part in ("objects", "imprint_objects", "store"):
        if (args.data / part).is_dir():
            shutil.copytree(args.data / part, stage / part)
    shutil.copy2(args.data / "run.json", stage / "run.json")
    for directory in (stage / "checkpoints", stage / "pretrained" / "checkpoints"):
        Checkpoints(directory, max_to_keep=1).save(nets, models, end)
    lines = []
    for line in (args.data / "log.jsonl").read_text().splitlines() if (args.data / "log.jsonl").exists() else []:
        try:
            if json.loads(line).get("stage") in ("data", "ae"):
                lines.append(line + "\n")
        except json.JSONDecodeError:
            continue
    lines.append(json.dumps({"stage": "start_weights", "weights": weights.source, "data": str(args.data)}) + "\n")
    (stage / "log.jsonl").write_text("".join(lines))
    if args.out.exists():
        args.out.rmdir()
    stage.rename(args.out)
    print(f"{args.out}: {args.data}'s data, the nets of {weights.source}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
