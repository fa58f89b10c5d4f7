"""MJX's step cost by the pieces' vertex count, in held grasps.

    python benchmarks/mjx_contacts.py                                  # V = 32 16 12 8, batch 64
    python benchmarks/mjx_contacts.py --vertices 32 8 --batch 64 --steps 20 --json out.json
    python benchmarks/mjx_contacts.py --vertices 32 --batch 64 1024 4096 8192   # on a GPU

MJX collides two convex meshes by a separating-axis test over every face normal and every edge
pair of the two (``collision_convex._sat_gaussmap``), so a pair's cost grows with the square of
its edges: ~8,100 edge pairs for two 32-vertex hulls, ~324 for two 8-vertex ones.  For each
``--vertices`` V: ``--n`` builtin imprint triples (coacd pieces from the cache reduced to V
vertices, ``hulls.with_max_vertices``; finger hulls made with V), each grasped by plain MuJoCo to
the end of its hold (the contact-rich state most steps of an evaluation are in), tiled to each
``--batch`` size; then ``--steps`` MJX steps of every world from those states (one jitted,
vmapped scan, as the backend's programs are), compile timed apart.  Printed per V: MJX env
steps/s and its ratio to the first V's (32: the mesh path as the backend runs it), plain
MuJoCo's steps/s from the same states on one thread, and how many of the held grasps still hold
at the end.  How far V changes outcomes is ``sim_agreement.py --hull-vertices V``'s question.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jp
import mujoco
import numpy as np

from f2f_jax import config
from f2f_jax.bench.agreement import load_objects
from f2f_jax.geometry import imprint_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import with_max_vertices
from f2f_jax.geometry.pieces import object_pieces_many
from f2f_jax.sim import mjx_batch, mjx_collision
from f2f_jax.sim.mujoco_cpu import batched_model_options
from f2f_jax.sim.protocol import GraspRunner
from f2f_jax.sim.scene import build_model

_STATE = ("qpos", "qvel", "act", "ctrl", "qacc_warmstart")


def held_states(models, cfg):
    """Each model grasped by plain MuJoCo at yaw 0 to the end of its hold: ({field: [N, ...]},
    held [N] bool, plain MuJoCo steps/s from those states on one thread)."""
    states, held, seconds, steps = {k: [] for k in _STATE}, [], 0.0, 0
    for m in models:
        runner = GraspRunner(m, cfg)
        ok, _, _ = runner.grasp(0.0)
        held.append(ok)
        for k in _STATE:
            states[k].append(np.array(getattr(runner.data, k)))
        t = time.perf_counter()
        mujoco.mj_step(m, runner.data, nstep=100)
        seconds += time.perf_counter() - t
        steps += 100
    return {k: np.stack(v) for k, v in states.items()}, np.array(held), steps / seconds


def mjx_rate(models, states, cfg, steps: int):
    """(compile s, env steps/s, still-held share) of ``steps`` MJX steps of every world."""
    sim = mjx_batch.MjxGraspSimulator(models[0], cfg)
    batch = sim.batch(models)
    ids = sim.ids
    nobody = np.zeros(steps, np.float32)

    def run(fields, convex, qpos, qvel, act, ctrl, warm):
        m = sim._model(fields, convex)
        d = sim.d0.replace(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, qacc_warmstart=warm)
        z0 = d.qpos[ids.object_qpos + 2]
        d, bad = sim._run(m, d, jp.array(False), jp.asarray(nobody), lambda d, x: d)
        return d.qpos[ids.object_qpos + 2] - z0, bad

    prog = jax.jit(jax.vmap(run))
    args = (batch.fields, batch.convex, *(states[k].astype(np.float32) for k in _STATE))
    with mjx_collision.merged_mesh_collisions():
        t = time.perf_counter()
        jax.block_until_ready(prog(*args))
        first = time.perf_counter() - t
        t = time.perf_counter()
        drop, bad = jax.block_until_ready(prog(*args))
        run_s = time.perf_counter() - t
    kept = float(np.mean((np.asarray(drop) > -0.005) & ~np.asarray(bad)))
    return first - run_s, len(models) * steps / run_s, kept


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vertices", type=int, nargs="+", default=[32, 16, 12, 8])
    p.add_argument("--n", type=int, default=8, help="distinct builtin imprint triples (default 8)")
    p.add_argument("--batch", type=int, nargs="+", default=[64],
                   help="worlds per MJX call, one row each (default 64)")
    p.add_argument("--steps", type=int, default=20, help="MJX steps timed per call (default 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    if min(args.vertices) < 4 or args.n < 1 or min(args.batch) < 1 or args.steps < 1:
        p.error("--vertices >= 4; --n, --batch and --steps >= 1")
    base = config.get("default")
    tsdfs, _ = load_objects(args.n, args.seed, None, base.geometry)
    pieces = object_pieces_many(list(tsdfs), base, progress=False)
    pairs = [imprint_fingers(t, base.geometry) for t in tsdfs]
    print(f"{jax.devices()[0].device_kind}: {len(tsdfs)} builtin imprint triples tiled to each batch "
          f"size, {args.steps} MJX steps from each held state")
    print(f"{'V':>3s} {'batch':>6s} {'compile s':>9s} {'env steps/s':>11s} {'x first':>7s} "
          f"{'mujoco steps/s':>14s} {'held':>5s} {'still held':>10s}")
    rows = []
    for v in args.vertices:
        cfg = base.replace(geometry=dataclasses.replace(base.geometry, hull_vertices=v))
        models = [build_model(with_max_vertices(h, v), finger_hulls(left, cfg),
                              finger_hulls(right, cfg), cfg, **batched_model_options("mjx"))
                  for h, (left, right) in zip(pieces, pairs)]
        states, held, cpu_rate = held_states(models, cfg)
        for size in args.batch:
            idx = np.arange(size) % len(models)
            compile_s, rate, kept = mjx_rate([models[i] for i in idx],
                                             {k: s[idx] for k, s in states.items()}, cfg, args.steps)
            first = next((r for r in rows if r["batch"] == size), None)
            row = dict(vertices=v, batch=size, compile_s=compile_s, env_steps_per_s=rate,
                       mujoco_steps_per_s=cpu_rate, held=float(held.mean()), still_held=kept,
                       ratio_to_first=rate / first["env_steps_per_s"] if first else 1.0)
            rows.append(row)
            print(f"{v:3d} {size:6d} {compile_s:9.1f} {rate:11.1f} {row['ratio_to_first']:7.2f} "
                  f"{cpu_rate:14.0f} {row['held']:5.2f} {kept:10.2f}", flush=True)
            if args.json:  # after every row: a run stopped early keeps what it measured
                args.json.write_text(json.dumps(dict(device=jax.devices()[0].device_kind,
                                                     steps=args.steps, n=len(tsdfs), rows=rows),
                                                indent=1))
    if args.json:
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
