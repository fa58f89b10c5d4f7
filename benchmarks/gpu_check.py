"""The GPU check: every accelerator figure in one command and one JSON.

    python benchmarks/gpu_check.py --out gpu_check.json         # one GPU: <= 13 minutes end to end
    python benchmarks/gpu_check.py --cpu --tiny --out dry.json   # dry run on a CPU (minutes)

Runs, one after the other, each as its own process with its own time limit (a step that runs
out of time or fails is recorded with its output's tail, and the next one still runs):

1. ``sim_throughput.py --backends mujoco,warp``: plain MuJoCo on the host's cores (fast and
   reference presets) and MuJoCo Warp on the same imprint triples tiled to each of ``--sizes``
   (default 256 and 2,048: on an H200 on 2026-12-04, warp compiled for 70 s and then ran 23
   evaluations/s under ``reference``, so 8,192 candidates alone take ~6 minutes), under each of
   ``--warp-presets`` (default reference and fast: every phase in full, at 2 ms Euler or 4 ms
   implicitfast): full evaluations/s, environment steps/s, compile seconds apart, grasp success
   and agreement with plain MuJoCo, the device's name.
2. ``sim_agreement.py --presets P reference --backends warp mujoco`` (P: ``--agreement-preset``,
   default fast, the default's figure; reference measured 99.25% on an H200): MuJoCo Warp
   against plain MuJoCo's reference on 256 mixed triples (imprint, WSG50, cut, perturbed pairs of
   64 builtin objects): per-trial, per-kind and whole-vector agreement, rates per kind.
3. ``mjx_contacts.py --vertices 32``: MJX's environment steps/s from held grasps at
   ``--mjx-sizes``, compile apart (MJX's full evaluations run at ~2 per second on an H100: a full
   8,192-candidate batch would take an hour, so its rate is measured per step).
4. ``train_throughput.py --config paper``: the paper-size training step per stage.
5. ``gpu_check.py --options-step``: MuJoCo Warp's two options on mixed builtin triples (imprint,
   WSG50, cut) tiled to ``--options-size`` under the fast preset: the pair list as MuJoCo Warp
   builds it, with ``pair_filter`` (the default: pairs that cannot touch left out), and with
   ``rest_stop`` too (resting phases end early): pairs the broad phase tests and pairs that reach
   the narrow phase per world, evaluations/s, and outcomes against the unfiltered run's.

The JSON (written after every step, so a killed run keeps what finished) holds ``device``
(GPU name, warp and JAX devices), ``steps`` ({name: {rc, seconds, command, tail}}), each
step's own JSON under its name: ``throughput``, ``mjx``, ``agreement``, ``training``, and
``summary``: the figures as markdown lines, also printed at the end; ``options`` holds step 5's rows.

``--cpu`` allows running without a GPU (otherwise refused: the sizes would take hours on a CPU);
``--tiny`` shrinks every step to a smoke test (tiny config, 2 triples, batches of 2 and 4, 4
agreement triples on 1 object, MJX at batch 2).  Every step's objects are builtin objects 0-63
of seed 0, whose coacd pieces ship with the package: a bare machine runs no coacd (on the H200,
24 triples and their pieces were ready in 16 s).

A bare GPU machine needs the project's dependencies importable.  A Python-with-JAX image
has JAX, flax, optax, orbax, scipy, scikit-image, h5py, matplotlib and tqdm; the rest
(mujoco, mujoco-mjx, mujoco-warp, warp-lang, trimesh, coacd, ...: 117 MB compressed, warp-lang's
wheel alone 149 MB, more than a 64 MiB transfer limit) is packed by ``tools/gpu_pack.py`` into parts;
it prints one shell line per part, the last of which runs this script.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TAIL = 4000  # characters of a step's output kept in the JSON


def device_info() -> dict:
    """The GPU as nvidia-smi names it, and the devices warp and JAX see."""
    info: dict = {}
    if shutil.which("nvidia-smi"):
        out = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version",
                              "--format=csv,noheader"], capture_output=True, text=True)
        info["nvidia_smi"] = out.stdout.strip().splitlines()
    # JAX asked in a child process: in this one it would hold most of the GPU's memory
    # (its preallocation) through every step
    out = subprocess.run([sys.executable, "-c", "import jax; print('\\n'.join(f'{d.platform}:"
                          "{d.device_kind}' for d in jax.devices()))"],
                         capture_output=True, text=True)
    info["jax"] = (out.stdout.split() if out.returncode == 0
                   else f"unavailable: {out.stderr.strip()[-300:]}")
    try:
        from f2f_jax.sim import warp_batch

        info["warp"] = warp_batch.local_devices()
    except ImportError as exc:
        info["warp"] = f"unavailable: {exc}"
    return info


def plan(args) -> list[tuple[str, list[str], int]]:
    """(name, command, seconds allowed) of each step."""
    py = sys.executable
    if args.tiny:
        thr = ["--config", "tiny", "--n", "2", "--batch-sizes", "2", "4"]
        mjx = ["--n", "1", "--batch", "2", "--steps", "5"]
        agr = ["--config", "tiny", "--n", "4", "--n-objects", "1"]
        trn = ["--config", "tiny", "--steps", "2"]
    else:
        sizes = [str(s) for s in args.sizes]
        thr = ["--n", "24", "--batch-sizes", *sizes]
        mjx = ["--n", "8", "--batch", *[str(b) for b in args.mjx_sizes], "--steps", "20"]
        agr = ["--n", "256", "--n-objects", "64"]
        trn = ["--config", "paper", "--steps", "3"]
    return [
        ("throughput", [py, str(HERE / "sim_throughput.py"), *thr, "--per-core-n", "0",
                        "--no-pybullet", "--meshing-n", "0", "--backends", "mujoco,warp",
                        "--batched-presets", *args.warp_presets],
         args.throughput_s),
        ("agreement", [py, str(HERE / "sim_agreement.py"), *agr, "--presets", args.agreement_preset,
                       "reference", "--backends", "warp", "mujoco"], args.agreement_s),
        ("mjx", [py, str(HERE / "mjx_contacts.py"), *mjx, "--vertices", "32"], args.mjx_s),
        ("training", [py, str(HERE / "train_throughput.py"), *trn], args.training_s),
    ] + ([("options", [py, str(HERE / "gpu_check.py"), "--options-step", "--options-size",
                       str(4 if args.tiny else args.options_size), *(["--tiny"] if args.tiny else [])],
           args.options_s)] if getattr(args, "options_s", 0) else [])


OPTIONS = (("unfiltered", dict(pair_filter=False)), ("pair_filter", {}),
           ("pair_filter+rest_stop", dict(rest_stop=True)))


def options_step(size: int, tiny: bool, json_path: Path) -> int:
    """Step 5: the warp backend with and without its options (OPTIONS) on the same worlds."""
    import numpy as np

    from f2f_jax import config
    from f2f_jax.bench.agreement import builtin_triples
    from f2f_jax.geometry.coacd_pieces import object_hulls
    from f2f_jax.geometry.finger_tiling import finger_hulls
    from f2f_jax.sim import warp_batch
    from f2f_jax.sim.scene import build_model

    cfg = config.with_sim_preset(config.get("tiny" if tiny else "default"), "fast")
    pool, triples = builtin_triples(2 if tiny else 24, 0, cfg)
    models = [build_model(object_hulls(pool[t["object"]], cfg), finger_hulls(t["left"], cfg),
                          finger_hulls(t["right"], cfg), cfg, pad_collides=True) for t in triples]
    chosen = [models[i] for i in np.arange(size) % len(models)]
    out = {"batch": size, "distinct": len(models), "preset": "fast", "rows": []}
    first = None
    for label, options in OPTIONS:
        start = time.perf_counter()
        res = warp_batch.WarpGraspSimulator(cfg, **options).run(chosen)
        run_s = time.perf_counter() - start - res["compile_seconds"]
        first = res["outcome"] if first is None else first
        row = dict(options=label, compile_s=res["compile_seconds"], run_s=run_s,
                   evals_per_s=size / run_s, listed_pairs=res["listed_pairs"],
                   mean_pairs=res["mean_pairs"], peak_pairs=res["peak_pairs"],
                   steps=float(res["steps"].mean()), same_as_unfiltered=float(
                       (res["outcome"] == first).mean()))
        out["rows"].append(row)
        print(json.dumps(row), flush=True)
        json_path.write_text(json.dumps(out, indent=1))
    return 0


def summary(result: dict) -> list[str]:
    """The figures a GPU run is for, as markdown lines (a table per step that produced any):
    warp's rows per preset and batch size, plain MuJoCo on the host, the agreement, MJX's rows,
    the training steps.  Steps that timed out contribute the rows they finished."""
    lines = []
    thr = result.get("throughput") or {}
    rows = [(k[:-len("_rows")], r) for k, v in thr.items() if k.endswith("_rows") for r in v]
    if rows:
        lines += ["| backend | candidates | compile s | run s | evaluations/s | env steps/s | agreement |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {label} | {r['batch']} | {r['compile_s']:.1f} | {r['run_s']:.1f} | "
                  f"{r['evals_per_s']:.2f} | {r['env_steps_per_s']:,.0f} | {r['agreement_with_mujoco']:.2%} |"
                  for label, r in rows]
    if "reference_evals_per_s" in thr:
        lines.append(f"plain MuJoCo on {thr.get('cores')} host threads, {thr.get('n')} triples: "
                     f"fast {thr['mujoco_evals_per_s']:.2f} evaluations/s, reference "
                     f"{thr['reference_evals_per_s']:.2f}")
    agr = result.get("agreement") or {}
    if "agreement_per_trial" in agr:
        judged, judge = agr["presets"]
        gap = agr.get("rate_gap_max", {})
        lines.append(f"agreement, {judged} against {judge}, {agr['n']} triples: "
                     f"{agr['agreement_per_trial']:.2%} of trials, whole vectors "
                     f"{agr['agreement_vectors']:.1%}, largest gap per kind: grasp "
                     f"{gap.get('grasp', float('nan')):.1f} points, trials {gap.get('trials', float('nan')):.1f}")
    for r in (result.get("mjx") or {}).get("rows", []):
        lines.append(f"MJX, {r['vertices']} vertices, {r['batch']} candidates: "
                     f"{r['env_steps_per_s']:,.0f} env steps/s (compile {r['compile_s']:.1f} s)")
    opt = result.get("options") or {}
    if opt.get("rows"):
        lines += [f"warp options, {opt['batch']} candidates ({opt['distinct']} distinct, {opt['preset']}):",
                  "| options | pairs listed/world | to narrow phase/world (peak) | evaluations/s | "
                  "steps/candidate | same outcomes |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['options']} | {r['listed_pairs']:.0f} | {r['mean_pairs']:.1f} ({r['peak_pairs']:.0f}) "
                  f"| {r['evals_per_s']:.2f} | {r['steps']:.0f} | {r['same_as_unfiltered']:.2%} |"
                  for r in opt["rows"]]
    for r in (result.get("training") or {}).get("rows", []):
        lines.append(f"training {r['stage']}, batch {r['batch']}: {r['step_s']:.2f} s per step "
                     f"(compile + first {r['compile_s']:.1f} s)")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("gpu_check.json"), help="the JSON to write")
    p.add_argument("--cpu", action="store_true", help="allow a run without a GPU (a dry run)")
    p.add_argument("--tiny", action="store_true", help="every step at smoke-test size")
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 2048],
                   help="warp's batch sizes, candidates (default 256 2048)")
    p.add_argument("--warp-presets", nargs="+", default=["reference", "fast"], choices=["reference", "fast"],
                   help="presets warp's throughput rows run (default reference fast)")
    p.add_argument("--agreement-preset", default="fast", choices=["reference", "fast"],
                   help="the preset warp runs in the agreement step, judged by plain MuJoCo's "
                        "reference (default fast)")
    p.add_argument("--mjx-sizes", type=int, nargs="+", default=[64],
                   help="MJX's batch sizes (default 64: each size is its own ~20 s compile, and "
                        "4,096 did not finish inside the step's 80 s on an H200)")
    p.add_argument("--throughput-s", type=int, default=300, help="time allowed to step 1 (s)")
    p.add_argument("--agreement-s", type=int, default=180, help="time allowed to step 2 (s)")
    p.add_argument("--mjx-s", type=int, default=60, help="time allowed to step 3 (s)")
    p.add_argument("--training-s", type=int, default=120, help="time allowed to step 4 (s)")
    p.add_argument("--options-s", type=int, default=120, help="time allowed to step 5 (s; 0 skips it)")
    p.add_argument("--options-size", type=int, default=512, help="step 5's candidates (default 512)")
    p.add_argument("--options-step", action="store_true", help=argparse.SUPPRESS)  # step 5 itself
    p.add_argument("--json", type=Path, default=None, help=argparse.SUPPRESS)  # step 5's JSON
    p.add_argument("--only", nargs="+", choices=["throughput", "agreement", "mjx", "training", "options"],
                   default=None, help="run only these steps")
    args = p.parse_args(argv)
    if args.options_step:
        return options_step(args.options_size, args.tiny, args.json or Path("options.json"))
    info = device_info()
    has_gpu = bool(info.get("nvidia_smi")) or (isinstance(info.get("warp"), list)
                                               and any(d.startswith("cuda") for d in info["warp"]))
    if not has_gpu and not args.cpu:
        p.error("no GPU found (nvidia-smi, warp); pass --cpu for a dry run on this machine")
    result = {"device": info, "tiny": args.tiny, "steps": {}}
    print(f"device: {json.dumps(info)}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MPLBACKEND": "Agg"}
    # the warp steps share their process with JAX (imported by the project): JAX must not take
    # 75% of the GPU up front, as it does by default, or warp's worlds would not fit
    warp_env = {**env, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    start_all = time.perf_counter()
    for name, command, limit in plan(args):
        if args.only and name not in args.only:
            continue
        with tempfile.TemporaryDirectory(prefix="f2f-gpu-check-") as tmp:
            out_json = Path(tmp) / f"{name}.json"
            start = time.perf_counter()
            print(f"\n== {name} (<= {limit} s): {' '.join(command[1:])}", flush=True)
            try:
                proc = subprocess.run([*command, "--json", str(out_json)], capture_output=True,
                                      text=True, timeout=limit,
                                      env=warp_env if "warp" in " ".join(command) or name == "options" else env)
                rc, output = proc.returncode, proc.stdout + proc.stderr
            except subprocess.TimeoutExpired as exc:
                rc = "timeout"
                output = ((exc.stdout or b"").decode(errors="replace")
                          + (exc.stderr or b"").decode(errors="replace"))
            seconds = time.perf_counter() - start
            lines = [line for line in output.splitlines() if "load on device" not in line]
            tail = "\n".join(lines)[-TAIL:]
            print(tail, flush=True)
            result["steps"][name] = dict(rc=rc, seconds=seconds, command=command[1:], tail=tail)
            if out_json.exists():
                result[name] = json.loads(out_json.read_text())
        result["seconds"] = time.perf_counter() - start_all
        result["summary"] = summary(result)
        args.out.write_text(json.dumps(result, indent=1))
    ok = all(s["rc"] == 0 for s in result["steps"].values())
    print("\n" + "\n".join(result.get("summary", [])))
    print(f"\nwrote {args.out} after {result['seconds']:.0f} s; steps "
          + ", ".join(f"{k}: {'ok' if v['rc'] == 0 else v['rc']}" for k, v in result["steps"].items()))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
