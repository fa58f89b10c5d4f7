"""Agreement between two simulators (or presets) on the same triples, as the benchmarks measure it.

Triples are made as the pretraining dataset makes them (``dataset.pretraining_pairs``: imprint,
WSG50 and cut pairs) plus designed-looking fingers (an imprint plus a smooth random field,
``dataset.perturbed_finger``): ``mixed_triples`` over any object set (``load_objects``: builtin objects or a
mesh directory), ``builtin_triples`` over builtin objects only.  ``agreement_stats`` and
``agreement_report`` compare two [N, 11] outcome arrays; ``rates`` and ``vector_text`` summarise
and print them.  Used by ``benchmarks/sim_agreement.py``, ``sim_throughput.py`` and ``mjx_contacts.py``, and by
``research/sim_retest.py`` and ``research/protocol_fidelity.py``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES
from f2f_jax.data import builtin_object, builtin_objects, load_mesh, mesh_files
from f2f_jax.dataset.pretraining import KINDS, PERTURBED, pretraining_pairs
from f2f_jax.errors import F2FError
from f2f_jax.geometry import mesh_to_tsdf
from f2f_jax.geometry.finger_tiling import finger_hulls
from f2f_jax.geometry.pieces import object_pieces, object_pieces_many

FINGER_KINDS = (*KINDS, PERTURBED)
SHOWN_DIFFERING = 10
TRIALS_S = [i for i, name in enumerate(TRIAL_NAMES) if name.startswith("S")]
TRIALS_R = [i for i, name in enumerate(TRIAL_NAMES) if name.startswith("R")]


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


def mixed_triples(tsdfs: np.ndarray, names: list[str], n: int, seed: int, cfg) -> list[dict]:
    """The first ``n`` triples over objects x ``FINGER_KINDS`` (fewer when the set runs out).

    Each is a dict: object (index into tsdfs), name, kind, left, right ([R, R, R] float32).
    Object i's pairs are ``pretraining_pairs``' with one cut and one perturbed pair, as the
    pretraining dataset of seed ``seed`` makes them (``default_rng([seed, i])``, the perturbed pair
    from ``default_rng([seed, i, 1])``); a cut or perturbed pair that cannot be made feasibly is
    skipped.
    """
    triples = []
    for i in range(len(tsdfs)):
        pairs = pretraining_pairs(tsdfs, i, np.random.default_rng([seed, i]), cfg, n_cut=1, n_perturbed=1,
                                  perturb_rng=np.random.default_rng([seed, i, 1]))
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


def rates(out: np.ndarray) -> dict:
    """Rates of [m, 11] bool outcomes: grasp success, mean trials passed, mean S and R success."""
    return dict(grasp=float(out[:, 0].mean()), trials=float(out.sum(1).mean()),
                S=float(out[:, TRIALS_S].mean()), R=float(out[:, TRIALS_R].mean()))


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
    by_kind = {k: {la: rates(a[m]), lb: rates(b[m])} for k, m in groups.items()}
    by_kind["all"] = {la: rates(a), lb: rates(b)}
    gaps = [(abs(r[la]["grasp"] - r[lb]["grasp"]), abs(r[la]["trials"] - r[lb]["trials"]))
            for k, r in by_kind.items() if k != "all"]
    ga, gb = a[:, 0], b[:, 0]
    return dict(
        agreement_per_trial=float(same.mean()),
        agreement_per_trial_kind={name: float(x) for name, x in zip(TRIAL_NAMES, same.mean(0))},
        agreement_per_kind={k: float(same[m].mean()) for k, m in groups.items()},
        agreement_vectors=float(same.all(1).mean()),
        rates=by_kind,
        grasp_confusion=[[int((~ga & ~gb).sum()), int((~ga & gb).sum())],
                         [int((ga & ~gb).sum()), int((ga & gb).sum())]],
        rate_gap_max=dict(grasp=100 * max(g for g, _ in gaps),
                          trials=100 * max(t for _, t in gaps) / len(TRIAL_NAMES)),
    )


def vector_text(row) -> str:
    """An outcome vector as "grasp S1..S4 R-30..R+30" digits."""
    s = "".join(str(int(v)) for v in row)
    return f"{s[0]} {s[1:5]} {s[5:]}"


def render_differing(triples, differing, presets, out_dir: Path) -> None:
    """Draw each differing triple with each preset: ``out_dir/<index>_<kind>_<label>.png``."""
    from f2f_jax.sim.view import render_trials  # matplotlib (its pyplot backend): only when drawing

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
            print(f"  drew #{d['index']} with {label} to {path} (outcome {vector_text(render_trials(model, cfg, path))})")


def builtin_triples(n: int, seed: int, cfg, kinds=KINDS):
    """N (object, left, right) triples from builtin objects, pairs as the pretraining dataset makes
    them (imprint, WSG50, one cut pair per object, in that order, filtered to ``kinds``).

    Returns (object_tsdfs [M, R, R, R] of the M objects used, triples: list of dicts with keys
    object (index into object_tsdfs), name, kind, left, right [R, R, R] float32).
    Object i is ``builtin_object(i, seed)``; cut pairs draw their shapes from the same M objects
    with ``np.random.default_rng(seed)``, so the set depends only on (n, seed, kinds, cfg).
    """
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    kinds = tuple(kinds)
    unknown = set(kinds) - set(KINDS)
    if unknown:
        raise ValueError(f"unknown pair kinds {sorted(unknown)}; choose from {KINDS}")
    tsdfs, names = [], []
    n_objects = math.ceil(n / len(kinds))
    while True:
        while len(tsdfs) < n_objects:
            mesh = builtin_object(len(tsdfs), seed)
            tsdfs.append(mesh_to_tsdf(mesh, cfg.geometry))
            names.append(str(mesh.metadata.get("name", f"builtin/{len(names):04d}")))
        pool = np.stack(tsdfs)
        rng = np.random.default_rng(seed)
        triples = []
        for i in range(len(pool)):
            for left, right, kind in pretraining_pairs(pool, i, rng, cfg, n_cut=1 if "cut" in kinds else 0):
                if kind in kinds:
                    triples.append(dict(object=i, name=names[i], kind=kind,
                                        left=np.asarray(left, np.float32), right=np.asarray(right, np.float32)))
        if len(triples) >= n:
            return pool, triples[:n]
        n_objects += max(1, math.ceil((n - len(triples)) / len(kinds)))  # a cut pair was skipped


def agreement_report(mj: np.ndarray, mx: np.ndarray) -> dict:
    """Agreement of two [N, 11] outcome arrays: per trial, overall, whole vectors, grasp confusion."""
    same = mj == mx
    g_mj, g_mx = mj[:, 0].astype(bool), mx[:, 0].astype(bool)
    both = g_mj & g_mx
    return dict(
        per_trial=[float(x) for x in same.mean(0)],
        agreement=float(same.mean()),
        whole_vectors=float(same.all(1).mean()),
        grasp_confusion=dict(both_hold=int(both.sum()), only_mujoco=int((g_mj & ~g_mx).sum()),
                             only_mjx=int((~g_mj & g_mx).sum()), neither=int((~g_mj & ~g_mx).sum())),
        # trials 1..10 where both held the grasp (elsewhere they are 0 == 0 by the protocol)
        per_trial_both_held=[float(x) for x in same[both].mean(0)] if both.any() else None,
    )
