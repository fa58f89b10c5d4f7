"""Agreement of two simulation presets on the same (object, left finger, right finger) triples.

    python benchmarks/sim_agreement.py                                  # fast vs reference, 256 triples
    python benchmarks/sim_agreement.py --objects meshes/ --n-objects 32 --n 128 --json agree.json
    python benchmarks/sim_agreement.py --n 4 --n-objects 1 --config tiny --presets fast fast \\
        --threads 1                                                     # smoke run: agreement 1.0
    python benchmarks/sim_agreement.py --n 64 --render 1                # draw a disagreement

``--presets JUDGED JUDGE`` (``config.SIM_PRESETS``; default ``fast reference``) names the preset
under test and the one it is judged against; ``--backends JUDGED JUDGE`` (default ``mujoco
mujoco``) the simulator of each side, e.g. ``--presets reference reference --backends warp
mujoco``: MuJoCo Warp against plain MuJoCo (labels become ``<preset>@<backend>``).  Both simulate the same triples with plain MuJoCo,
each with its own object pieces (``geometry.pieces.object_pieces`` under that preset's
``object_method``: coacd cached on disk, or tiles made in this process) and its own protocol
settings (early exits at rest or none).  Two equal presets give a determinism check:
their outcomes must agree exactly.

Objects: ``--n-objects`` builtin objects (``--seed``) or the first ``--n-objects`` readable meshes
of ``--objects DIR``.  Per object, four finger kinds, in this order: its imprint pair, the WSG50
pair, one pair cut from two other objects of the set (``dataset.pretraining_pairs``, seeded
by (seed, object)) and a "perturbed" pair, designed-looking fingers: the imprint pair plus a
smooth random field (``perturbed_finger``).  The first ``--n`` triples of objects x kinds are
simulated.

Printed: each preset's object meshing cost per object (uncached, one thread; coacd presets are read from
their cache or decomposed in ``--threads`` processes and not timed per object), the wall time and
physics steps of each preset's evaluation, a table of rates per finger kind and preset (grasp
success, mean trials passed of 11, mean S1..S4 and R-30..R+30 success), agreement per trial
name, per finger kind and overall, whole 11-vector agreement, the grasp confusion counts, the
largest rate gap over finger kinds and the first 10 differing triples.  ``--render K`` draws the
first K differing triples with both presets (``sim.view.render_trials``) to ``--out`` (a
drawing that fails is reported and skipped);
``--json PATH`` writes every figure: the keys of ``agreement_stats`` plus n, presets (the two
labels, "<name>-1" / "<name>-2" when both are the same preset), object_meshing_s ({mean, max} s
per object of the judged preset; null for coacd), steps_per_eval and seconds per preset, and
differing (index, object, kind and both outcome vectors of every differing triple).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from f2f_jax import config, sim
from f2f_jax.config import SIM_PRESETS, TRIAL_NAMES
from f2f_jax.data import builtin_objects, load_mesh, mesh_files
from f2f_jax.dataset.pretraining import KINDS, pretraining_pairs
from f2f_jax.errors import F2FError
from f2f_jax.geometry import is_feasible, largest_component, mesh_to_tsdf
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.hulls import with_max_vertices
from f2f_jax.geometry.pieces import object_pieces, object_pieces_many

FINGER_KINDS = (*KINDS, "perturbed")
PERTURB_GRID = 5  # the random field's coarse grid, per side, upsampled to the volume
PERTURB_AMPLITUDE = 0.3  # the field's peak, as a share of the TSDF range [-1, 1]
PERTURB_TRIES = 10  # draws per finger before a perturbed pair is skipped
SHOWN_DIFFERING = 10
_S = [i for i, name in enumerate(TRIAL_NAMES) if name.startswith("S")]
_R = [i for i, name in enumerate(TRIAL_NAMES) if name.startswith("R")]


def perturbed_finger(finger: np.ndarray, rng: np.random.Generator, geometry,
                     *, amplitude: float = PERTURB_AMPLITUDE, tries: int = PERTURB_TRIES):
    """A designed-looking variant of ``finger`` [R, R, R]: plus a smooth random field, or None.

    The field is Gaussian noise on a ``PERTURB_GRID``^3 grid, upsampled to R^3 (cubic spline)
    and scaled to a peak of ``amplitude`` x 2 (the TSDF range); the sum is clipped to [-1, 1]
    and reduced to its largest component.  Up to ``tries`` draws are made until one is feasible
    (``geometry.is_feasible``); None when none is.
    """
    r = geometry.resolution
    for _ in range(tries):
        field = ndimage.zoom(rng.standard_normal((PERTURB_GRID,) * 3), r / PERTURB_GRID, order=3)
        field *= 2 * amplitude / np.abs(field).max()
        out = largest_component(np.clip(finger + field, -1.0, 1.0).astype(np.float32))
        if is_feasible(out, geometry):
            return out
    return None


def load_objects(n: int, seed: int, directory: Path | None, geometry):
    """Object volumes [M, R, R, R] and M names: ``n`` builtin objects, or the first ``n`` meshes
    of ``directory`` that become volumes (the others are skipped with a message)."""
    if directory is None:
        meshes = builtin_objects(n, seed=seed)
        return np.stack([mesh_to_tsdf(m, geometry) for m in meshes]), [m.metadata["name"] for m in meshes]
    tsdfs, names = [], []
    root = directory.resolve().name or "meshes"
    for path in mesh_files(directory):
        if len(tsdfs) == n:
            break
        name = f"{root}/{path.relative_to(directory).with_suffix('').as_posix()}"
        try:
            tsdfs.append(mesh_to_tsdf(load_mesh(path, name=name), geometry))
        except F2FError as exc:
            print(f"skipping {path}: {exc}")
            continue
        names.append(name)
    return (np.stack(tsdfs) if tsdfs else np.zeros((0,) + (geometry.resolution,) * 3, np.float32)), names


def make_triples(tsdfs: np.ndarray, names: list[str], n: int, seed: int, cfg) -> list[dict]:
    """The first ``n`` triples over objects x ``FINGER_KINDS`` (fewer when the set runs out).

    Each is a dict: object (index into tsdfs), name, kind, left, right ([R, R, R] float32).
    Object i's imprint, WSG50 and cut pairs come from ``pretraining_pairs`` with
    ``default_rng([seed, i])``, its perturbed pair from ``default_rng([seed, i, 1])``; a cut or
    perturbed pair that cannot be made feasibly is skipped.
    """
    triples = []
    for i in range(len(tsdfs)):
        pairs = pretraining_pairs(tsdfs, i, np.random.default_rng([seed, i]), cfg, n_cut=1)
        rng = np.random.default_rng([seed, i, 1])
        left, right = (perturbed_finger(f, rng, cfg.geometry) for f in pairs[0][:2])
        if left is not None and right is not None:
            pairs.append((left, right, "perturbed"))
        for left, right, kind in pairs:
            triples.append(dict(object=i, name=names[i], kind=kind,
                                left=np.asarray(left, np.float32), right=np.asarray(right, np.float32)))
        if len(triples) >= n:
            break
    return triples[:n]


def preset_hulls(tsdfs, cfg, threads: int):
    """Object pieces of every volume under ``cfg``'s object_method: (list of Hulls or error
    message, per-object seconds or None).  coacd goes through its disk cache in ``threads``
    processes (not timed per object); any other method is timed call by call on this thread."""
    if cfg.geometry.object_method == "coacd":
        return object_pieces_many(list(tsdfs), cfg, workers=threads), None
    hulls, seconds = [], []
    for tsdf in tsdfs:
        t = time.perf_counter()
        try:
            hulls.append(object_pieces(tsdf, cfg))
        except (F2FError, ValueError) as exc:  # its triples score zeros, as in object_pieces_many
            hulls.append(f"{type(exc).__name__}: {exc}")
        seconds.append(time.perf_counter() - t)
    return hulls, np.array(seconds)


def _rates(out: np.ndarray) -> dict:
    """Rates of [m, 11] bool outcomes: grasp success, mean trials passed, mean S and R success."""
    return dict(grasp=float(out[:, 0].mean()), trials=float(out.sum(1).mean()),
                S=float(out[:, _S].mean()), R=float(out[:, _R].mean()))


def agreement_stats(out_a, out_b, kinds, labels=("judged", "judge")) -> dict:
    """How two presets' [N, 11] outcomes of the same N triples agree; ``kinds``: N finger kinds.

    Returns a dict of:

    * ``agreement_per_trial``: share of the N x 11 trial outcomes that are equal;
    * ``agreement_per_trial_kind``: that share per trial name ({"grasp": .., "S1": .., ...});
    * ``agreement_per_kind``: that share per finger kind;
    * ``agreement_vectors``: share of triples whose whole 11-vectors are equal;
    * ``rates``: {kind: {label: {"grasp", "trials" (mean passed of 11), "S", "R"}}} per finger
      kind in order of appearance, plus "all";
    * ``grasp_confusion``: 2 x 2 counts ``[judged][judge]`` of the grasp trial, 0 = dropped,
      1 = held (so ``[1][0]``: held by the judged preset (``out_a``) only);
    * ``rate_gap_max``: the largest |rate difference| over finger kinds, in points: "grasp"
      (grasp success) and "trials" (mean trials passed / 11).
    """
    a, b = np.asarray(out_a).astype(bool), np.asarray(out_b).astype(bool)
    kinds = np.asarray(kinds)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != len(TRIAL_NAMES) or len(kinds) != len(a):
        raise ValueError(f"agreement_stats: expected two [N, {len(TRIAL_NAMES)}] outcome arrays and N "
                         f"kinds, got {a.shape}, {b.shape} and {kinds.shape}")
    la, lb = labels
    if la == lb:
        raise ValueError(f"agreement_stats: the two labels must differ, got {labels}")
    same = a == b
    groups = {str(k): kinds == k for k in dict.fromkeys(kinds.tolist())}
    rates = {k: {la: _rates(a[m]), lb: _rates(b[m])} for k, m in groups.items()}
    rates["all"] = {la: _rates(a), lb: _rates(b)}
    gaps = [(abs(r[la]["grasp"] - r[lb]["grasp"]), abs(r[la]["trials"] - r[lb]["trials"]))
            for k, r in rates.items() if k != "all"]
    ga, gb = a[:, 0], b[:, 0]
    return dict(
        agreement_per_trial=float(same.mean()),
        agreement_per_trial_kind={name: float(x) for name, x in zip(TRIAL_NAMES, same.mean(0))},
        agreement_per_kind={k: float(same[m].mean()) for k, m in groups.items()},
        agreement_vectors=float(same.all(1).mean()),
        rates=rates,
        grasp_confusion=[[int((~ga & ~gb).sum()), int((~ga & gb).sum())],
                         [int((ga & ~gb).sum()), int((ga & gb).sum())]],
        rate_gap_max=dict(grasp=100 * max(g for g, _ in gaps),
                          trials=100 * max(t for _, t in gaps) / len(TRIAL_NAMES)),
    )


def _vector(row) -> str:
    """An outcome vector as "grasp S1..S4 R-30..R+30" digits."""
    s = "".join(str(int(v)) for v in row)
    return f"{s[0]} {s[1:5]} {s[5:]}"


def _render(triples, differing, presets, out_dir: Path) -> None:
    """Draw each differing triple with each preset: ``out_dir/<index>_<kind>_<label>.png``."""
    from f2f_jax.sim.view import render_trials  # matplotlib: only when drawing

    out_dir.mkdir(parents=True, exist_ok=True)
    for d in differing:
        tr = triples[d["index"]]
        for label, (cfg, hulls) in presets.items():
            obj = hulls[tr["object"]]
            if isinstance(obj, str):
                print(f"  #{d['index']} {label}: no object hulls ({obj})")
                continue
            model = sim.build_model(obj, finger_hulls(tr["left"], cfg), finger_hulls(tr["right"], cfg), cfg)
            path = out_dir / f"{d['index']:04d}_{tr['kind']}_{label}.png"
            print(f"  drew #{d['index']} with {label} to {path} (outcome {_vector(render_trials(model, cfg, path))})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=256, help="triples simulated by both presets (default 256)")
    p.add_argument("--n-objects", type=int, default=64, help="objects the triples are made on (default 64)")
    p.add_argument("--objects", type=Path, default=None,
                   help="a directory of mesh files (default: builtin objects)")
    p.add_argument("--presets", nargs=2, default=["fast", "reference"], choices=sorted(SIM_PRESETS),
                   metavar=("JUDGED", "JUDGE"),
                   help=f"the preset under test and its judge, of {sorted(SIM_PRESETS)} (default: fast reference)")
    p.add_argument("--backends", nargs=2, default=["mujoco", "mujoco"], metavar=("JUDGED", "JUDGE"),
                   choices=list(sim.BACKENDS),
                   help="the simulator of each side, of mujoco, mjx, warp (default: mujoco mujoco)")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS),
                   help="the config both presets are applied to (default: default)")
    p.add_argument("--hull-vertices", type=int, default=None, metavar="V",
                   help="the judged side's pieces with at most V vertices each: its object pieces "
                        "reduced from the judge's cached ones, its finger hulls made with V")
    p.add_argument("--seed", type=int, default=0, help="builtin objects, cut and perturbed fingers")
    p.add_argument("--threads", type=int, default=os.cpu_count(),
                   help="MuJoCo worker threads and coacd processes (default: all cores)")
    p.add_argument("--render", type=int, default=0, metavar="K",
                   help="draw the first K differing triples with both presets (default 0)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/out/agreement"),
                   help="folder for --render's PNGs (default benchmarks/out/agreement)")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    if args.n < 1 or args.n_objects < 1 or args.threads < 1 or args.render < 0:
        p.error("--n, --n-objects and --threads must be >= 1, --render >= 0")
    if args.hull_vertices is not None and args.hull_vertices < 4:
        p.error("--hull-vertices must be >= 4")
    if args.objects is not None:
        if not args.objects.is_dir():
            p.error(f"--objects {args.objects}: no such directory")
        if not mesh_files(args.objects):
            p.error(f"--objects {args.objects}: no mesh files in this directory")
    base = config.get(args.config)
    judged, judge = args.presets
    labels = tuple(name if backend == "mujoco" else f"{name}@{backend}"
                   for name, backend in zip(args.presets, args.backends))
    if args.hull_vertices is not None:
        labels = (f"{labels[0]}/v{args.hull_vertices}", labels[1])
    if labels[0] == labels[1]:
        labels = (f"{labels[0]}-1", f"{labels[1]}-2")
    backend_of = dict(zip(labels, args.backends))

    t = time.perf_counter()
    tsdfs, names = load_objects(args.n_objects, args.seed, args.objects, base.geometry)
    if not len(tsdfs):
        p.error(f"--objects {args.objects}: none of its mesh files became an object volume")
    triples = make_triples(tsdfs, names, args.n, args.seed, base)
    kinds = [tr["kind"] for tr in triples]
    counts = {k: kinds.count(k) for k in FINGER_KINDS if k in kinds}
    source = str(args.objects) if args.objects is not None else f"builtin (seed {args.seed})"
    print(f"{len(triples)} triples on {len(tsdfs)} objects of {source} "
          f"({', '.join(f'{v} {k}' for k, v in counts.items())}) in {time.perf_counter() - t:.1f} s; "
          f"config {args.config}, presets {judged} (judged) vs {judge} (judge)", flush=True)
    if len(triples) < args.n:
        print(f"note: only {len(triples)} of the {args.n} triples asked for: give more --n-objects")

    used = sorted({tr["object"] for tr in triples})
    presets, meshing = {}, None
    for side, (label, name) in enumerate(zip(labels, args.presets)):
        cfg = config.with_sim_preset(base, name)
        t = time.perf_counter()
        made, seconds = preset_hulls(tsdfs[used], cfg, args.threads)
        if side == 0 and args.hull_vertices is not None:
            v = args.hull_vertices
            made = [h if isinstance(h, str) else with_max_vertices(h, v) for h in made]
            cfg = cfg.replace(geometry=dataclasses.replace(cfg.geometry, hull_vertices=v))
        by_object = dict(zip(used, made))
        presets[label] = (cfg, by_object)
        how = (f"{cfg.geometry.object_method}, per object mean {seconds.mean():.3f} s, max {seconds.max():.3f} s"
               if seconds is not None else f"{cfg.geometry.object_method}, cached, {args.threads} processes")
        print(f"{label}: object hulls of {len(used)} objects in {time.perf_counter() - t:.1f} s ({how})", flush=True)
        for i, h in by_object.items():
            if isinstance(h, str):
                print(f"  {names[i]}: no object hulls ({h}); its triples score zeros")
        if label == labels[0] and seconds is not None:
            meshing = dict(mean=float(seconds.mean()), max=float(seconds.max()))

    objs = np.stack([tsdfs[tr["object"]] for tr in triples])
    lefts = np.stack([tr["left"] for tr in triples])
    rights = np.stack([tr["right"] for tr in triples])
    outcomes, seconds, steps = {}, {}, {}
    for label, (cfg, by_object) in presets.items():
        t = time.perf_counter()
        outcomes[label], info = sim.evaluate(objs, lefts, rights, cfg=cfg, threads=args.threads,
                                             object_hulls=[by_object[tr["object"]] for tr in triples],
                                             return_info=True, progress=True,
                                             backend=backend_of[label])
        seconds[label] = time.perf_counter() - t
        ran = ~(info.infeasible | info.failed)
        steps[label] = float(info.steps[ran].mean()) if ran.any() else 0.0
        where = f"{args.threads} threads" if backend_of[label] == "mujoco" else backend_of[label]
        print(f"{label}: {seconds[label]:.1f} s on {where}, {steps[label]:.0f} steps per "
              f"evaluation; {int(info.infeasible.sum())} infeasible, {int(info.failed.sum())} failed, "
              f"{int(info.unstable.sum())} unstable trials", flush=True)

    la, lb = labels
    stats = agreement_stats(outcomes[la], outcomes[lb], kinds, labels)
    print(f"\n{'rates':12s} {'n':>4s}  " + "  ".join(f"{label:^22s}" for label in labels))
    print(f"{'':12s} {'':4s}  " + "  ".join(f"{'grasp':>5s} {'trials':>6s} {'S':>4s} {'R':>4s}" for _ in labels))
    for kind, rates in stats["rates"].items():
        n_kind = len(kinds) if kind == "all" else counts[kind]
        print(f"{kind:12s} {n_kind:4d}  " + "  ".join(
            f"{r['grasp']:5.2f} {r['trials']:6.2f} {r['S']:4.2f} {r['R']:4.2f}" for r in rates.values()))
    print(f"\n{'trial':>8s} " + " ".join(f"{n:>5s}" for n in TRIAL_NAMES))
    print(f"{'agree':>8s} " + " ".join(f"{a:5.3f}" for a in stats["agreement_per_trial_kind"].values()))
    print("agreement per finger kind: " + ", ".join(f"{k} {a:.3f}" for k, a in stats["agreement_per_kind"].items()))
    print(f"agreement {stats['agreement_per_trial']:.4f} over {outcomes[la].size} trials; whole vectors "
          f"{stats['agreement_vectors']:.3f}")
    (nn, nh), (hn, hh) = stats["grasp_confusion"]
    print(f"grasp: both hold {hh}, only {la} {hn}, only {lb} {nh}, neither {nn}")
    gap = stats["rate_gap_max"]
    print(f"largest gap over finger kinds: grasp success {gap['grasp']:.1f} points, trials passed / 11 "
          f"{gap['trials']:.1f} points")

    differing = [dict(index=int(i), object=triples[i]["name"], kind=triples[i]["kind"],
                      outcomes={label: outcomes[label][i].tolist() for label in labels})
                 for i in np.nonzero((outcomes[la] != outcomes[lb]).any(1))[0]]
    print(f"\n{len(differing)} differing triples" + (f", the first {SHOWN_DIFFERING}:" if differing else ""))
    for d in differing[:SHOWN_DIFFERING]:
        print(f"  #{d['index']:4d} {d['kind']:9s} {d['object']:28s} " + "  ".join(
            f"{label} {_vector(v)}" for label, v in d["outcomes"].items()))
    if args.render and differing:
        try:
            _render(triples, differing[:args.render], presets, args.out)
        except Exception as exc:  # noqa: BLE001 - a drawing is optional; the figures above stand
            print(f"rendering skipped: {type(exc).__name__}: {exc}")

    if args.json:
        result = dict(n=len(triples), presets=list(labels), backends=list(args.backends),
                      hull_vertices=args.hull_vertices,
                      config=args.config, seed=args.seed, source=source,
                      kinds=counts, **stats, object_meshing_s=meshing, steps_per_eval=steps,
                      seconds=seconds, threads=args.threads, differing=differing)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
