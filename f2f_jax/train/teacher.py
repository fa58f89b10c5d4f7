"""The simulator as the generator's teacher (``train.teacher = "simulator"``): expert iteration.

The fitness net cannot rank one object's designs at the data scales a CPU reaches
(docs/learning.md), so it cannot point the generator to better ones; the simulator can, which is
what ``design(verify=True)`` exploits per object at design time.  Here the generator amortises
that search over many objects.  Each cycle c:

1. every teacher object (the run's training objects and ``teacher_objects`` more built-in ones)
   gets ``teacher_candidates`` designs: the generator's own and its height-noise candidates
   (``nets.inference.propose``), and in cycle 1 also the imprint and its two variants
   (``geometry.fingers.IMPRINT_VARIANTS``); all are simulated by the run's simulator and appended to the
   grasp store, ``teacher_chunk`` objects per chunk (keyed, so a killed cycle resumes where it
   stopped and nothing simulated is lost);
2. each object's target is its best-simulated pair over cycles 1..c: most trials passed, ties to
   the imprint (an object keeps its imprint until a design passes strictly more); with
   ``teacher_copies`` the pair must also lead its imprint on moved copies (``confirm_targets``);
3. the fitness net trains on the teacher rows (all 11 trials; half of each batch teacher rows,
   half pretraining rows) except those of ``teacher_fn_holdout`` of the objects, on whose
   candidates its within-object Spearman is measured (``nets.inference.within_object_spearman``);
4. the generator is regressed onto the targets (the pretraining's loss, ``gn_imprint_step``) for
   ``teacher_epochs`` epochs at ``teacher_lr``.

``train.teacher = "imprint"`` is its control: step 4 alone, every target the object's imprint, the
same objects, batches and steps.  Randomness comes from (seed, "cycle", c, part, ...), as in
co-training, so a resumed run repeats what an uninterrupted one does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from tqdm.auto import tqdm

from f2f_jax.data import load_or_make_builtin_range
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import is_feasible, postprocess
from f2f_jax.geometry.fingers import IMPRINT_VARIANTS, imprint_candidates
from f2f_jax.nets.inference import (
    GENERATOR,
    GENERATOR_HEIGHT_NOISE,
    GENERATOR_NOISE,
    TrainedNets,
    predict,
    printed_copies,
    propose,
    within_object_spearman,
)
from f2f_jax.train import steps as S
from f2f_jax.train.epochs import LazyBatches, row_batches
from f2f_jax.train.run_data import read_rows
from f2f_jax.train.run_state import RunState

if TYPE_CHECKING:
    from f2f_jax.config import Config
    from f2f_jax.train.cotrain import CoTrainRun

TEACHERS = ("fitness", "simulator", "imprint")
IMPRINT = IMPRINT_VARIANTS[0][0]
CONFIRM_FILE = "teacher_confirm.json"  # in the run directory: the moved copies' outcomes


@dataclass
class TeacherSet:
    """The teacher objects: volumes [M, R, R, R] float16 (the table the rows' volumes share),
    names, and their imprint pairs (float16), the control's targets and the ties' winners;
    fn_holdout: [M] bool, the objects whose rows the fitness net never trains on."""

    objects: np.ndarray
    names: list[str]
    imprint_left: np.ndarray
    imprint_right: np.ndarray
    fn_holdout: np.ndarray


def check_teacher(t) -> list[str]:
    """Problems with a TrainConfig's teacher fields, as messages (none: it can run)."""
    bad = []
    if t.teacher not in TEACHERS:
        bad.append(f"train.teacher must be one of {TEACHERS}, got {t.teacher!r}")
    for name, low in (("teacher_objects", 0), ("teacher_candidates", 1), ("teacher_epochs", 1),
                      ("teacher_chunk", 1)):
        if getattr(t, name) < low:
            bad.append(f"train.{name} must be >= {low}, got {getattr(t, name)}")
    if t.teacher_lr is not None and not t.teacher_lr > 0:
        bad.append(f"train.teacher_lr must be > 0 (or None: train.lr), got {t.teacher_lr}")
    if not 0.0 <= t.teacher_fn_holdout < 1.0:
        bad.append(f"train.teacher_fn_holdout must be in [0, 1), got {t.teacher_fn_holdout}")
    if t.teacher_copies < 0:
        bad.append(f"train.teacher_copies must be >= 0 (0: exact targets), got {t.teacher_copies}")
    if not t.teacher_tolerance > 0:
        bad.append(f"train.teacher_tolerance must be > 0 (mm), got {t.teacher_tolerance}")
    if not t.teacher_min_lead >= 0:
        bad.append(f"train.teacher_min_lead must be >= 0 (trials of 11), got {t.teacher_min_lead}")
    return bad


def _held_out(name: str, seed: int, share: float) -> bool:
    digest = hashlib.sha256(f"teacher-fn\x00{seed}\x00{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2.0 ** 64 < share


def teacher_set(run: CoTrainRun, st: RunState) -> TeacherSet:
    """The run's teacher objects with their imprints, made once (the extra objects into the run's
    ``teacher_objects/``, resumable) and kept in ``st.teacher``."""
    if st.teacher is not None:
        return st.teacher
    t, data, g = run.cfg.train, st.data, run.cfg.geometry
    objects = [data.object_table[data.train_idx]]
    names = [data.names[i] for i in data.train_idx]
    if t.teacher_objects:
        extra, extra_names = load_or_make_builtin_range(
            run.dir / "teacher_objects", t.n_objects, t.teacher_objects, t.teacher_seed, g,
            progress=run.progress)
        objects.append(extra.astype(np.float16))  # exact: kept as float16
        names += extra_names
    clash = sorted(set(names[len(data.train_idx):]) & set(data.names))
    if clash or len(set(names)) != len(names):
        raise F2FError(f"teacher objects share names with the run's objects ({clash[:3]}); "
                       "choose train.teacher_seed or n_objects so that they do not overlap")
    table = np.concatenate(objects)
    lefts, rights = [], []
    for obj in tqdm(table, desc="teacher imprints", unit="obj", disable=not run.progress):
        left, right, _ = imprint_candidates(obj[None].astype(np.float32), g)
        lefts.append(left[0, 0].astype(np.float16))
        rights.append(right[0, 0].astype(np.float16))
    holdout = np.array([_held_out(n, run.seed, t.teacher_fn_holdout) for n in names])
    st.teacher = TeacherSet(table, names, np.stack(lefts), np.stack(rights), holdout)
    return st.teacher


def _candidates(run: CoTrainRun, st: RunState, objs: np.ndarray, c: int, j: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chunk j's designs in cycle c: object rows [N], lefts, rights, origins, feasible, each per
    design (the generator's candidates; in cycle 1 first the imprint variants that can be made)."""
    cfg = run.cfg
    k = cfg.train.teacher_candidates
    nets = TrainedNets(cfg, st.nets["gn"].variables, st.nets["fn"].variables)
    x = objs.astype(np.float32)
    lefts, rights = propose(nets, x, run.key("cycle", c, 4, j), k)
    feasible = postprocess(lefts, rights, cfg.geometry)
    noise = GENERATOR_HEIGHT_NOISE if cfg.net.generator == "heights" else GENERATOR_NOISE
    origins = np.array([[GENERATOR] + [noise] * (k - 1)] * len(objs))
    rows = np.repeat(np.arange(len(objs))[:, None], k, 1)
    parts = [(rows.ravel(), lefts.reshape(-1, *x.shape[1:]), rights.reshape(-1, *x.shape[1:]),
              origins.ravel(), feasible.ravel())]
    if c == 1:
        il, ir, made = imprint_candidates(x, cfg.geometry)
        ib, iv = np.nonzero(made)
        parts.insert(0, (ib, il[ib, iv], ir[ib, iv], np.array([IMPRINT_VARIANTS[v][0] for v in iv]),
                         np.ones(len(ib), bool)))  # an imprint is feasible by construction
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


def simulate_teacher(run: CoTrainRun, st: RunState, ts: TeacherSet, c: int) -> float:
    """Cycle c's designs of every teacher object, simulated and stored chunk by chunk (keys
    "teacher-c-j"); chunks a killed run finished are skipped.  Returns the seconds spent."""
    store, t = st.data.store, run.cfg.train
    done = store.done_keys()
    starts = range(0, len(ts.names), t.teacher_chunk)
    todo = [j for j in range(len(starts)) if f"teacher-{c}-{j}" not in done]
    start = time.perf_counter()
    bar = tqdm(total=len(starts), initial=len(starts) - len(todo), desc=f"cycle {c} teacher chunks",
               unit="chunk", disable=not run.progress)
    for j in todo:
        lo = starts[j]
        objs = ts.objects[lo:lo + t.teacher_chunk]
        rows, lefts, rights, origins, feasible = _candidates(run, st, objs, c, j)
        out = np.zeros((len(rows), run.cfg.sim.n_trials), np.uint8)  # infeasible: fails all
        if feasible.any():
            out[feasible] = run.simulate(objs[rows[feasible]].astype(np.float32), lefts[feasible],
                                         rights[feasible], f"cycle {c} teacher designs, chunk {j + 1}")
        store.append(objs[rows], lefts, rights, out, kind=list(origins),
                     names=[ts.names[lo + r] for r in rows], keys=[f"teacher-{c}-{j}"], cycle=c)
        bar.update(1)
    bar.close()
    return time.perf_counter() - start


def best_rows(rows: dict[str, np.ndarray], names: list[str], excluded: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per teacher object (``names``' order), the row of its best-simulated design: most trials
    passed; ties to the imprint, then to the earlier cycle and row; rows where ``excluded`` [rows]
    bool is set never count.  Returns (row index or -1 for an object without rows, its trials
    passed, the imprint's trials passed or -1 without one)."""
    where = {n: i for i, n in enumerate(names)}
    obj = np.array([where[str(n)] for n in rows["name"]], int)
    trials = rows["outcome"].sum(1).astype(int)
    is_imprint = rows["kind"] == IMPRINT
    # best first: trials descending, the imprint first, earlier cycle, earlier row
    order = np.lexsort((np.arange(len(obj)), rows["cycle"], ~is_imprint, -trials, obj))
    if excluded is not None:
        order = order[~np.asarray(excluded, bool)[order]]
    first = np.ones(len(order), bool)
    first[1:] = obj[order][1:] != obj[order][:-1]
    best = np.full(len(names), -1)
    best[obj[order][first]] = order[first]
    imprint = np.full(len(names), -1)
    imprint[obj[is_imprint]] = trials[is_imprint]
    passed = np.where(best >= 0, trials[np.maximum(best, 0)], -1)
    return best, passed, imprint


def teacher_targets(st: RunState, ts: TeacherSet, rows: dict[str, np.ndarray] | None,
                    chosen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The generator's targets (lefts, rights float16, one pair per teacher object) and what they
    are: each object's best-simulated pair over ``rows`` (None: the imprints, the control's), or
    the rows ``chosen`` [objects] picks (-1: the imprint; ``confirm_targets``' picks)."""
    left, right = ts.imprint_left.copy(), ts.imprint_right.copy()
    if rows is None:
        return left, right, {}
    best, passed, imprint = best_rows(rows, ts.names)
    better = (best >= 0) & (imprint >= 0) & (passed > imprint)
    if chosen is not None:
        best, better = np.asarray(chosen), np.asarray(chosen) >= 0
        passed = np.where(better, rows["outcome"][np.maximum(best, 0)].sum(1).astype(int), imprint)
    left[better] = rows["left"][best[better]]
    right[better] = rows["right"][best[better]]
    kinds = rows["kind"][best[better]]
    stats = {"improved_objects": int(better.sum()), "objects": len(ts.names),
             "target_trials": float(np.where(better, passed, np.maximum(imprint, 0)).mean()),
             "imprint_trials": float(np.maximum(imprint, 0).mean()),
             "improved_by_origin": {str(k): int(v) for k, v in zip(*np.unique(kinds, return_counts=True))}}
    return left, right, stats


def design_digest(left: np.ndarray, right: np.ndarray) -> str:
    """A pair of finger volumes' identity (their float16 bytes), as the confirmation file keys it."""
    h = hashlib.sha256(np.ascontiguousarray(left, np.float16).tobytes())
    h.update(np.ascontiguousarray(right, np.float16).tobytes())
    return h.hexdigest()[:24]


def _copy_seed(seed: int, name: str) -> list[int]:
    """The moved copies' fields of object ``name``: the same for each of its pairs and cycles."""
    return [seed, 0xC0F1, int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "big")]


def _read_confirmations(path) -> dict:
    if not path.exists():
        return {"imprints": {}, "designs": {}}
    return json.loads(path.read_text())


def _refused(book: dict, rows: dict, last_cycle: int, digests: dict) -> np.ndarray:
    """[rows] bool: the rows whose pair the confirmation refused in cycles <= ``last_cycle``."""
    refused: dict[str, set] = {}
    for key, e in book["designs"].items():
        if not e["kept"] and e["cycle"] <= last_cycle:
            name, digest = key.rsplit(":", 1)
            refused.setdefault(name, set()).add(digest)
    out = np.zeros(len(rows["name"]), bool)
    for i in np.flatnonzero(np.isin(rows["name"].astype(str), list(refused))):
        if i not in digests:
            digests[i] = design_digest(rows["left"][i], rows["right"][i])
        out[i] = digests[i] in refused[str(rows["name"][i])]
    return out


def confirm_targets(run: CoTrainRun, ts: TeacherSet, c: int, rows: dict) -> tuple[np.ndarray, dict]:
    """Cycle c's targets confirmed on moved copies (``train.teacher_copies`` > 0).

    Each object's best pair over ``rows`` (as ``best_rows``; pairs refused in earlier cycles left
    out) that passes more trials than its imprint, if not yet confirmed, is simulated on
    ``teacher_copies`` copies of its fingers, each moved by a smooth field of ``teacher_tolerance``
    mm (``nets.inference.printed_copies``), and so is the imprint once, on the same fields.  The pair
    is kept when its mean over the copies leads the imprint's by >= ``teacher_min_lead`` trials
    and by more than none; a refused pair is never an object's target again.  The outcomes are
    written to the run's ``teacher_confirm.json`` after each chunk of ``teacher_chunk`` objects, so
    a killed cycle resumes without simulating them again.  Returns, per object, the row of its
    target (-1: the imprint) and the figures of the cycle's confirmation."""
    t, g = run.cfg.train, run.cfg.geometry
    path = run.dir / CONFIRM_FILE
    book = _read_confirmations(path)
    digests: dict[int, str] = {}
    start = time.perf_counter()

    def key(o: int, i: int) -> str:
        if i not in digests:
            digests[i] = design_digest(rows["left"][i], rows["right"][i])
        return f"{ts.names[o]}:{digests[i]}"

    best, passed, imprint = best_rows(rows, ts.names, _refused(book, rows, c - 1, digests))
    lead = np.flatnonzero((best >= 0) & (imprint >= 0) & (passed > imprint))
    todo = [o for o in lead if key(o, best[o]) not in book["designs"]]
    n_eval = 0
    chunks = range(0, len(todo), t.teacher_chunk)
    for j in tqdm(chunks, desc=f"cycle {c} targets on moved copies", unit="chunk",
                  disable=not run.progress or not todo):
        part = todo[j:j + t.teacher_chunk]
        objs, lefts, rights, what = [], [], [], []  # what: (object, "target" or "imprint")
        for o in part:
            name, seed = ts.names[o], _copy_seed(run.seed, ts.names[o])
            pairs = [("target", rows["left"][best[o]], rows["right"][best[o]])]
            if name not in book["imprints"]:
                pairs.append(("imprint", ts.imprint_left[o], ts.imprint_right[o]))
            for role, left, right in pairs:
                ml, mr = printed_copies(left[None].astype(np.float32), right[None].astype(np.float32),
                                        t.teacher_tolerance, g, t.teacher_copies, seed)
                objs += [ts.objects[o]] * t.teacher_copies
                lefts.append(ml)
                rights.append(mr)
                what.append((o, role))
        out = run.simulate(np.stack(objs).astype(np.float32), np.concatenate(lefts), np.concatenate(rights),
                           f"cycle {c} targets and imprints on {t.teacher_copies} moved copies, "
                           f"chunk {j // t.teacher_chunk + 1}")
        n_eval += len(out)
        trials = np.asarray(out).sum(1).reshape(len(what), t.teacher_copies)
        for (o, role), tr in zip(what, trials):
            if role == "imprint":
                book["imprints"][ts.names[o]] = tr.tolist()
        for (o, role), tr in zip(what, trials):
            if role == "target":
                gain = float(tr.mean() - np.mean(book["imprints"][ts.names[o]]))
                book["designs"][key(o, best[o])] = {
                    "cycle": c, "trials": tr.tolist(), "lead": gain,
                    "kept": bool(gain > 0 and gain >= t.teacher_min_lead)}
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(book))
    # the targets: the best pair of each object with this cycle's refusals left out, if confirmed
    best, passed, imprint = best_rows(rows, ts.names, _refused(book, rows, c, digests))
    chosen = np.full(len(ts.names), -1)
    for o in np.flatnonzero((best >= 0) & (imprint >= 0) & (passed > imprint)):
        e = book["designs"].get(key(o, best[o]))
        if e is not None and e["kept"]:
            chosen[o] = best[o]
    made = [e for e in book["designs"].values() if e["cycle"] == c]
    kept_leads = [book["designs"][key(o, chosen[o])]["lead"] for o in np.flatnonzero(chosen >= 0)]
    return chosen, {"exact_improved_objects": int(len(lead)), "confirmed_pairs": len(todo),
                    "confirm_evaluations": n_eval, "confirm_seconds": round(time.perf_counter() - start, 2),
                    "kept_this_cycle": sum(e["kept"] for e in made),
                    "refused_this_cycle": sum(not e["kept"] for e in made),
                    "target_lead_on_copies": float(np.mean(kept_leads)) if kept_leads else None}


def teacher_generator_cfg(cfg: Config) -> Config:
    """The config of the generator's steps onto the targets: ``teacher_lr`` when set, else
    ``lr``; the optimiser state is kept (its structure does not depend on the rate)."""
    t = cfg.train
    if t.teacher_lr is None or t.teacher_lr == t.lr:
        return cfg
    return cfg.replace(train=dataclasses.replace(t, lr=t.teacher_lr))


def train_generator(run: CoTrainRun, st: RunState, ts: TeacherSet, c: int, left: np.ndarray,
                    right: np.ndarray) -> dict:
    """``teacher_epochs`` epochs of the generator's regression onto the targets (``gn_passes``
    capped passes each, as its pretraining), at ``teacher_lr``.  Returns the last epoch's record."""
    t = run.cfg.train
    step = S.gn_imprint_step(teacher_generator_cfg(run.cfg))
    rec = {}
    for epoch in range(1, t.teacher_epochs + 1):
        rng = run.rng("cycle", c, 2, epoch)
        index = [b for _ in range(t.gn_passes) for b in run.batches(len(ts.names), t.fn_batch_size, rng)]
        batches = LazyBatches(lambda i, b: S.shard(*(a[b].astype(np.float32)
                                                     for a in (ts.objects, left, right))), index)
        rec = run.epoch(st, "gn", step, batches, epoch, c, desc=f"cycle {c} GN epoch {epoch}")
        run.log(rec)
    return rec


def train_fitness(run: CoTrainRun, st: RunState, ts: TeacherSet, c: int, rows: dict) -> dict:
    """The fitness net on the teacher rows of the objects it may see (half of each batch; the
    other half pretraining rows), ``teacher_epochs`` epochs; then its within-object Spearman on
    cycle c's candidates of the objects it never saw.  Returns those figures."""
    t, pre = run.cfg.train, st.data.pre
    where = {n: i for i, n in enumerate(ts.names)}
    obj = np.array([where[str(n)] for n in rows["name"]], int)
    seen = np.flatnonzero(~ts.fn_holdout[obj])
    half = max(1, t.cotrain_batch_size // 2)
    step = S.fn_step(run.cfg)
    rec = {}
    for epoch in range(1, t.teacher_epochs + 1):
        rng = run.rng("cycle", c, 1, epoch)
        nb = [seen[b] for b in run.batches(len(seen), half, rng)]
        ob = [rng.choice(len(pre["outcome"]), len(b)) for b in nb]
        rec = run.epoch(st, "fn", step, row_batches(rows, pre, idx_batches=list(zip(nb, ob))), epoch, c,
                        desc=f"cycle {c} FN epoch {epoch}")
        run.log(rec)
    # within-object ranking of cycle c's candidates of the unseen objects (the generator's and
    # its noise candidates: K per object in every cycle)
    mine = np.flatnonzero(ts.fn_holdout[obj] & (rows["cycle"] == c)
                          & np.isin(rows["kind"], [GENERATOR, GENERATOR_NOISE, GENERATOR_HEIGHT_NOISE]))
    k = t.teacher_candidates
    out = {"fn_loss": rec.get("loss")}
    if len(mine) < 2 * k or k < 2:
        return {**out, "fn_spearman": None, "fn_ranked_objects": 0}
    mine = mine[np.lexsort((mine, obj[mine]))]
    groups = obj[mine].reshape(-1, k)
    if not (groups == groups[:, :1]).all():
        raise F2FError(f"cycle {c}: the held-out objects' candidates are not {k} per object")
    nets = TrainedNets(run.cfg, st.nets["gn"].variables, st.nets["fn"].variables)
    r = ts.objects.shape[1:]
    pred = predict(nets, ts.objects[groups[:, 0]].astype(np.float32),
                   rows["left"][mine].astype(np.float32).reshape(-1, k, *r),
                   rows["right"][mine].astype(np.float32).reshape(-1, k, *r))
    rho = within_object_spearman(pred, rows["outcome"][mine].reshape(-1, k, rows["outcome"].shape[1]))
    ranked = np.isfinite(rho)
    return {**out, "fn_spearman": float(rho[ranked].mean()) if ranked.any() else None,
            "fn_ranked_objects": int(ranked.sum()), "fn_holdout_objects": int(len(groups))}


def run_teacher_cycle(run: CoTrainRun, st: RunState, c: int) -> dict:
    """Cycle ``c`` of a run whose generator's teacher is the simulator (or, for the control, the
    imprints): simulate, pick targets, train; logged, checkpointed, its summary returned."""
    t = run.cfg.train
    start = time.perf_counter()
    ts = teacher_set(run, st)
    summary = {"stage": "cycle", "cycle": c, "teacher": t.teacher, "teacher_objects": len(ts.names)}
    if t.teacher == "simulator":
        summary["sim_seconds"] = round(simulate_teacher(run, st, ts, c), 2)
        rows = read_rows(st.data.store, lambda cyc, k: 1 <= cyc <= c, objects=(ts.objects, ts.names))
        new = rows["cycle"] == c
        own = np.flatnonzero(new & (rows["kind"] == GENERATOR))  # the generator's own designs
        g = run.cfg.geometry
        summary.update(designs=int(new.sum()), designs_so_far=len(rows["outcome"]),
                       success=rows["outcome"][own].mean(0).round(4).tolist(),
                       feasible=float(np.mean([is_feasible(rows["left"][i].astype(np.float32), g)
                                               and is_feasible(rows["right"][i].astype(np.float32), g)
                                               for i in own])))
        chosen = None
        if t.teacher_copies:
            chosen, confirmed = confirm_targets(run, ts, c, rows)
            summary.update(confirmed)
        left, right, stats = teacher_targets(st, ts, rows, chosen)
        summary.update(stats)
        summary.update(train_fitness(run, st, ts, c, rows))
        del rows
    else:
        left, right, _ = teacher_targets(st, ts, None)
        summary.update(designs=0)
    rec = train_generator(run, st, ts, c, left, right)
    summary.update(gn_loss=rec.get("loss"), gn_epochs=t.teacher_epochs,
                   seconds=round(time.perf_counter() - start, 2))
    run.log(summary)
    run.save(st, "cycle", 0, c)
    return summary
