"""MJX batched grasp throughput against plain MuJoCo, in one run.

    python benchmarks/mjx_throughput.py --triples triples.npz --sizes 64 256 1024 4096

Triples (object hulls and finger volumes) come from ``--triples`` (made by ``--make N``, which
runs coacd: minutes) so an accelerator's time goes to its time simulating.  Candidates are the
triples tiled up to each batch size.  Printed per batch size: compile seconds of the grasp
program (apart), steady grasp trials/s and environment steps/s; then full 11-trial evaluations/s
of MJX at the largest size and of plain MuJoCo on ``--cpu-threads`` threads, and their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from f2f_jax import config
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import Hulls
from f2f_jax.sim import mjx_batch, mjx_collision
from f2f_jax.sim.protocol import run_trials
from f2f_jax.sim.scene import build_model


def make_triples(path: Path, n: int, seed: int, cfg) -> None:
    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf
    from f2f_jax.geometry.coacd_pieces import object_hulls

    rows = {k: [] for k in ("ohv", "ohc", "left", "right")}
    for mesh in builtin_objects(n, seed=seed):
        o = mesh_to_tsdf(mesh, cfg.geometry)
        h = object_hulls(o, cfg)
        left, right = imprint_fingers(o, cfg.geometry)
        for k, v in zip(rows, (h.vertices, h.counts, left, right)):
            rows[k].append(v)
    np.savez_compressed(path, **{k: np.stack(v) for k, v in rows.items()})


def load_mujoco_models(path: Path, cfg):
    data = np.load(path)
    models = []
    for v, c, left, right in zip(data["ohv"], data["ohc"], data["left"], data["right"]):
        models.append(build_model(Hulls(v, c), finger_hulls(left, cfg), finger_hulls(right, cfg), cfg,
                                  pad_collides=True, max_geom_pairs=mjx_collision.MAX_GEOM_PAIRS,
                                  max_contact_points=mjx_collision.MAX_CONTACT_POINTS))
    return models


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--triples", type=Path, required=True)
    p.add_argument("--make", type=int, default=0, help="first make this many triples (coacd, slow)")
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 1024])
    p.add_argument("--full", type=int, default=None, help="batch for the full 11-trial run (default: largest size)")
    p.add_argument("--cpu-threads", type=int, default=2)
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    cfg = config.get(args.config)
    if args.make:
        make_triples(args.triples, args.make, 1, cfg)
    dev = jax.local_devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}) x{jax.local_device_count()}; jax {jax.__version__}; "
          f"config {args.config}", flush=True)
    t = time.perf_counter()
    models = load_mujoco_models(args.triples, cfg)
    print(f"{len(models)} distinct triples built in {time.perf_counter() - t:.1f} s", flush=True)
    sim = mjx_batch.simulator_for(models[0], cfg)
    t = time.perf_counter()
    base = sim.batch(models)
    print(f"convex data for the batch: {time.perf_counter() - t:.1f} s", flush=True)
    steps_grasp = sim.n_settle + sim.n_close + len(sim.lift_ctrl) + sim.n_hold
    rows = []
    print(f"\n{'batch':>6s} {'compile s':>10s} {'grasp s':>8s} {'grasps/s':>9s} {'env steps/s':>12s} {'held':>5s}")
    for size in args.sizes:
        idx = np.arange(size) % len(models)
        b = base.take(idx)
        yaw = np.zeros(size, np.float32)
        before = sim.compile_seconds
        out = sim._call("grasp", size, b.fields, b.convex, b.planes, yaw)
        compile_s = sim.compile_seconds - before
        t = time.perf_counter()
        out = sim._call("grasp", size, b.fields, b.convex, b.planes, yaw)
        sec = time.perf_counter() - t
        row = dict(batch=size, compile_s=compile_s, seconds=sec, grasps_per_s=size / sec,
                   env_steps_per_s=size * steps_grasp / sec, held=float(np.mean(np.asarray(out[0]))))
        rows.append(row)
        print(f"{size:6d} {compile_s:10.1f} {sec:8.2f} {row['grasps_per_s']:9.1f} "
              f"{row['env_steps_per_s']:12.0f} {row['held']:5.2f}", flush=True)
    full = args.full or max(args.sizes)
    b = base.take(np.arange(full) % len(models))
    sim.run(b, chunk=full)  # compiles what the sizes above did not (pushes, turned grasps)
    t = time.perf_counter()
    res = sim.run(b, chunk=full)
    mjx_sec = time.perf_counter() - t
    mjx_eps = full / mjx_sec
    # plain MuJoCo on the same triples, threads over candidates
    from concurrent.futures import ThreadPoolExecutor

    k = min(len(models), 16)
    t = time.perf_counter()
    with ThreadPoolExecutor(args.cpu_threads) as pool:
        cpu = list(pool.map(lambda m: run_trials(m, cfg), models[:k]))
    cpu_sec = time.perf_counter() - t
    cpu_eps = k / cpu_sec
    agree = np.mean([np.array_equal(c.outcome, res["outcome"][i]) for i, c in enumerate(cpu)])
    trial_agree = np.mean([(c.outcome == res["outcome"][i]).mean() for i, c in enumerate(cpu)])
    print(f"\nfull 11-trial evaluations: MJX batch {full}: {mjx_eps:.1f}/s ({mjx_sec:.1f} s); "
          f"plain MuJoCo {args.cpu_threads} threads: {cpu_eps:.2f}/s; ratio {mjx_eps / cpu_eps:.1f}x")
    print(f"agreement MJX vs MuJoCo on {k} triples: per trial {trial_agree:.3f}, whole vectors {agree:.2f}")
    print(f"MJX compile total {sim.compile_seconds:.1f} s; grasp held rate {res['outcome'][:, 0].mean():.2f}")
    result = dict(device=dev.device_kind, platform=dev.platform, sizes=rows, mjx_evals_per_s=mjx_eps,
                  mjx_compile_s=sim.compile_seconds, mujoco_evals_per_s=cpu_eps,
                  mujoco_threads=args.cpu_threads, ratio_mjx_vs_mujoco=mjx_eps / cpu_eps,
                  agreement=float(trial_agree), full_batch=full, cores=os.cpu_count())
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
