"""Grasp-simulation throughput: full 11-trial evaluations per second, backends side by side.

    python benchmarks/sim_throughput.py                 # 64 builtin imprint triples
    python benchmarks/sim_throughput.py --n 16 --pybullet-n 8 --json out.json

Every backend gets the same triples (imprint finger pairs of builtin objects, object hulls
decomposed once beforehand and not timed).  Printed: evaluations/s, physics steps/s, and the
ratios per core measured in this one run.  The PyBullet peer (the original Fit2Form protocol,
``benchmarks/pybullet_original.py``) needs the ``pybullet`` extra; without it that column is
skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from f2f_jax import config  # noqa: E402
from f2f_jax import sim  # noqa: E402
from f2f_jax.data import builtin_objects  # noqa: E402
from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf  # noqa: E402
from f2f_jax.geometry.hulls import finger_hulls, object_hulls  # noqa: E402


def imprint_triples(n: int, seed: int, cfg):
    objs, lefts, rights = [], [], []
    for mesh in builtin_objects(n, seed=seed):
        tsdf = mesh_to_tsdf(mesh, cfg.geometry)
        left, right = imprint_fingers(tsdf, cfg.geometry)
        objs.append(tsdf), lefts.append(left), rights.append(right)
    return np.stack(objs), np.stack(lefts), np.stack(rights)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=64, help="triples for the MuJoCo backend")
    p.add_argument("--pybullet-n", type=int, default=16, help="of those, triples for the PyBullet peer")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    cfg = config.get(args.config)
    cores = os.cpu_count()
    print(f"machine: {platform.processor() or platform.machine()}, {cores} cores; "
          f"config {args.config}; {args.n} builtin imprint triples")

    t = time.perf_counter()
    objs, lefts, rights = imprint_triples(args.n, args.seed, cfg)
    hulls = [object_hulls(o, cfg) for o in objs]
    print(f"prepared volumes and object hulls in {time.perf_counter() - t:.1f} s (not timed below)")

    rows = {}
    t = time.perf_counter()
    out, info = sim.evaluate(objs, lefts, rights, backend="mujoco", cfg=cfg, threads=args.threads,
                             object_hulls=hulls, return_info=True, progress=False)
    sec = time.perf_counter() - t
    rows["mujoco"] = dict(evals=len(objs), seconds=sec, steps=info.total_steps, workers=args.threads,
                          grasp_rate=float(out[:, 0].mean()))

    pyb = None
    if args.pybullet_n > 0:
        try:
            import pybullet_original as peer
        except ImportError as exc:
            print(f"PyBullet peer skipped: {exc} (pip install -e '.[pybullet]')")
        else:
            k = min(args.pybullet_n, len(objs))
            lh = [finger_hulls(f, cfg) for f in lefts[:k]]
            rh = [finger_hulls(f, cfg) for f in rights[:k]]
            t = time.perf_counter()
            pout, stats = peer.evaluate_original(hulls[:k], lh, rh, cfg=cfg)
            sec = time.perf_counter() - t
            rows["pybullet_original"] = dict(evals=k, seconds=sec, steps=int(stats["steps"]), workers=1,
                                             grasp_rate=float(pout[:, 0].mean()))
            # the same k triples through MuJoCo on one thread: the per-core comparison
            t = time.perf_counter()
            sim.evaluate(objs[:k], lefts[:k], rights[:k], backend="mujoco", cfg=cfg, threads=1,
                         object_hulls=hulls[:k], progress=False)
            rows["mujoco_1thread_same"] = dict(evals=k, seconds=time.perf_counter() - t, steps=None,
                                               workers=1, grasp_rate=None)
            pyb = rows["pybullet_original"]

    print(f"\n{'backend':22s} {'evals':>6s} {'seconds':>8s} {'evals/s':>8s} {'per core':>9s} "
          f"{'steps/s':>9s} {'grasp':>6s}")
    for name, r in rows.items():
        eps = r["evals"] / r["seconds"]
        sps = f"{r['steps'] / r['seconds']:9.0f}" if r["steps"] else f"{'':9s}"
        gr = f"{r['grasp_rate']:6.2f}" if r["grasp_rate"] is not None else ""
        print(f"{name:22s} {r['evals']:6d} {r['seconds']:8.2f} {eps:8.2f} {eps / r['workers']:9.2f} {sps} {gr}")

    result = {"cores": cores, "n": args.n, "config": args.config,
              "mujoco_evals_per_s": rows["mujoco"]["evals"] / rows["mujoco"]["seconds"],
              "mujoco_steps_per_s": rows["mujoco"]["steps"] / rows["mujoco"]["seconds"],
              "mujoco_steps_per_eval": rows["mujoco"]["steps"] / rows["mujoco"]["evals"]}
    if pyb is not None:
        same = rows["mujoco_1thread_same"]
        result["pybullet_evals_per_s"] = pyb["evals"] / pyb["seconds"]
        result["pybullet_steps_per_eval"] = pyb["steps"] / pyb["evals"]
        result["ratio_mujoco_vs_pybullet"] = (same["evals"] / same["seconds"]) / result["pybullet_evals_per_s"]
        print(f"\nper core, same {pyb['evals']} triples: MuJoCo / PyBullet-original = "
              f"{result['ratio_mujoco_vs_pybullet']:.1f}x (target >= 30x)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
