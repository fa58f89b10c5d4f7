"""Our grasp protocol against the original's, trial by trial, on the same triples and geometry.

    python benchmarks/protocol_fidelity.py                          # 64 builtin objects x 5 kinds
    python benchmarks/protocol_fidelity.py --objects DIR --n-objects 15 --json fidelity.json
    python benchmarks/protocol_fidelity.py --n-objects 2 --config tiny --kinds imprint  # smoke

Three simulators score every triple: our MuJoCo protocol under the default ``fast`` preset and
under ``reference`` (``sim.evaluate``), and the PyBullet original (``benchmarks/
pybullet_original.py``: the original Fit2Form script, its departures listed in its docstring;
needs the ``pybullet`` extra), all on the same collision geometry: coacd object pieces (cached)
and height-map finger hulls.  The peer runs in ``--workers`` processes, one PyBullet client each.

Triples, per object (``--n-objects`` builtin objects of ``--seed``, or the first readable meshes of
``--objects DIR``), of the finger kinds in ``--kinds`` (default all): "imprint" (its imprint pair),
"wsg50-fmf" (the paper's WSG50 fingers, Schunk's WSG-FMF: ``data.sources.wsg_fmf_fingers``),
"flat" (``geometry.wsg50_fingers``, ideal flat pads), "cut" (a pair cut from two other objects,
as the pretraining dataset makes them) and "perturbed" (the imprint pair plus a smooth random
field: designed-looking fingers, ``sim_agreement.perturbed_finger``).

Printed: per finger kind and simulator the grasp success, mean trials passed of 11 and mean S and
R success; per simulator of ours its agreement with PyBullet per trial name, per finger kind,
overall and as whole vectors; the grasp confusion; the first differing triples.  ``--json PATH``:
``agreement`` ({fast, reference}: ``sim_agreement.agreement_stats`` against "pybullet"), ``rates``
({kind: {simulator: {grasp, trials, S, R}}}, and "all"), n, kinds, objects, seconds, differing,
triples (object, kind) and outcomes ({simulator: one 11-digit string per triple}): enough to judge
an ablation of our side against the same PyBullet outcomes without running PyBullet again.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from f2f_jax import config, sim  # noqa: E402
from f2f_jax.config import TRIAL_NAMES  # noqa: E402
from f2f_jax.data.dataset import pretraining_pairs  # noqa: E402
from f2f_jax.geometry import wsg50_fingers  # noqa: E402
from f2f_jax.geometry.hulls import finger_hulls  # noqa: E402
from f2f_jax.geometry.pieces import object_pieces_many  # noqa: E402
from sim_agreement import _rates, _vector, agreement_stats, load_objects, perturbed_finger  # noqa: E402

FINGER_KINDS = ("imprint", "wsg50-fmf", "flat", "cut", "perturbed")
SIMULATORS = ("fast", "reference", "pybullet")
SHOWN_DIFFERING = 10


def make_triples(tsdfs: np.ndarray, names: list[str], kinds, seed: int, cfg) -> list[dict]:
    """Triples (dicts: object index, name, kind, left, right) of every object x ``kinds``; a cut
    or perturbed pair that cannot be made feasibly is left out."""
    fmf = None
    if "wsg50-fmf" in kinds:
        from f2f_jax.data.sources import wsg_fmf_fingers

        fmf = wsg_fmf_fingers(cfg.geometry)
    flat = wsg50_fingers(cfg.geometry)
    triples = []
    for i in range(len(tsdfs)):
        pairs = {kind: (left, right) for left, right, kind in
                 pretraining_pairs(tsdfs, i, np.random.default_rng([seed, i]), cfg, n_cut=1)}
        pairs["flat"], pairs["wsg50-fmf"] = flat, fmf
        if "perturbed" in kinds:
            rng = np.random.default_rng([seed, i, 1])
            left, right = (perturbed_finger(f, rng, cfg.geometry) for f in pairs["imprint"])
            if left is not None and right is not None:
                pairs["perturbed"] = (left, right)
        for kind in kinds:
            if pairs.get(kind) is not None:
                left, right = pairs[kind]
                triples.append(dict(object=i, name=names[i], kind=kind,
                                    left=np.asarray(left, np.float32),
                                    right=np.asarray(right, np.float32)))
    return triples


def _peer_chunk(args):
    """Worker process: one PyBullet client over a chunk of (object, left, right) hulls."""
    objects, lefts, rights, cfg = args
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import pybullet_original as peer

    out, stats = peer.evaluate_original(objects, lefts, rights, cfg=cfg)
    return out, int(stats["steps"])


def run_peer(objects, lefts, rights, cfg, workers: int):
    """The PyBullet original on every triple, in ``workers`` spawned processes: ([N, 11], steps)."""
    n = len(objects)
    bounds = np.linspace(0, n, max(1, min(workers, n)) + 1).astype(int)
    chunks = [(objects[a:b], lefts[a:b], rights[a:b], cfg) for a, b in zip(bounds[:-1], bounds[1:])]
    with ProcessPoolExecutor(len(chunks), mp_context=get_context("spawn")) as pool:
        parts = list(pool.map(_peer_chunk, chunks))
    return np.concatenate([p[0] for p in parts]), sum(p[1] for p in parts)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n-objects", type=int, default=64)
    p.add_argument("--objects", type=Path, default=None, help="a mesh directory (default: builtin)")
    p.add_argument("--kinds", nargs="+", default=list(FINGER_KINDS), choices=FINGER_KINDS)
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=os.cpu_count(),
                   help="MuJoCo threads, coacd and PyBullet processes (default: all cores)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    if args.n_objects < 1 or args.workers < 1:
        p.error("--n-objects and --workers must be >= 1")
    if args.objects is not None and not args.objects.is_dir():
        p.error(f"--objects {args.objects}: no such directory")
    if importlib.util.find_spec("pybullet") is None:  # the workers import pybullet_original
        p.error("the PyBullet original needs the pybullet extra: pip install -e '.[pybullet]'")
    base = config.get(args.config)
    presets = {name: config.with_sim_preset(base, name) for name in ("fast", "reference")}
    ref = presets["reference"]

    t = time.perf_counter()
    tsdfs, names = load_objects(args.n_objects, args.seed, args.objects, base.geometry)
    if len(tsdfs) == 0:
        p.error(f"--objects {args.objects}: no mesh could be read")
    triples = make_triples(tsdfs, names, args.kinds, args.seed, base)
    pieces = object_pieces_many(list(tsdfs), ref, workers=args.workers)
    keep = [tr for tr in triples if not isinstance(pieces[tr["object"]], str)]
    if len(keep) < len(triples):
        print(f"{len(triples) - len(keep)} triples dropped: their objects have no pieces")
    triples = keep
    objs = np.stack([tsdfs[tr["object"]] for tr in triples])
    lefts = np.stack([tr["left"] for tr in triples])
    rights = np.stack([tr["right"] for tr in triples])
    kinds = [tr["kind"] for tr in triples]
    obj_hulls = [pieces[tr["object"]] for tr in triples]
    print(f"{len(triples)} triples ({', '.join(args.kinds)}) of {len(tsdfs)} objects "
          f"({args.objects or 'builtin'}), config {args.config}; prepared in "
          f"{time.perf_counter() - t:.1f} s", flush=True)

    outcomes, seconds = {}, {}
    for name, cfg in presets.items():
        t = time.perf_counter()
        outcomes[name] = sim.evaluate(objs, lefts, rights, cfg=cfg, threads=args.workers,
                                      object_hulls=obj_hulls, progress=True)
        seconds[name] = time.perf_counter() - t
        print(f"{name}: {seconds[name]:.0f} s", flush=True)
    t = time.perf_counter()
    lh = [finger_hulls(f, ref) for f in lefts]
    rh = [finger_hulls(f, ref) for f in rights]
    outcomes["pybullet"], _ = run_peer(obj_hulls, lh, rh, ref, args.workers)
    seconds["pybullet"] = time.perf_counter() - t
    print(f"pybullet: {seconds['pybullet']:.0f} s in {args.workers} processes", flush=True)

    stats = {name: agreement_stats(outcomes[name], outcomes["pybullet"], kinds, (name, "pybullet"))
             for name in presets}
    rates = {}
    for kind in [*dict.fromkeys(kinds), "all"]:
        m = np.ones(len(kinds), bool) if kind == "all" else np.array(kinds) == kind
        rates[kind] = {s: _rates(outcomes[s][m].astype(bool)) for s in SIMULATORS}
        rates[kind]["n"] = int(m.sum())

    print(f"\n{'kind':10s} {'n':>4s}  " + "  ".join(f"{s:>26s}" for s in SIMULATORS))
    print(f"{'':10s} {'':>4s}  " + "  ".join(f"{'grasp  trials    S     R':>26s}" for _ in SIMULATORS))
    for kind, r in rates.items():
        cells = [f"{r[s]['grasp']:6.3f} {r[s]['trials']:6.2f} {r[s]['S']:5.2f} {r[s]['R']:5.2f}"
                 for s in SIMULATORS]
        print(f"{kind:10s} {r['n']:4d}  " + "  ".join(f"{c:>26s}" for c in cells))
    print("\nagreement with the PyBullet original:")
    print(f"{'trial':8s} " + " ".join(f"{s:>10s}" for s in presets))
    for trial in TRIAL_NAMES:
        print(f"{trial:8s} " + " ".join(f"{stats[s]['agreement_per_trial_kind'][trial]:10.3f}"
                                        for s in presets))
    for kind in dict.fromkeys(kinds):
        print(f"{kind:8s} " + " ".join(f"{stats[s]['agreement_per_kind'][kind]:10.3f}" for s in presets))
    print(f"{'all':8s} " + " ".join(f"{stats[s]['agreement_per_trial']:10.3f}" for s in presets))
    print(f"{'vectors':8s} " + " ".join(f"{stats[s]['agreement_vectors']:10.3f}" for s in presets))
    for s in presets:
        c = stats[s]["grasp_confusion"]
        print(f"grasp, {s} x pybullet: both held {c[1][1]}, both dropped {c[0][0]}, only {s} held "
              f"{c[1][0]}, only pybullet held {c[0][1]}")
    differing = [i for i in range(len(triples))
                 if not np.array_equal(outcomes["fast"][i], outcomes["pybullet"][i])]
    print(f"\n{len(differing)} triples differ (fast vs pybullet); the first {SHOWN_DIFFERING}:")
    for i in differing[:SHOWN_DIFFERING]:
        print(f"  {i:4d} {triples[i]['name']:28s} {kinds[i]:10s} fast {_vector(outcomes['fast'][i])}"
              f"  pybullet {_vector(outcomes['pybullet'][i])}")
    if args.json:
        args.json.write_text(json.dumps(dict(
            n=len(triples), kinds=args.kinds, objects=str(args.objects or "builtin"),
            config=args.config, agreement=stats, rates=rates, seconds=seconds,
            triples=[dict(object=tr["name"], kind=tr["kind"]) for tr in triples],
            outcomes={s: ["".join(map(str, row)) for row in outcomes[s]] for s in SIMULATORS},
            differing=[dict(index=i, object=triples[i]["name"], kind=kinds[i],
                            **{s: _vector(outcomes[s][i]) for s in SIMULATORS})
                       for i in differing]), indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
