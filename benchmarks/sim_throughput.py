"""Grasp-simulation throughput: full 11-trial evaluations per second, presets and peers side by side.

    python benchmarks/sim_throughput.py                       # 32 builtin imprint triples
    python benchmarks/sim_throughput.py --n 16 --per-core-n 8 --json out.json
    python benchmarks/sim_throughput.py --objects DIR --n 16  # a mesh directory, e.g. random_urdfs
    python benchmarks/sim_throughput.py --n 64 --per-core-n 0 --executor ray   # + Ray's overhead
    python benchmarks/sim_throughput.py --n 64 --per-core-n 0 --no-pybullet --meshing-n 0 \
        --backends mujoco,mjx --batch-sizes 64 256 1024 4096 --grasp-only   # MJX on a GPU
    python benchmarks/sim_throughput.py --peer-shapes convex --peer-repeat 3   # the PyBullet peer alone

Every simulator gets the same triples: imprint finger pairs of builtin objects (or of the first
meshes of ``--objects DIR``).  Object pieces are made beforehand (coacd, cached on disk) and not
counted in the evaluation times; making them is timed apart, uncached and on one core, for the
default preset's method on ``--meshing-n`` objects (``object_meshing_s``) and for the object
tiles option on all of them (``tiles_meshing_s``).

Measured in this one run: the default ("fast") preset and the ``reference`` preset of plain
MuJoCo on all ``--threads`` cores over ``--n`` triples, and each on one thread over the first
``--per-core-n`` of them, the PyBullet original protocol (``f2f_jax.bench.pybullet_peer``, one
core, on the reference's hulls; needs the ``pybullet`` extra, else skipped) on the same
subset.  Printed: evaluations/s, per core, physics steps/s, steps per evaluation and grasp
success per row, and the per-core ratios fast / reference and fast / PyBullet.

Those rows repeat fingers, meshed once per process.  The unique rows (``--unique-n``, default
``--per-core-n``; ``bench.sim_costs``) time new designs, every finger moved by its own field of
``--unique-sd`` voxels and meshed inside the row, one thread, under fast, reference and the
PyBullet peer: per-core evaluations/s, fast / reference and fast / PyBullet, then a fast
evaluation's ms part by part over ``--breakdown-n`` of them (finger pieces, model building, jaw
opener, checks, mj_step, ...).

``--executor ray [--ray-address ADDR]`` adds the default preset on Ray (``sim.evaluate(...,
executor="ray")``, a local cluster over this machine's cores unless an address is given) on the
same triples and pieces: its evaluations/s, ``ray_overhead`` = threads' evaluations/s / Ray's
(1.0: none; compare on the same cores), whether the outcomes are identical, and the seconds to
start Ray and its workers (timed apart: a long job pays them once).

``--backends mujoco,mjx,warp`` adds the batched backends on the same triples: the imprint
triples tiled up to each of ``--batch-sizes``, all 11 trials of every candidate
(``mjx_batch`` / ``warp_batch`` run directly, so that compiling is timed apart), every phase at
full length (both step all worlds in lock-step) under each of ``--batched-presets`` (default
``reference``; ``fast``: its 4 ms implicitfast steps, half as many, keys ``<backend>_fast_...``).
Per backend, preset and batch size: full evaluations/s and environment steps/s (one world
stepped once) after compiling, compile seconds, grasp success, and per-trial agreement with
plain MuJoCo's reference outcomes of the same triples.
MJX has one contact path (convex meshes, its separating-axis test): ``mjx_mesh_env_steps_per_s``
is that path's figure, and ``mjx_env_steps_per_s`` the same until a cheaper contact geometry
exists.  warp runs on every local GPU, else on warp's CPU device (slow: for checks only).
Each batched row also prints its evaluations/s over plain MuJoCo's all-thread row of the same
preset (``<label>_ratio_vs_mujoco``).  ``--grasp-only`` adds, per MJX batch size, the grasp
program alone (settle, close, lift, hold; compile timed apart): grasps/s, environment steps/s
and the share held (``mjx_grasp_rows``).

``--peer-shapes convex|coacd`` times the PyBullet peer alone instead, on the imprint triples of
four convex shapes (sphere, box, cylinder, cone), each ``--peer-repeat`` times, their objects one
hull each (``bench.pybullet_runs.convex_object_hulls``) or coacd pieces: per triple its pieces and
steps, then evaluations/s, steps/s, steps per evaluation, the seconds spent building bodies and the
held and failed grasps apart (a failed grasp ends its evaluation after one attempt).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from f2f_jax import config, sim
from f2f_jax.bench import sim_costs
from f2f_jax.bench.agreement import load_objects
from f2f_jax.cli import sim_options
from f2f_jax.geometry import imprint_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls, remembered_finger_hulls
from f2f_jax.geometry.pieces import object_pieces, object_pieces_many
from f2f_jax.sim import ray_executor


def imprint_triples(tsdfs: np.ndarray, cfg):
    """[N, R, R, R] object volumes -> (objects, lefts, rights) with the imprint pairs."""
    pairs = [imprint_fingers(t, cfg.geometry) for t in tsdfs]
    return tsdfs, np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


def meshing_seconds(tsdfs, cfg) -> np.ndarray:
    """Per-object seconds of making object pieces under cfg, uncached (neither the disk cache nor
    the pieces shipped for builtin objects), one core."""
    seconds = []
    for t in tsdfs:
        start = time.perf_counter()
        object_pieces(t, cfg, cache_dir=False)
        seconds.append(time.perf_counter() - start)
    return np.array(seconds)


def peer_shapes(method: str, repeat: int) -> None:
    """``--peer-shapes``: the PyBullet peer alone on four convex shapes' imprint triples, one
    process (one core); prints the table the module docstring describes."""
    import importlib.metadata

    import trimesh

    from f2f_jax.bench.pybullet_runs import convex_object_hulls, evaluate_original
    from f2f_jax.config import TRIAL_NAMES
    from f2f_jax.geometry import mesh_to_tsdf, object_hulls

    cfg = config.default()
    shapes = {  # convex shapes that rest still on the floor (each stretched to fill the cube)
        "sphere": trimesh.creation.icosphere(subdivisions=3, radius=0.03),
        "box": trimesh.creation.box(extents=(0.06, 0.06, 0.06)),
        "cylinder": trimesh.creation.cylinder(radius=0.03, height=0.06, sections=32),
        "cone": trimesh.creation.cone(radius=0.03, height=0.06, sections=32),
    }
    objects, lefts, rights, names = [], [], [], []
    for name, mesh in shapes.items():
        tsdf = mesh_to_tsdf(mesh, cfg.geometry, name=name)
        left, right = imprint_fingers(tsdf, cfg.geometry)
        obj = object_hulls(tsdf, cfg.geometry) if method == "coacd" else convex_object_hulls(tsdf, cfg)
        objects += [obj] * repeat
        lefts += [finger_hulls(left, cfg.geometry)] * repeat
        rights += [finger_hulls(right, cfg.geometry)] * repeat
        names += [name] * repeat
    outcomes, stats = evaluate_original(objects, lefts, rights, cfg=cfg)
    print(f"pybullet {importlib.metadata.version('pybullet')} | DIRECT client, one process "
          f"(one core) | {platform.processor() or platform.machine()} | dt 1/240 | world x10")
    print("triple      pieces(o/l/r)  steps   " + " ".join(f"{t:>4}" for t in TRIAL_NAMES))
    for i, name in enumerate(names):
        pieces = f"{objects[i].n_pieces}/{lefts[i].n_pieces}/{rights[i].n_pieces}"
        print(f"{name:<10}  {pieces:<13}  {stats['steps_per_evaluation'][i]:>6}  "
              + " ".join(f"{v:>4}" for v in outcomes[i]))
    print(f"{stats['evaluations']} evaluations, {stats['steps']} steps in {stats['seconds']:.1f} s: "
          f"{stats['evaluations_per_second']:.3f} evaluations/s, {stats['steps_per_second']:.0f} steps/s, "
          f"{stats['steps'] / stats['evaluations']:.0f} steps/evaluation, "
          f"{stats['build_seconds']:.2f} s building bodies, {stats['unstable']} unstable")
    for label, mask in (("grasp held, all 11 trials run", outcomes[:, 0] == 1),
                        ("grasp failed, one attempt", outcomes[:, 0] == 0)):
        if mask.any():
            steps = stats["steps_per_evaluation"][mask].sum()
            secs = stats["seconds_per_evaluation"][mask].sum()
            print(f"{label}: {mask.sum()} evaluations, {steps / mask.sum():.0f} steps each, "
                  f"{mask.sum() / secs:.3f} evaluations/s, {steps / secs:.0f} steps/s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=32, help="triples for the all-core runs (default 32)")
    p.add_argument("--per-core-n", "--pybullet-n", dest="per_core_n", type=int, default=8,
                   help="of those, triples for the one-thread runs and the PyBullet peer (default 8)")
    p.add_argument("--unique-n", type=int, default=None,
                   help="unique-design triples for the one-thread unique rows (default --per-core-n)")
    p.add_argument("--unique-sd", type=float, default=0.5,
                   help="the unique designs' fields, voxels of standard deviation (default 0.5)")
    p.add_argument("--breakdown-n", type=int, default=4,
                   help="of the unique designs, evaluations timed part by part (default 4; 0 skips)")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--objects", type=Path, default=None, help="a mesh directory (default: builtin objects)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-pybullet", action="store_true", help="skip the PyBullet peer")
    p.add_argument("--meshing-n", type=int, default=2,
                   help="objects whose pieces are timed uncached (coacd: 13-30 s each; default 2; 0 skips "
                        "the meshing timings, as the GPU check does)")
    p.add_argument("--batched-presets", nargs="+", default=["reference"], choices=["reference", "fast"],
                   help="presets the batched backends run (default reference)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--task-size", type=int, default=None, help="--executor ray: candidates per task")
    p.add_argument("--backends", default="mujoco",
                   help="comma-separated, of mujoco,mjx,warp (default mujoco: plain MuJoCo only)")
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[64],
                   help="candidates per batch for mjx and warp (default 64)")
    p.add_argument("--grasp-only", action="store_true",
                   help="with mjx in --backends: also time MJX's grasp program alone per batch size")
    p.add_argument("--peer-shapes", choices=("convex", "coacd"), default=None,
                   help="time only the PyBullet peer, on four convex shapes' imprint triples whose "
                        "objects are one hull each (convex) or coacd pieces")
    p.add_argument("--peer-repeat", type=int, default=1,
                   help="--peer-shapes: evaluate each triple this many times (default 1)")
    sim_options.add_cli_arguments(p)
    args = p.parse_args(argv)
    if args.peer_shapes is not None:
        if args.peer_repeat < 1:
            p.error("--peer-repeat must be >= 1")
        try:
            import pybullet  # noqa: F401
        except ImportError:
            p.error("--peer-shapes needs the pybullet extra: pip install -e '.[pybullet]'")
        peer_shapes(args.peer_shapes, args.peer_repeat)
        return 0
    if args.n < 1 or args.per_core_n < 0 or args.threads < 1 or args.meshing_n < 0:
        p.error("--n and --threads must be >= 1, --per-core-n and --meshing-n >= 0")
    if args.objects is not None and not args.objects.is_dir():
        p.error(f"--objects {args.objects}: no such directory")
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    if not backends or set(backends) - {"mujoco", "mjx", "warp"} or min(args.batch_sizes) < 1:
        p.error("--backends: a comma-separated list of mujoco, mjx, warp; --batch-sizes >= 1")
    if "warp" in backends:
        try:
            importlib.import_module("f2f_jax.sim.warp_batch")
        except ImportError as exc:
            p.error(str(exc))
    base = config.get(args.config)
    presets = {name: config.with_sim_preset(base, name) for name in ("fast", "reference")}
    cores = os.cpu_count()
    print(f"machine: {platform.processor() or platform.machine()}, {cores} cores; config {args.config}; "
          f"{args.n} imprint triples of {args.objects or 'builtin objects'}")

    t = time.perf_counter()
    tsdfs, _ = load_objects(args.n, args.seed, args.objects, base.geometry)
    if len(tsdfs) == 0:
        p.error(f"--objects {args.objects}: no mesh could be read")
    objs, lefts, rights = imprint_triples(tsdfs, base)
    k = min(args.per_core_n, len(objs))
    pieces = {name: object_pieces_many(list(objs), cfg, workers=args.threads, progress=False)
              for name, cfg in presets.items()}
    print(f"prepared {len(objs)} triples and their object pieces in {time.perf_counter() - t:.1f} s "
          "(cached coacd pieces; not timed below)")
    # the simulator meshes each distinct finger once per process (remembered_finger_hulls):
    # meshed here, the first timed row does not pay for the fingers that the others reuse (the
    # memo keeps the last 256: past 128 triples every row meshes some again, all rows alike)
    t = time.perf_counter()
    for cfg in presets.values():
        for finger in (*lefts, *rights):
            remembered_finger_hulls(finger, cfg)
    print(f"finger pieces of {2 * len(objs)} fingers in {time.perf_counter() - t:.1f} s (not timed below)")
    meshing_keys = {}
    if args.meshing_n:
        meshing = meshing_seconds(objs[:args.meshing_n], presets["fast"])
        tiles_cfg = base.replace(geometry=dataclasses.replace(base.geometry, object_method="tiles"))
        tiles = meshing_seconds(objs, tiles_cfg)
        print(f"object meshing, one core, uncached: default preset "
              f"({presets['fast'].geometry.object_method}) {meshing.mean():.2f} s mean, "
              f"{meshing.max():.2f} s max over {len(meshing)} objects; "
              f"object tiles {tiles.mean():.3f} s mean, {tiles.max():.3f} s max over {len(tiles)}")
        meshing_keys = {"object_meshing_s": {"mean": float(meshing.mean()), "max": float(meshing.max()),
                                             "n": len(meshing),
                                             "method": presets["fast"].geometry.object_method},
                        "tiles_meshing_s": {"mean": float(tiles.mean()), "max": float(tiles.max())}}

    rows = {}

    def run(label, name, n, threads):
        cfg = presets[name]
        start = time.perf_counter()
        out, info = sim.evaluate_with_info(objs[:n], lefts[:n], rights[:n], cfg=cfg, threads=threads,
                                           object_hulls=pieces[name][:n], progress=False)
        rows[label] = dict(evals=n, seconds=time.perf_counter() - start, steps=info.total_steps,
                           workers=threads, grasp_rate=float(out[:, 0].mean()), outcomes=out)

    for name in presets:
        run(name, name, len(objs), args.threads)
    ray_info = {}
    if args.executor == "ray":
        start = time.perf_counter()
        ray = ray_executor.connect(args.ray_address)
        cpus = ray_executor.cluster_cpus(ray)
        # start every worker (process, imports) on a first small batch, timed apart
        warm = min(len(objs), cpus)
        sim.evaluate(objs[:warm], lefts[:warm], rights[:warm], cfg=presets["fast"], executor="ray",
                     object_hulls=pieces["fast"][:warm], task_size=1, progress=False)
        ray_info["start_s"] = time.perf_counter() - start
        start = time.perf_counter()
        out, info = sim.evaluate_with_info(objs, lefts, rights, cfg=presets["fast"], executor="ray",
                                           object_hulls=pieces["fast"], task_size=args.task_size,
                                           progress=False)
        rows["fast ray"] = dict(evals=len(objs), seconds=time.perf_counter() - start,
                                steps=info.total_steps, workers=cpus,
                                grasp_rate=float(out[:, 0].mean()))
        ray_info.update(cpus=cpus, identical=bool(np.array_equal(out, rows["fast"]["outcomes"])))
    if k > 0:
        for name in presets:
            run(f"{name} 1 thread", name, k, 1)
    peer = None
    if not args.no_pybullet:
        try:
            from f2f_jax.bench import pybullet_runs as peer
        except ImportError as exc:
            print(f"PyBullet peer skipped: {exc} (pip install -e '.[pybullet]')")
    if k > 0 and peer is not None:
        ref = presets["reference"]
        lh = [finger_hulls(f, ref) for f in lefts[:k]]
        rh = [finger_hulls(f, ref) for f in rights[:k]]
        start = time.perf_counter()
        pout, stats = peer.evaluate_original(pieces["reference"][:k], lh, rh, cfg=ref)
        rows["pybullet_original"] = dict(evals=k, seconds=time.perf_counter() - start,
                                         steps=int(stats["steps"]), workers=1,
                                         grasp_rate=float(pout[:, 0].mean()))
    u = min(args.per_core_n if args.unique_n is None else args.unique_n, len(objs))
    unique = None if u < 1 else sim_costs.unique_report(  # new designs, fingers meshed in the rows
        objs[:u], {n: pieces[n][:u] for n in presets}, presets, sd_voxels=args.unique_sd,
        seed=args.seed, breakdown_n=args.breakdown_n, pybullet=peer is not None)
    rows.update(unique["rows"] if unique else {})

    print(f"\n{'simulator':26s} {'evals':>6s} {'seconds':>8s} {'evals/s':>8s} {'per core':>9s} "
          f"{'steps/s':>9s} {'steps/eval':>10s} {'grasp':>6s}")
    for label, r in rows.items():
        eps = r["evals"] / r["seconds"]
        print(f"{label:26s} {r['evals']:6d} {r['seconds']:8.2f} {eps:8.2f} {eps / r['workers']:9.2f} "
              f"{r['steps'] / r['seconds']:9.0f} {r['steps'] / r['evals']:10.0f} {r['grasp_rate']:6.2f}")

    def rate(label):
        return rows[label]["evals"] / rows[label]["seconds"]

    fast, ref = rows["fast"], rows["reference"]
    result = {"cores": cores, "n": len(objs), "config": args.config,
              "objects": str(args.objects or "builtin"),
              "mujoco_evals_per_s": rate("fast"),
              "mujoco_steps_per_s": fast["steps"] / fast["seconds"],
              "mujoco_steps_per_eval": fast["steps"] / fast["evals"],
              "reference_evals_per_s": rate("reference"),
              "reference_steps_per_eval": ref["steps"] / ref["evals"], **meshing_keys}
    if ray_info:
        result["ray_evals_per_s"] = rate("fast ray")
        result["ray_overhead"] = rate("fast") / rate("fast ray")
        result.update(ray_cpus=ray_info["cpus"], ray_identical=ray_info["identical"],
                      ray_start_s=ray_info["start_s"], threads=args.threads)
        print(f"\nray ({ray_info['cpus']} CPUs) against {args.threads} threads, same {len(objs)} "
              f"triples: overhead {result['ray_overhead']:.3f} (threads / ray evals/s; target "
              f"<= 1.15); outcomes identical: {'yes' if ray_info['identical'] else 'NO'}; ray and "
              f"its workers started in {ray_info['start_s']:.1f} s (not counted)")
    if k > 0:
        result["ratio_fast_vs_reference"] = rate("fast 1 thread") / rate("reference 1 thread")
        print(f"\nper core, same {k} triples: fast / reference = {result['ratio_fast_vs_reference']:.2f}x "
              f"(target >= 10x)")
    if "pybullet_original" in rows:
        result["pybullet_evals_per_s"] = rate("pybullet_original")
        result["pybullet_steps_per_eval"] = rows["pybullet_original"]["steps"] / k
        result["ratio_mujoco_vs_pybullet"] = rate("fast 1 thread") / result["pybullet_evals_per_s"]
        result["ratio_reference_vs_pybullet"] = rate("reference 1 thread") / result["pybullet_evals_per_s"]
        print(f"per core, same {k} triples: fast / PyBullet-original = "
              f"{result['ratio_mujoco_vs_pybullet']:.1f}x (target >= 30x); reference / PyBullet = "
              f"{result['ratio_reference_vs_pybullet']:.1f}x")
    if unique is not None:
        result.update(unique["result"])
        print("\n".join(unique["lines"]))
    for backend in backends:
        if backend != "mujoco":
            if args.json:  # what is measured so far, in case the batched rows are cut short
                args.json.write_text(json.dumps(result, indent=1))
            for name in args.batched_presets:
                batched_rows(backend, objs, lefts, rights, pieces[name], rows["reference"]["outcomes"],
                             presets[name], args.batch_sizes, threads=args.threads, result=result,
                             json_path=args.json,
                             label=backend if name == "reference" else f"{backend}_{name}",
                             mujoco_evals_per_s=rate(name), grasp_only=args.grasp_only)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    return 0


def batched_rows(backend, objs, lefts, rights, pieces, reference, cfg, sizes, *, threads, result,
                 json_path=None, label=None, mujoco_evals_per_s=None, grasp_only=False) -> None:
    """Full 11-trial evaluations of the triples tiled to each batch size on ``backend`` under
    ``cfg``; prints a table and adds its JSON keys (``<label>_...``, label defaults to the
    backend) to ``result``, written to ``json_path`` after every row.  Agreement is with
    ``reference``, plain MuJoCo's outcomes of the same triples; the ratio with
    ``mujoco_evals_per_s``, plain MuJoCo's all-thread rate under the same preset.  ``grasp_only``
    (MJX): the grasp program alone at each size too (``<label>_grasp_rows``)."""
    from f2f_jax.sim.mujoco_cpu import batched_model_options
    from f2f_jax.sim.scene import build_model

    batched = importlib.import_module(f"f2f_jax.sim.{backend}_batch")
    if backend == "mjx":
        import jax

        device = str(jax.devices()[0].device_kind)
    else:
        device = ", ".join(batched.local_devices())
    options = batched_model_options(backend)
    models = [build_model(h, finger_hulls(left, cfg), finger_hulls(right, cfg), cfg, **options)
              for h, left, right in zip(pieces, lefts, rights)]
    label = label or backend
    print(f"\n{label} on {device}: {len(models)} distinct imprint triples tiled to each batch size, "
          f"every phase in full at {cfg.sim.timestep * 1e3:g} ms ({cfg.sim.integrator}), all 11 trials; "
          "agreement with plain MuJoCo's reference")
    print(f"{'batch':>6s} {'compile s':>9s} {'run s':>7s} {'evals/s':>8s} {'env steps/s':>11s} "
          f"{'grasp':>6s} {'agree':>6s}")
    out = result
    out.update({f"{backend}_device": device, f"{label}_rows": []})
    for size in sizes:
        idx = np.arange(size) % len(models)
        chosen = [models[i] for i in idx]
        start = time.perf_counter()
        if backend == "mjx":
            sim_ = batched.simulator_for(chosen[0], cfg)
            before = sim_.compile_seconds
            res = sim_.run(sim_.batch(chosen), chunk=size)
            compile_s = sim_.compile_seconds - before
        else:
            res = batched.WarpGraspSimulator(cfg, threads=threads).run(chosen)
            compile_s = res["compile_seconds"]
        run_s = time.perf_counter() - start - compile_s
        agree = float((res["outcome"] == reference[idx]).mean())
        row = dict(batch=size, compile_s=compile_s, run_s=run_s, evals_per_s=size / run_s,
                   env_steps_per_s=float(res["steps"].sum()) / run_s,
                   grasp_rate=float(res["outcome"][:, 0].mean()), agreement_with_mujoco=agree,
                   approach_s=res.get("approach_seconds"))
        out[f"{label}_rows"].append(row)
        print(f"{size:6d} {compile_s:9.1f} {run_s:7.1f} {row['evals_per_s']:8.2f} "
              f"{row['env_steps_per_s']:11.0f} {row['grasp_rate']:6.2f} {agree:6.3f}", flush=True)
        best = max(out[f"{label}_rows"], key=lambda r: r["evals_per_s"])
        out[f"{label}_evals_per_s"] = best["evals_per_s"]
        out[f"{label}_env_steps_per_s"] = best["env_steps_per_s"]
        if label == "mjx":  # one contact path so far: convex meshes
            out["mjx_mesh_env_steps_per_s"] = best["env_steps_per_s"]
        if mujoco_evals_per_s:
            out[f"{label}_ratio_vs_mujoco"] = best["evals_per_s"] / mujoco_evals_per_s
        if json_path:
            json_path.write_text(json.dumps(out, indent=1))
    if mujoco_evals_per_s:
        print(f"{label}: best {out[f'{label}_evals_per_s']:.2f} evaluations/s = "
              f"{out[f'{label}_ratio_vs_mujoco']:.1f}x plain MuJoCo on {threads} threads "
              f"({mujoco_evals_per_s:.2f}/s, same preset)")
    if grasp_only and backend == "mjx":
        grasp_rows(batched, models, cfg, sizes, out, label)
        if json_path:
            json_path.write_text(json.dumps(out, indent=1))


def grasp_rows(batched, models, cfg, sizes, out: dict, label: str) -> None:
    """MJX's grasp program alone (settle, close, lift, hold) on the models tiled to each size:
    compile (the first call) apart from a second, timed call."""
    sim_ = batched.simulator_for(models[0], cfg)
    steps = sim_.n_settle + sim_.n_close + len(sim_.lift_ctrl) + sim_.n_hold
    print(f"\n{label}, the grasp program alone ({steps} steps a grasp):")
    print(f"{'batch':>6s} {'compile s':>10s} {'grasp s':>8s} {'grasps/s':>9s} {'env steps/s':>12s} {'held':>5s}")
    out[f"{label}_grasp_rows"] = []
    for size in sizes:
        b = sim_.batch([models[i] for i in np.arange(size) % len(models)])
        yaw = np.zeros(size, np.float32)
        before = sim_.compile_seconds
        sim_._call("grasp", size, b.fields, b.convex, b.planes, yaw)
        compile_s = sim_.compile_seconds - before
        start = time.perf_counter()
        held = sim_._call("grasp", size, b.fields, b.convex, b.planes, yaw)[0]
        sec = time.perf_counter() - start
        row = dict(batch=size, compile_s=compile_s, seconds=sec, grasps_per_s=size / sec,
                   env_steps_per_s=size * steps / sec, held=float(np.mean(np.asarray(held))))
        out[f"{label}_grasp_rows"].append(row)
        print(f"{size:6d} {compile_s:10.1f} {sec:8.2f} {row['grasps_per_s']:9.1f} "
              f"{row['env_steps_per_s']:12.0f} {row['held']:5.2f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
