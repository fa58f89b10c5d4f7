"""Training throughput per stage: samples per second of each jitted step, compile time apart.

    python benchmarks/train_throughput.py                       # CPU-sized default config
    python benchmarks/train_throughput.py --config paper --batch 32 --json out.json   # on a GPU
    python benchmarks/train_throughput.py --set "net.decoder_channels=(8, 4, 2, 1)" \
        --set "net.decoder_strides=(3, 3, 1, 1)" --set "net.decoder_kernels=()"   # the old decoder

Stages: shape VAE (ae), fitness net (fn), generator on imprint latents (gn_imprint) and generator
against the fitness net (gn_fitness: decoder + fitness forward and backward).  Inputs are built-in
object volumes and their imprint fingers, so the numbers are for real data layouts; the step is
the one the co-training run uses (``f2f_jax.train.steps``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="default")
    p.add_argument("--batch", type=int, default=None, help="batch size (default: the config's)")
    p.add_argument("--steps", type=int, default=5, help="timed steps per stage after the compile")
    p.add_argument("--stages", default="ae,fn,gn_imprint,gn_fitness")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="change one config field, as in experiments/cotrain.py (repeatable)")
    args = p.parse_args(argv)

    from f2f_jax import config
    from f2f_jax.cli import overrides
    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf
    from f2f_jax.train import steps as S
    from f2f_jax.train.state import (
        init_autoencoder,
        init_fitness,
        init_generator,
        new_state,
        optimizer,
    )

    try:
        cfg = overrides.override(config.get(args.config), args.set)
    except ValueError as e:
        p.error(str(e))
    batch = args.batch or cfg.train.fn_batch_size
    objs = np.stack([mesh_to_tsdf(m, cfg.geometry) for m in builtin_objects(min(batch, 8), seed=7)])
    objs = np.concatenate([objs] * (batch // len(objs) + 1))[:batch].astype(np.float32)
    pairs = [imprint_fingers(o, cfg.geometry) for o in objs]
    lefts = np.stack([a for a, _ in pairs]).astype(np.float32)
    rights = np.stack([b for _, b in pairs]).astype(np.float32)
    outcomes = (np.random.default_rng(0).random((batch, 11)) < 0.3).astype(np.float32)
    device = jax.devices()[0]
    print(f"device: {device.device_kind} ({jax.default_backend()}) x {jax.device_count()}; "
          f"config {args.config}; batch {batch}", flush=True)

    o, l, r, y = S.shard(objs, lefts, rights, outcomes)
    fn_vars = init_fitness(cfg, 1)
    stages = {
        "ae": lambda: (S.ae_step(cfg), new_state(init_autoencoder(cfg), optimizer(cfg.train)),
                       (o, jax.random.key(0))),
        # the fn state is donated to its step: give it a copy, gn_fitness still reads fn_vars
        "fn": lambda: (S.fn_step(cfg), new_state(jax.tree.map(jax.numpy.copy, fn_vars),
                                                 optimizer(cfg.train)), (o, l, r, y)),
        "gn_imprint": lambda: (S.gn_imprint_step(cfg),
                               new_state(init_generator(cfg, 2), S.generator_optimizer(cfg)), (o, l, r)),
        "gn_fitness": lambda: (S.gn_fitness_step(cfg),
                               new_state(init_generator(cfg, 2), S.generator_optimizer(cfg)),
                               (fn_vars, o)),
    }
    rows = []
    for name in args.stages.split(","):
        if name not in stages:
            p.error(f"unknown stage {name!r}; choose from {', '.join(stages)}")
        step, state, inputs = stages[name]()
        t0 = time.perf_counter()
        state, m = step(state, *inputs)
        jax.block_until_ready(m)
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.steps):
            state, m = step(state, *inputs)
        jax.block_until_ready(m)
        per_step = (time.perf_counter() - t0) / args.steps
        rows.append({"stage": name, "batch": batch, "compile_s": round(compile_s, 2),
                     "step_s": round(per_step, 4), "samples_per_s": round(batch / per_step, 2)})
        print(f"{name:11s} compile+first {compile_s:6.1f} s   step {per_step * 1e3:8.1f} ms   "
              f"{batch / per_step:8.1f} samples/s", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device.device_kind, "backend": jax.default_backend(),
                       "config": args.config, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
