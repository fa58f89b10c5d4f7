"""Latency of ``f2f_jax.design``: seconds per new object in each mode, and the nets alone.

    python benchmarks/design_latency.py                      # shipped weights, this machine
    python benchmarks/design_latency.py --new-objects 0 --config paper --json design_latency.json

First, per new object (``--new-objects`` built-in meshes of ``--mesh-seed``, whose pieces are in
no cache), what a user waits for in each mode of ``design()`` from a mesh: the TSDF, the object's
coacd pieces (paid once per object by every mode that simulates; 13-15 s), and the design call
itself, warm (one untimed call per mode first: tracing and compilation are paid once per process):

- ``net``: ``design(obj, candidates=1, verify=False)``, the generator's own design;
- ``net 16``: 16 candidates ranked by the fitness net, ``verify=False``;
- ``default``: ``design(obj)``, 16 candidates + the imprint pair and two variants, simulated;
- ``tolerance``: the default ranked over 3 moved copies as well (``tolerance=0.3``).

Then the nets alone:

Cold is the first call of a shape in this process (tracing and XLA compilation included); warm
is the median of ``--repeats`` further calls (``--batch-repeats`` for the batch).  The warm
calls are split into the generator (``propose``: encoder, embedding, latent noise, decoder), the
host post-processing (largest component and feasibility of every finger, numpy) and the fitness
net (``predict``).  No simulation: ``verify=True`` adds ``sim.evaluate`` of the feasible
candidates (see ``benchmarks/sim_throughput.py``).

TrainedNets: the newest checkpoint of ``--run-dir`` (default: the shipped weights) when its nets
have the requested config's sizes, else randomly initialised nets of that config (latency does not depend on the weights; the
output says which).  A batch whose estimated time (warm single-object time x B) exceeds
``--budget-s``, or whose candidate volumes would not fit in the free host memory, is skipped
with the estimate printed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings

import numpy as np


def _available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _models(config_name: str, run_dir):
    from f2f_jax import config
    from f2f_jax.errors import CheckpointError
    from f2f_jax.train.state import init_trained_nets

    cfg = config.get(config_name)
    try:
        from f2f_jax.train.checkpoint import load_trained_nets
        from f2f_jax.train.weights import load_weights

        nets = load_trained_nets(run_dir) if run_dir else load_weights()
        if nets.config.net == cfg.net:
            return nets, nets.source
        note = f"{run_dir or 'the shipped weights'} have other net sizes"
    except CheckpointError as exc:
        note = f"no checkpoint ({str(exc).split(':')[0]})"
    t = time.perf_counter()
    nets = init_trained_nets(cfg)
    return nets, f"random init, {note}; init took {time.perf_counter() - t:.1f} s"


def _objects(n_distinct: int):
    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import mesh_to_tsdf

    return np.stack([mesh_to_tsdf(m) for m in builtin_objects(n_distinct, seed=0)])


class _StepTimer:
    """Wraps design's step functions to time them inside design() calls."""

    STEPS = ("propose", "postprocess", "predict")

    def __init__(self, module):
        self.module = module
        self.originals = {s: getattr(module, s) for s in self.STEPS}
        self.seconds = {s: [] for s in self.STEPS}

    def __enter__(self):
        for step, fn in self.originals.items():
            def timed(*args, _fn=fn, _step=step, **kwargs):
                t = time.perf_counter()
                out = _fn(*args, **kwargs)
                self.seconds[_step].append(time.perf_counter() - t)
                return out

            setattr(self.module, step, timed)
        return self

    def __exit__(self, *exc):
        for step, fn in self.originals.items():
            setattr(self.module, step, fn)

    def medians(self) -> dict:
        return {s: statistics.median(v) for s, v in self.seconds.items() if v}


def _measure(design_module, nets, objs, k: int, repeats: int) -> dict:
    import jax

    key = jax.random.key(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", design_module.InfeasibleDesignWarning)
        t = time.perf_counter()
        pairs = design_module.design(objs, params=nets, candidates=k, key=key, verify=False)
        cold = time.perf_counter() - t
        warm = []
        with _StepTimer(design_module) as timer:
            for _ in range(repeats):
                t = time.perf_counter()
                design_module.design(objs, params=nets, candidates=k, key=key, verify=False)
                warm.append(time.perf_counter() - t)
    n = len(objs) * k
    feasible = np.mean([p.feasible for p in pairs])
    med = statistics.median(warm)
    return dict(objects=len(objs), candidates=k, cold_s=cold, warm_median_s=med,
                warm_all_s=warm, per_candidate_ms=1e3 * med / n,
                steps_warm_median_s=timer.medians(), feasible_fraction=float(feasible))


MODES = {  # name: design() options
    "net": dict(candidates=1, verify=False),
    "net 16": dict(candidates=16, verify=False),
    "default": dict(),
    "tolerance": dict(tolerance=0.3, copies=3),
}


def per_object(design_module, nets, n: int, seed: int, modes: list[str]) -> list[dict]:
    """Seconds per new object in each mode (see the module's docstring); prints a table."""
    import tempfile

    from f2f_jax.data import builtin_objects
    from f2f_jax.geometry import mesh_to_tsdf, object_volume
    from f2f_jax.geometry.pieces import object_pieces

    g = nets.config.geometry
    warm_obj = mesh_to_tsdf(builtin_objects(1, seed=0)[0], g)  # its pieces ship with the package
    for mode in modes:
        design_module.design(warm_obj, params=nets, **MODES[mode])
    print(f"{'object':>8} {'tsdf s':>7} {'coacd s':>8} " + " ".join(f"{m + ' s':>12}" for m in modes)
          + "   (design call, warm; trials of the pick: simulated)")
    rows = []
    with tempfile.TemporaryDirectory(prefix="f2f-latency-") as cache:
        os.environ["F2F_CACHE_DIR"] = cache  # a new object: no cached pieces
        for i, mesh in enumerate(builtin_objects(n, seed=seed)):
            t = time.perf_counter()
            obj, _ = object_volume(mesh, g)
            row = dict(object=f"{seed}:{i}", tsdf_s=time.perf_counter() - t)
            t = time.perf_counter()
            object_pieces(obj, g)
            row["coacd_s"] = time.perf_counter() - t
            for mode in modes:
                t = time.perf_counter()
                pair = design_module.design(obj, params=nets, **MODES[mode])
                row[mode] = dict(seconds=time.perf_counter() - t, origin=pair.origin,
                                 passed=None if pair.simulated is None else int(pair.simulated.sum()))
            rows.append(row)
            print(f"{row['object']:>8} {row['tsdf_s']:>7.2f} {row['coacd_s']:>8.2f} " + " ".join(
                f"{row[m]['seconds']:>7.2f}" + (f" ({row[m]['passed']:>2})" if row[m]["passed"] is not None
                                                 else " " * 5) for m in modes), flush=True)
    med = {m: statistics.median(r[m]["seconds"] for r in rows) for m in modes}
    tsdf = statistics.median(r["tsdf_s"] for r in rows)
    coacd = statistics.median(r["coacd_s"] for r in rows)
    print("median seconds per new object, meshing included: " + "; ".join(
        f"{m} {tsdf + med[m] + (coacd if MODES[m].get('verify', True) else 0):.1f}" for m in modes))
    print()
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="default", choices=("tiny", "default", "paper"))
    p.add_argument("--candidates", type=int, nargs="+", default=[1, 64])
    p.add_argument("--batch", type=int, default=256, help="objects in the batch measurement")
    p.add_argument("--repeats", type=int, default=5, help="warm calls for one object")
    p.add_argument("--batch-repeats", type=int, default=2, help="warm calls for the batch")
    p.add_argument("--distinct", type=int, default=16,
                   help="distinct builtin objects, tiled to fill the batch")
    p.add_argument("--budget-s", type=float, default=600.0,
                   help="skip a batch measurement estimated to take longer than this per call")
    p.add_argument("--run-dir", default=None, help="a run's newest checkpoint (default: the shipped weights)")
    p.add_argument("--new-objects", type=int, default=3,
                   help="new meshes timed per mode (0: skip; each costs one coacd, 13-15 s)")
    p.add_argument("--mesh-seed", type=int, default=11, help="seed of the new built-in meshes")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--json", default=None, help="write the results here")
    args = p.parse_args(argv)

    import jax

    from f2f_jax import designer as design_module
    from f2f_jax.nets.inference import CHUNK

    dev = jax.devices()[0]
    device = f"{dev.platform} ({dev.device_kind}), {jax.device_count()} device(s)"
    nets, source = _models(args.config, args.run_dir)
    distinct = _objects(min(args.distinct, args.batch))
    batch = distinct[np.arange(args.batch) % len(distinct)]
    print(f"design() latency: config {args.config}, device {device}, jax {jax.__version__}")
    print(f"models: {source}")
    new_rows = []
    if args.new_objects > 0:
        print(f"\nper new object ({args.new_objects} built-in meshes of seed {args.mesh_seed}), "
              f"{os.cpu_count()} cores:")
        new_rows = per_object(design_module, nets, args.new_objects, args.mesh_seed, args.modes)
    print(f"objects: {len(distinct)} builtin objects (the batch tiles them to {args.batch}); "
          f"no simulation (verify=False); chunk {CHUNK} candidates per vmap")
    print()
    header = (f"{'B':>4} {'K':>4} {'cold s':>9} {'warm s':>9} {'ms/cand':>9} "
              f"{'propose':>8} {'post':>8} {'predict':>8} {'feasible':>8}")
    print(header)
    sys.stdout.flush()
    rows = []

    def show(r):
        s = r["steps_warm_median_s"]
        print(f"{r['objects']:>4} {r['candidates']:>4} {r['cold_s']:>9.3f} {r['warm_median_s']:>9.3f} "
              f"{r['per_candidate_ms']:>9.2f} {s.get('propose', 0):>8.3f} "
              f"{s.get('postprocess', 0):>8.3f} {s.get('predict', 0):>8.3f} "
              f"{r['feasible_fraction']:>8.2f}")
        sys.stdout.flush()

    single = {}
    for k in args.candidates:
        r = _measure(design_module, nets, distinct[:1], k, args.repeats)
        single[k] = r
        rows.append(r)
        show(r)
    for k in args.candidates:
        n = args.batch * k
        est_s = single[k]["warm_median_s"] * args.batch
        # lefts and rights: the device output, its host copy, the fitness net's device input
        need = 3 * n * 2 * 40 ** 3 * 4
        free = _available_bytes()
        if est_s > args.budget_s or (free is not None and need > 0.8 * free):
            why = (f"estimated {est_s:.0f} s per call (> --budget-s {args.budget_s:.0f})"
                   if est_s > args.budget_s else
                   f"needs ~{need / 2**30:.1f} GiB of host memory, {free / 2**30:.1f} GiB free")
            print(f"{args.batch:>4} {k:>4}   skipped: {why}")
            rows.append(dict(objects=args.batch, candidates=k, skipped=why, estimated_s=est_s))
            continue
        r = _measure(design_module, nets, batch, k, args.batch_repeats)
        rows.append(r)
        show(r)

    if args.json:
        result = dict(config=args.config, device=device, jax=jax.__version__, models=source,
                      chunk=CHUNK, rows=rows, per_new_object=new_rows)
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    sys.exit(main())
