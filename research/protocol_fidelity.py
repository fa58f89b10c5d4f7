"""Our grasp protocol against the original's, trial by trial, on the same triples and geometry.

    python research/protocol_fidelity.py                          # 64 builtin objects x 5 kinds
    python research/protocol_fidelity.py --objects DIR --n-objects 15 --json fidelity.json
    python research/protocol_fidelity.py --n-objects 2 --config tiny --kinds imprint  # smoke
    python research/protocol_fidelity.py --kinds imprint wsg50-fmf --ablations --render both.png

Three simulators score every triple: our MuJoCo protocol under the default ``fast`` preset and
under ``reference`` (``sim.evaluate``), and the PyBullet original (``f2f_jax.bench.pybullet_peer``:
the original Fit2Form script, its departures listed in its docstring; needs the ``pybullet``
extra, run by ``bench.pybullet_runs.run_peer``), all on the same collision geometry: coacd object pieces (cached)
and height-map finger hulls.  The peer runs in ``--workers`` processes, one PyBullet client each.

Triples, per object (``--n-objects`` builtin objects of ``--seed``, or the first readable meshes of
``--objects DIR``), of the finger kinds in ``--kinds`` (default all): "imprint" (its imprint pair),
"wsg50-fmf" (the paper's WSG50 fingers, Schunk's WSG-FMF: ``data.sources.wsg_fmf_fingers``),
"flat" (``geometry.wsg50_fingers``, ideal flat pads), "cut" (a pair cut from two other objects,
as the pretraining dataset makes them) and "perturbed" (the imprint pair plus a smooth random
field: designed-looking fingers, ``dataset.perturbed_finger``).

Printed: per finger kind and simulator the grasp success, mean trials passed of 11 and mean S and
R success; per simulator of ours its agreement with PyBullet per trial name, per finger kind,
overall and as whole vectors; the grasp confusion; the first differing triples.  ``--json PATH``:
``agreement`` ({fast, reference}: ``bench.agreement.agreement_stats`` against "pybullet"), ``rates``
({kind: {simulator: {grasp, trials, S, R}}}, and "all"), n, kinds, objects, seconds, differing,
triples (object, kind) and outcomes ({simulator: one 11-digit string per triple}): enough to judge
an ablation of our side against the same PyBullet outcomes without running PyBullet again.

``--render PNG`` draws the first differing triple (an imprint pair where one differs) as both
simulators ran it, one strip of panels each.  ``--ablations`` then changes one difference between
the protocols at a time (``ABLATIONS``: a ``SimConfig`` field of ours, or a switch of the PyBullet
peer, several of them the original's own choices that the peer departs from) and judges the
changed side against the other side's unchanged outcomes: a table of each change's agreement,
the share of its own side's trials it flipped and the rates per finger kind (``ablations`` in
the JSON).  ``--ablations lift open`` runs only those whose label holds one of the words.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from f2f_jax import config, sim
from f2f_jax.bench.agreement import agreement_stats, load_objects, rates, vector_text
from f2f_jax.bench.pybullet_runs import run_peer
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.dataset.pretraining import perturbed_finger, pretraining_pairs
from f2f_jax.geometry import wsg50_fingers
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.pieces import object_pieces_many

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


# One difference between the two protocols at a time, on one side: (side, label, changes).
# "ours" changes are SimConfig fields of the ``fast`` preset; "pybullet" changes are
# ``bench.pybullet_peer.OriginalProtocol`` fields (the peer's departures from the original are
# switches there) or, where no such field exists, SimConfig fields the peer reads as "sim.FIELD"
# (``bench.pybullet_runs.SIM_PREFIX``).  Two arms of our side ran at commit dd4f091 and are gone
# with their SimConfig fields (research/README.md): fingers passing through each other
# (finger_collisions off) and the push through the world origin (push_point="origin").
ABLATIONS: tuple[tuple[str, str, dict], ...] = (
    ("ours", "lift as hard as the original's (lift_time 0.25 s: 11 m/s^2 peak)", dict(lift_time=0.25)),
    ("ours", "jaws close from 3 cm open (open_margin 0.03)", dict(open_margin=0.03)),
    ("ours", "pyramidal friction cone", dict(cone="pyramidal")),
    ("ours", "no torsional friction (condim 3)", dict(condim=3)),
    ("ours", "impratio 1", dict(impratio=1.0)),
    ("ours", "finger-object friction 0.4", dict(finger_friction=0.4)),
    ("pybullet", "gentle lift (lift_max_force 20: 1.0 m/s^2 peak; ours 1.2)", dict(lift_max_force=20.0)),
    ("pybullet", "jaws open 3 cm clear of the cube (open_clearance 0.3)", dict(open_clearance=0.3)),
    ("pybullet", "fingers collide with each other (the original's)", dict(self_collision=True)),
    ("pybullet", "push at the world origin (the original's)", dict(push_point="origin")),
    ("pybullet", "centre of mass at the bottom centre (the original's)", dict(centre_of_mass="base")),
    ("pybullet", "jaws stop 2.45 cm short of the cube (the original's)", dict(stroke_short=0.245)),
    ("pybullet", "no settling before the turned grasps", dict(settle_turned=False)),
    ("pybullet", "finger-object friction 0.4", {"sim.finger_friction": 0.4}),
    ("pybullet", "gentle lift and jaws open 3 cm clear, together",
     dict(lift_max_force=20.0, open_clearance=0.3)),
    ("pybullet", "Bullet steps split in 4 (numSubSteps 4: 1/960 s)", dict(substeps=4)),
    ("pybullet", "Bullet steps split in 8 (numSubSteps 8: 1/1920 s)", dict(substeps=8)),
    ("pybullet", "Bullet steps split in 4, no rolling or spinning friction at the fingers (the original's: 1)",
     dict(substeps=4, finger_rolling_friction=0.0)),
    ("pybullet", "no rolling or spinning friction at the fingers (the original's: 1)",
     dict(finger_rolling_friction=0.0)),
    ("pybullet", "Bullet's solver at 200 iterations (numSolverIterations)", dict(solver_iterations=200)),
)


def render_both(triple: dict, object_hulls, left_hulls, right_hulls, cfg, path: Path) -> None:
    """One triple as our protocol (``cfg``) and the PyBullet original ran it: two strips of the
    same panels on one scale (``f2f_jax.sim.view.draw_strips``)."""
    from f2f_jax.bench import pybullet_runs as peer
    from f2f_jax.sim import view

    model = sim.build_model(object_hulls, left_hulls, right_hulls, cfg)
    ours = view.trial_strip(model, cfg, f"ours ({config.sim_preset_name(cfg)})")
    theirs = peer.render_original(object_hulls, left_hulls, right_hulls, cfg=cfg)
    view.draw_strips([ours, theirs], path, f"{triple['name']}, {triple['kind']} fingers", cols=7)


def run_ablations(outcomes: dict, kinds: list[str], inputs, fast, workers: int,
                  ablations=None) -> list[dict]:
    """Each of ``ablations`` (default ABLATIONS) on its side; prints a table and returns one dict
    per row, the first the unchanged protocols: side, label,
    changes, agreement (the changed side against the other side's unchanged outcomes, per trial),
    moved (share of the changed side's own trials that the change flipped), rates per kind
    (the changed side and the other, unchanged one), the changed side's outcomes."""
    import dataclasses

    objs, lefts, rights, obj_hulls, lh, rh = inputs
    shown = [k for k in FINGER_KINDS if k in kinds]
    rows = [dict(side="-", label="none (fast and the PyBullet peer as they are)", changes={},
                 agreement=_agreement(outcomes["fast"], outcomes["pybullet"]), moved=0.0,
                 rates={k: {s: _kind_rates(outcomes[s], kinds, k) for s in ("fast", "pybullet")}
                        for k in shown})]
    print(f"\nablations, one difference at a time ({len(kinds)} triples):", flush=True)
    for side, label, changes in ABLATIONS if ablations is None else ablations:
        t = time.perf_counter()
        if side == "ours":
            cfg = fast.replace(sim=dataclasses.replace(fast.sim, **changes))
            changed = sim.evaluate(objs, lefts, rights, cfg=cfg, threads=workers,
                                   object_hulls=obj_hulls, progress=False)
            own, other = outcomes["fast"], outcomes["pybullet"]
        else:
            changed, _ = run_peer(obj_hulls, lh, rh, fast, workers, changes)
            own, other = outcomes["pybullet"], outcomes["fast"]
        ours, theirs = (changed, other) if side == "ours" else (other, changed)
        rows.append(dict(side=side, label=label, changes=changes,
                         agreement=_agreement(changed, other), moved=1.0 - _agreement(changed, own),
                         rates={k: {"fast": _kind_rates(ours, kinds, k),
                                    "pybullet": _kind_rates(theirs, kinds, k)} for k in shown},
                         outcomes=["".join(map(str, row)) for row in changed],
                         seconds=time.perf_counter() - t))
        print(f"  {side:8s} {label[:60]:60s} {time.perf_counter() - t:5.0f} s", flush=True)
    print("\n| side | change | agreement | own trials moved | "
          + " | ".join(f"{k}: ours grasp/S/R | {k}: PyBullet" for k in shown) + " |")
    print("|---" * (4 + 2 * len(shown)) + "|")
    for r in rows:
        cells = []
        for k in shown:
            for s in ("fast", "pybullet"):
                v = r["rates"][k][s]
                cells.append(f"{v['grasp']:.3f} / {v['S']:.2f} / {v['R']:.2f}")
        print(f"| {r['side']} | {r['label']} | {100 * r['agreement']:.1f}% | "
              f"{100 * r['moved']:.1f}% | " + " | ".join(cells) + " |")
    return rows


def _agreement(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.asarray(a) == np.asarray(b)))


def _kind_rates(outcomes: np.ndarray, kinds: list[str], kind: str) -> dict:
    return rates(np.asarray(outcomes)[np.array(kinds) == kind].astype(bool))


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
    p.add_argument("--render", type=Path, default=None,
                   help="draw the first differing triple (imprint fingers where one differs) as "
                        "both simulators ran it, one strip each, to this PNG")
    p.add_argument("--ablations", nargs="*", default=None, metavar="WORD",
                   help="then each difference in ABLATIONS on its own side, judged against the "
                        "other side's unchanged outcomes (a table; ablations in --json); with "
                        "words, only the ablations whose label contains one of them")
    args = p.parse_args(argv)
    if args.n_objects < 1 or args.workers < 1:
        p.error("--n-objects and --workers must be >= 1")
    if args.objects is not None and not args.objects.is_dir():
        p.error(f"--objects {args.objects}: no such directory")
    if importlib.util.find_spec("pybullet") is None:  # the workers import pybullet
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
    by_kind = {}
    for kind in [*dict.fromkeys(kinds), "all"]:
        m = np.ones(len(kinds), bool) if kind == "all" else np.array(kinds) == kind
        by_kind[kind] = {s: rates(outcomes[s][m].astype(bool)) for s in SIMULATORS}
        by_kind[kind]["n"] = int(m.sum())

    print(f"\n{'kind':10s} {'n':>4s}  " + "  ".join(f"{s:>26s}" for s in SIMULATORS))
    print(f"{'':10s} {'':>4s}  " + "  ".join(f"{'grasp  trials    S     R':>26s}" for _ in SIMULATORS))
    for kind, r in by_kind.items():
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
        print(f"  {i:4d} {triples[i]['name']:28s} {kinds[i]:10s} fast {vector_text(outcomes['fast'][i])}"
              f"  pybullet {vector_text(outcomes['pybullet'][i])}")
    if args.render and differing:
        i = next((i for i in differing if kinds[i] == "imprint"), differing[0])
        render_both(triples[i], obj_hulls[i], lh[i], rh[i], presets["fast"], args.render)
        print(f"drew triple {i} ({triples[i]['name']}, {kinds[i]}) from both simulators to "
              f"{args.render}")
    ablations = None
    if args.ablations is not None:
        chosen = [a for a in ABLATIONS
                  if not args.ablations or any(w in a[1] for w in args.ablations)]
        ablations = run_ablations(outcomes, kinds, (objs, lefts, rights, obj_hulls, lh, rh),
                                  presets["fast"], args.workers, chosen)
    if args.json:
        args.json.write_text(json.dumps(dict(ablations=ablations,
            n=len(triples), kinds=args.kinds, objects=str(args.objects or "builtin"),
            config=args.config, agreement=stats, rates=by_kind, seconds=seconds,
            triples=[dict(object=tr["name"], kind=tr["kind"]) for tr in triples],
            outcomes={s: ["".join(map(str, row)) for row in outcomes[s]] for s in SIMULATORS},
            differing=[dict(index=i, object=triples[i]["name"], kind=kinds[i],
                            **{s: vector_text(outcomes[s][i]) for s in SIMULATORS})
                       for i in differing]), indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
