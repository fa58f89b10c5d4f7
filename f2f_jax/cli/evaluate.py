"""The paper's Table 1 and Table 2 for a co-training run (or the baselines alone).

    python experiments/evaluate.py                          # WSG50, flat pads, Imprint; 12 built-in objects
    python experiments/evaluate.py --run-dir runs/cotrain   # + RandEmb+FN, Fit2Form; held-out objects
    python experiments/evaluate.py --run-dir runs/cotrain --extra "Fit2Form GS=runs/gs" \\
        --extra ImpGN=runs/impgn --design-search 64 --objects 64 --tables 1,2
    python experiments/evaluate.py --run-dir runs/cotrain --extra "cycle 0=runs/cotrain/pretrained" \\
        --fresh 48 --seed 7 --neighbourhood 8 --tables 1 --no-randemb   # did co-training help?
    python experiments/evaluate.py --run-dir runs/cotrain --executor ray   # trials on a Ray cluster

With --run-dir the held-out objects of the run (DIR/objects, its fixed split) are evaluated and the
run's newest checkpoint gives the rows "Fit2Form" (or "Fit2Form GS", ... after the run's objectives)
and "RandEmb+FN" (its shape decoder and fitness net without the generator).  Without a checkpoint
only the baselines are run: "WSG50" (Schunk's standard WSG-FMF fingers, the paper's baseline; the
mesh comes with the pybullet extra, and the row is skipped with a note without it), "Flat pads"
(ideal flat fingertips, ours) and "Imprint".  Each --extra NAME=RUN_DIR adds a Table 1 row from
another run's checkpoint (ablations).  Table 2 has the paper's rows: WSG50, Imprint and the run's
own row.
--neighbourhood K compares the generators (the run's and the extras'): K candidates per object
each, all simulated, and the run's gain over each extra paired over objects with a bootstrap
interval; --fresh N adds N never-seen built-in objects to the run's held-out ones.
--checkpoint DIR takes the nets from DIR/checkpoints instead of the run's newest: RUN_DIR/pretrained
scores the run's pretrained generator and fitness net on its held-out objects.
--fitness-ranking K simulates K candidates per object of the run's generator and asks whether its
fitness net ranks them as the simulator does; every --extra's fitness net scores the same
candidates, and the run's within-object Spearman minus each one's is printed paired over objects:

    python experiments/evaluate.py --run-dir runs/a --extra "b=runs/b" --fitness-ranking 16 \
        --fresh 48 --seed 7 --tables 1 --no-randemb   # does run a's fitness net rank better than b's?
--printed MM adds Table 1 as printed: every row's fingers, both of them, moved by a smooth random
field of standard deviation MM millimetres (a printer's error; 0.3 moves the surface ~0.15 mm on
average), --printed-copies copies per object, the same fields for every row (paired).  A simulated
trial turns on tenths of a millimetre of finger, so the rows chosen by simulation (--design-search)
report their own luck in Table 1; here they are scored on fingers they were not chosen with.
Writes table1.{md,csv,png}, table2.{md,csv,png} (table1_printed.* with --printed) and results.json
into --out (default DIR/eval, or runs/eval without a run) and prints the markdown.

Nothing finished is lost to a kill: each row's designs, its outcomes in each table and the
candidates --neighbourhood and --fitness-ranking simulate are saved in OUT/.steps as they end (``f2f_jax.tables.steps``), and the same command run again does only what
is missing.  A command that adds rows (another --extra, --design-search, Table 2) reuses the rows
already simulated with the same objects, settings and code; --no-resume starts afresh.  The
designs are deleted once results.json is written; the outcomes (bytes per object) stay.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from f2f_jax import config
from f2f_jax import tables as E
from f2f_jax.cli import reproducible
from f2f_jax.data import builtin_objects, held_out_objects
from f2f_jax.designer import design, printed_copies
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import mesh_to_tsdf
from f2f_jax.sim import ray_executor
from f2f_jax.tables import steps
from f2f_jax.tables.seeds import FRESH_PREFIX, fresh_source
from f2f_jax.train.checkpoint import config_from_dict, load_trained_nets


def _fail(msg: str) -> int:
    print(f"evaluate: error: {msg}", file=sys.stderr)
    return 2


def _say(msg: str) -> None:
    print(f"evaluate: {msg}", file=sys.stderr, flush=True)


def _run_config(run_dir: Path):
    """The Config recorded in a run's run.json, or None."""
    path = run_dir / "run.json"
    if not path.exists():
        return None
    return config_from_dict(json.loads(path.read_text())["config"])


def _builtin_objects(n: int, seed: int, cfg):
    meshes = builtin_objects(n, seed=seed)
    tsdfs = [mesh_to_tsdf(m, cfg.geometry) for m in tqdm(meshes, desc="objects -> TSDF", unit="obj")]
    return np.stack(tsdfs), [m.metadata.get("name", f"object{i}") for i, m in enumerate(meshes)]


def _load_trained_nets(run_dir: Path):
    """(TrainedNets, None) or (None, why not)."""
    try:
        return load_trained_nets(run_dir), None
    except (F2FError, FileNotFoundError) as exc:
        return None, str(exc)


# The flags that add a measurement of K candidates (or N objects): (flag, metavar, help)
COUNT_FLAGS = (
    ("--design-search", "K", "add the rows 'Fit2Form + search (K, verify)' (f2f_jax.design with the "
                             "generator's K candidates) and 'Design pool (K + imprints, verify)' (the "
                             "same plus the imprint pair and its variants: design()'s default)"),
    ("--fitness-ranking", "K", "also measure how well the fitness net ranks K candidate designs per "
                               "object (all simulated): within-object Spearman, its pick vs the best; "
                               "every --extra's fitness net scores the same candidates, paired"),
    ("--neighbourhood", "K", "simulate K candidates per object (own design + K-1 latent perturbations) "
                             "of the run and of every --extra; print each one's trials passed and the "
                             "run's paired gain over each --extra with a 95%% bootstrap interval"),
    ("--fresh", "N", "with --run-dir: add N new built-in objects (drawn with --seed, which must "
                     "differ from the run's) to its held-out ones"),
)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", default=None, help="a co-training run directory (objects + checkpoints)")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="with --run-dir: the nets of DIR/checkpoints instead of the run's newest, e.g. "
                        "RUN_DIR/pretrained (the end of its pretraining: its ImpGN and pretrained "
                        "fitness net) on the run's held-out objects")
    p.add_argument("--extra", action="append", default=[], metavar="NAME=RUN_DIR",
                   help="another run's checkpoint as a Table 1 row (repeatable), e.g. 'Fit2Form GS=runs/gs'")
    p.add_argument("--objects", type=int, default=None,
                   help="cap on held-out objects (default: all of them; 12 built-in ones without a run)")
    p.add_argument("--tables", default="1,2", help="which tables: 1, 2 or 1,2")
    p.add_argument("--out", default=None, help="output directory (default RUN_DIR/eval, or runs/eval)")
    p.add_argument("--config", default=None,
                   help="tiny | default | workstation | paper: the simulator settings (default: the run's, else default)")
    for flag, metavar, text in COUNT_FLAGS:
        p.add_argument(flag, type=int, default=None, metavar=metavar, help=text)
    p.add_argument("--printed", type=float, default=None, metavar="MM",
                   help="add Table 1 with every row's fingers moved by a smooth random field of this "
                        "standard deviation in mm (a printer's error, e.g. 0.3), --printed-copies "
                        "copies per object, paired across rows")
    p.add_argument("--printed-copies", type=int, default=4, metavar="J",
                   help="moved copies per object and row for --printed (default 4)")
    p.add_argument("--backend", choices=list(config.BACKENDS), default="mujoco")
    p.add_argument("--sim-preset", default=None, choices=sorted(config.SIM_PRESETS),
                   help="simulation preset (config.SIM_PRESETS; default: the run's config's)")
    p.add_argument("--randemb-steps", type=int, default=200,
                   help="RandEmb+FN optimisation steps (paper: 200)")
    p.add_argument("--randemb-samples", type=int, default=4, help="RandEmb+FN random starts per object")
    p.add_argument("--no-randemb", action="store_true", help="skip the RandEmb+FN row (slow on a CPU)")
    p.add_argument("--seed", type=int, default=0, help="built-in objects, RandEmb keys, position shifts")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--no-resume", action="store_true",
                   help="start afresh: delete the steps an earlier call saved in OUT/.steps instead of "
                        "taking them up (by default a killed or extended evaluation continues)")
    reproducible.add_cli_argument(p)
    ray_executor.add_cli_arguments(p)
    return p


def _check(args) -> tuple[str | None, list[int], list[tuple[str, Path]]]:
    """(error or None, the tables asked for, the --extra rows as (name, run dir))."""
    try:
        tables = sorted({int(t) for t in args.tables.split(",") if t.strip()})
    except ValueError:
        return f"--tables {args.tables!r}: a comma-separated list of 1 and 2", [], []
    checks = [
        (not tables or not set(tables) <= {1, 2}, f"--tables {args.tables!r}: choose 1, 2 or 1,2"),
        (args.config is not None and args.config not in config.CONFIGS,
         f"unknown --config {args.config!r}; choose one of {', '.join(config.CONFIGS)}"),
        (args.objects is not None and args.objects < 1, "--objects must be at least 1"),
        (args.randemb_steps < 0 or args.randemb_samples < 1,
         "--randemb-steps must be >= 0 and --randemb-samples >= 1"),
        (args.design_search is not None and args.design_search < 1, "--design-search K needs K >= 1"),
        (args.fitness_ranking is not None and args.fitness_ranking < 2,
         "--fitness-ranking K needs K >= 2 candidates to rank"),
        (args.neighbourhood is not None and args.neighbourhood < 1, "--neighbourhood K needs K >= 1"),
        (args.printed is not None and not 0 < args.printed < float("inf"),
         "--printed MM needs a finite MM > 0 (the moving field's standard deviation, mm)"),
        (args.printed is not None and args.printed_copies < 1, "--printed-copies J needs J >= 1"),
        (args.printed is not None and 1 not in tables,
         "--printed rescores Table 1's rows: add 1 to --tables"),
        (args.fresh is not None and (args.fresh < 1 or not args.run_dir),
         "--fresh N needs N >= 1 and --run-dir"),
        (args.checkpoint is not None and not args.run_dir,
         "--checkpoint DIR needs --run-dir (whose held-out objects it is scored on)"),
        (args.checkpoint is not None and not (Path(args.checkpoint).expanduser() / "checkpoints").is_dir(),
         f"--checkpoint {args.checkpoint}: no checkpoints/ directory in it (e.g. RUN_DIR/pretrained)"),
    ]
    for bad, message in checks:
        if bad:
            return message, [], []
    extras = []
    for item in args.extra:
        name, sep, path = item.partition("=")
        if not sep or not name.strip() or not path.strip():
            return f"--extra {item!r}: expected NAME=RUN_DIR", [], []
        if not Path(path).expanduser().is_dir():
            return f"--extra {item!r}: no such directory {path}", [], []
        extras.append((name.strip(), Path(path).expanduser()))
    if args.executor == "ray" and args.backend != "mujoco":
        return f"--executor ray distributes the mujoco backend; drop --backend {args.backend}", [], []
    return None, tables, extras


def _objects(args, run_dir: Path | None, cfg):
    """(objects [N, R, R, R], names, what they are) or raises ValueError with the message."""
    if run_dir is None:
        objects, names = _builtin_objects(args.objects or 12, args.seed, cfg)
        return objects, names, f"built-in objects (seed {args.seed})"
    source = run_dir / "objects" / "source.json"
    meta = json.loads(source.read_text()) if source.exists() else {}
    if args.fresh and meta.get("source") == "builtin" and meta.get("seed") == args.seed:
        raise ValueError(f"--fresh with --seed {args.seed}: the run made its built-in objects with "
                         "that seed, so they would not be new; pick another --seed")
    try:
        objects, names = held_out_objects(run_dir, cfg.geometry)
    except FileNotFoundError as exc:
        raise ValueError(str(exc)) from None
    what = f"held-out objects of {run_dir}"
    if args.fresh:
        new, new_names = _builtin_objects(args.fresh, args.seed, cfg)
        objects = np.concatenate([objects[: args.objects], new])
        names = list(names[: args.objects]) + [f"{FRESH_PREFIX}{n}" for n in new_names]
        what += f" + {fresh_source(args.fresh, args.seed)}"
    elif args.objects is not None:
        objects, names = objects[: args.objects], names[: args.objects]
    return objects, names, what


class _Rows:
    """The designers of Table 1, the rows of Table 2, notes under the tables, and the nets that
    --fitness-ranking and --neighbourhood measure."""

    def __init__(self):
        self.designers, self.table2, self.notes = {}, [], []
        self.pool_origins = []  # FingerPair.origin of the design pool's picks, one per object
        self.pool_name, self.store = None, None  # the pool row; the StepStore (set in main)
        self.ranked, self.generators = None, {}
        self.judges = {}  # --extra nets whose fitness nets also score --fitness-ranking's candidates
        # {row: what makes its fingers}: with the objects and config, names its saved steps
        self.recipes: dict[str, str] = {}


def _nets_recipe(nets) -> str:
    """What a checkpoint's designs depend on: its nets' sizes and every parameter."""
    from f2f_jax.tables.steps import tree_digest

    return f"{nets.config.net!r} {tree_digest({'g': nets.generator, 'f': nets.fitness})}"


def _baseline_rows(rows: _Rows, cfg) -> None:
    try:
        rows.designers["WSG50"] = E.wsg_fmf_designer(cfg)
        rows.recipes["WSG50"] = "WSG-FMF fingers"
        rows.table2.append("WSG50")
        rows.notes.append("WSG50: Schunk's standard WSG-FMF fingers (the mesh pybullet_data ships; "
                          "faces meet at the object's mid-plane at full closure, as every finger "
                          "here); Flat pads: ideal flat fingertips (ours, not in the paper)")
    except ImportError as exc:  # MissingExtraError: the mesh ships with pybullet
        _say(f"WSG50 row (WSG-FMF fingers) skipped: {exc}")
        rows.notes.append(f"WSG50 (WSG-FMF fingers) not run: {exc}")
    rows.designers["Flat pads"] = E.wsg50_designer(cfg)
    rows.designers["Imprint"] = E.imprint_designer(cfg)
    rows.recipes.update({"Flat pads": "flat pads", "Imprint": "imprint"})
    rows.table2.append("Imprint")


def _search_rows(rows: _Rows, nets, recipe: str, args) -> None:
    """--design-search K: f2f_jax.design on the generator's K candidates, then with the imprints."""
    k = args.design_search
    search = functools.partial(design, params=nets, candidates=k, verify=True,
                               backend=args.backend, executor=args.executor,
                               progress=False if args.quiet else None)
    name = f"Fit2Form + search ({k}, verify)"  # the generator's candidates only
    rows.designers[name] = E.pair_designer(functools.partial(search, imprint=False), batched=True,
                                           desc=name)
    rows.recipes[name] = f"search {k} without imprints, {recipe}"
    rows.table2.append(name)
    pool_name = f"Design pool ({k} + imprints, verify)"  # design()'s default with verify
    rows.recipes[pool_name] = f"search {k} with imprints, {recipe}"
    rows.pool_name = pool_name

    def pool(objs):
        pairs = search(objs, imprint=True)
        rows.pool_origins = [pair.origin for pair in pairs]
        if rows.store is not None:
            rows.store.save("origins", pool_name, origins=np.array(rows.pool_origins))
        return pairs

    rows.designers[pool_name] = E.pair_designer(pool, batched=True, desc=pool_name)
    rows.table2.append(pool_name)


def _model_rows(rows: _Rows, args, run_dir: Path | None, extras) -> None:
    """The run's checkpoint (Fit2Form, RandEmb+FN, search rows) and every --extra's."""
    nets = None
    if run_dir is not None:
        source = Path(args.checkpoint).expanduser() if args.checkpoint else run_dir
        nets, why = _load_trained_nets(source)
        if nets is None:
            _say(f"no usable checkpoint in {source} ({why}): running the baseline rows only")
    if nets is not None:
        row = E.OBJECTIVE_ROWS.get(nets.objectives, f"Fit2Form ({nets.objectives})")
        _say(f"{row}: {nets.source}")
        recipe = _nets_recipe(nets)  # what this checkpoint's rows' designs depend on
        if not args.no_randemb:
            rows.designers["RandEmb+FN"] = E.random_embedding_designer(
                nets, jax.random.key(args.seed), samples=args.randemb_samples,
                steps=args.randemb_steps)
            rows.recipes["RandEmb+FN"] = (f"randemb {args.randemb_steps} steps {args.randemb_samples} "
                                          f"samples seed {args.seed}, {recipe}")
        rows.designers[row] = E.nets_designer(nets)
        rows.recipes[row] = f"generator, {recipe}"
        rows.table2.append(row)
        if args.design_search:
            _search_rows(rows, nets, recipe, args)
        rows.ranked = (row, nets) if args.fitness_ranking else None
        if args.neighbourhood:
            rows.generators[row] = nets
    for flag, value in (("--design-search", args.design_search),
                        ("--fitness-ranking", args.fitness_ranking),
                        ("--neighbourhood", args.neighbourhood)):
        if value and nets is None:
            _say(f"{flag} needs --run-dir with a checkpoint: skipped")
    for name, path in extras:
        nets_x, why = _load_trained_nets(path)
        if nets_x is None:
            _say(f"--extra {name}: no usable checkpoint in {path} ({why}): row skipped")
            continue
        rows.designers[name] = E.nets_designer(nets_x)
        rows.recipes[name] = f"generator, {_nets_recipe(nets_x)}"
        if rows.generators:
            rows.generators[name] = nets_x
        if rows.ranked is not None:
            rows.judges[name] = nets_x


def _pool_note(rows: _Rows) -> None:
    """The note on where the design pool's picks came from, once (from this call's search or,
    when an earlier call made the pool, from the store)."""
    if rows.pool_name is None or any(n.startswith("Design pool:") for n in rows.notes):
        return
    if not rows.pool_origins and rows.store is not None:
        got = rows.store.load("origins", rows.pool_name)
        rows.pool_origins = [str(o) for o in got["origins"]] if got is not None else []
    if rows.pool_origins:
        picks = "; ".join(f"{n} {origin}" for origin, n in  # origins hold commas
                          collections.Counter(rows.pool_origins).most_common())
        rows.notes.append(f"Design pool: where the verified picks of {len(rows.pool_origins)} objects "
                          f"came from: {picks}")
        _say(rows.notes[-1])


def _table_results(args, designers, rows: _Rows, objs, hulls, cfg, notes, tables,
                   out_dir) -> tuple[dict, list]:
    """Tables 1 and 2 as asked: their results.json entries (design_seconds included) and markdown."""
    results, printed, progress = {}, [], not args.quiet
    kw = dict(backend=args.backend, progress=progress, object_hulls=hulls, executor=args.executor,
              store=rows.store, made={})
    design_seconds = {}
    if 1 in tables:
        t1 = E.table1(designers, objs, cfg, **kw)
        design_seconds.update(t1.design_seconds)
        _pool_note(rows)
        t1.notes[:0] = notes + rows.notes
        results["table1"] = {"values": t1.values, "feasible": t1.feasible,
                             "sim_seconds": round(t1.sim_seconds, 2),
                             "outcomes": {k: ["".join(map(str, o)) for o in v]
                                          for k, v in t1.outcomes.items()},
                             "files": {k: str(v) for k, v in t1.write(out_dir, "table1").items()}}
        printed.append(t1.to_markdown())
        if args.printed is not None:
            tp = _printed_table1(args, designers, kw["made"], objs, hulls, cfg, kw)
            tp.notes[:0] = notes
            results["table1_printed"] = {
                "tolerance_mm": args.printed, "copies": args.printed_copies, "values": tp.values,
                "feasible": tp.feasible, "sim_seconds": round(tp.sim_seconds, 2),
                "files": {k: str(v) for k, v in tp.write(out_dir, "table1_printed").items()}}
            printed.append(tp.to_markdown())
    if 2 in tables:
        t2 = E.table2({k: designers[k] for k in rows.table2}, objs, cfg, seed=args.seed, **kw)
        design_seconds.update(t2.design_seconds)
        _pool_note(rows)
        t2.notes[:0] = notes + rows.notes
        results["table2"] = {"values": t2.values, "feasible": t2.feasible,
                             "sim_seconds": round(t2.sim_seconds, 2),
                             "grasp": {k: {c: "".join(map(str, v[j, :, 0]))
                                           for j, c in enumerate(t2.columns)}
                                       for k, v in t2.outcomes.items()},
                             "files": {k: str(v) for k, v in t2.write(out_dir, "table2").items()}}
        printed.append(t2.to_markdown())
    results["design_seconds"] = {k: round(v, 2) for k, v in design_seconds.items()}
    return results, printed


def _printed_table1(args, designers, made: dict, objs, hulls, cfg, kw) -> E.Table:
    """Table 1 of the same rows with both fingers of every design moved by a smooth field of
    ``args.printed`` mm (``nets.inference.perturbed_heights``), ``args.printed_copies`` copies per
    object; copy j of object i is moved by the same fields in every row (paired), drawn from
    --seed (``designer.printed_copies``).  A row's designs are taken from this process (``made``)
    or its designer (stored); rows whose moved outcomes an earlier call saved are not designed."""
    j, n = args.printed_copies, len(objs)

    def moved(name):
        def designer(_objects):  # the table's objects are objs repeated j times
            base = made.get(name) or E.make_designs({name: designers[name]}, objs, progress=False)[name]
            lefts, rights = printed_copies(base.lefts, base.rights, args.printed, cfg.geometry, j,
                                           [args.seed, 3])
            return E.Design(lefts, rights, base.seconds)
        return designer

    title = (f"Table 1 as printed: both fingers moved by a smooth field of {args.printed:g} mm, "
             f"{j} copies per object (%)")
    table = E.table1({name: moved(name) for name in designers}, np.concatenate([objs] * j), cfg,
                     **{**kw, "object_hulls": list(hulls) * j, "made": {}},
                     step=f"table1 printed {args.printed!r} mm x {j}", title=title)
    table.notes.append(f"{n} objects x {j} moved copies each: every rate is over all {n * j} "
                       "(object, copy) pairs; the copies' fields are the same in every row")
    return table


def _fitness_ranking(args, rows: _Rows, objs, hulls, cfg) -> tuple[dict, str]:
    """--fitness-ranking K: the run's K candidates per object, all simulated (kept in the step
    store), scored by the run's fitness net and by every --extra's on the same candidates."""
    row, nets = rows.ranked
    k = args.fitness_ranking
    step = f"fitness ranking {k}"
    got = rows.store.load(step, row)
    if got is not None and "outcomes" in got:  # the designs are made again (deterministic), not simulated
        lefts, rights, feasible = E.candidate_designs(nets, objs, cfg, candidates=k, key=args.seed)
        simulated = got["outcomes"]
    else:
        _say(f"fitness ranking: {k} candidates per object, all simulated")
        lefts, rights, feasible, simulated = E.candidate_outcomes(
            nets, objs, cfg, candidates=k, key=args.seed, backend=args.backend, object_hulls=hulls,
            progress=not args.quiet, executor=args.executor)
        rows.store.save(step, row, outcomes=simulated)
    rk = E.ranking_report(nets, objs, lefts, rights, feasible, simulated, judges=rows.judges)
    lines = [f"Fitness net ranking ({rk['candidates']} candidates x {rk['objects']} objects): "
             f"within-object Spearman {rk['spearman']:.2f} ({rk['objects_ranked']} objects with "
             f"differing candidates), grasp AUC {rk['grasp_auc']:.2f}; trials passed of 11: "
             f"generator's own {rk['trials_first']:.2f}, average candidate {rk['trials_mean']:.2f}, "
             f"fitness net's pick {rk['trials_picked']:.2f}, best {rk['trials_best']:.2f}, "
             f"worst {rk['trials_worst']:.2f}"]
    near = rk["nearest_own"]
    g = near["spearman_gain"]
    lines.append(f"  no fitness net, the candidates ranked by closeness to the generator's own design (its "
                 f"pick: the own design): Spearman {near['spearman']:.2f}; {row}'s net minus it, paired over "
                 f"{g['objects']} objects: {g['diff']:+.3f} [{g['ci_low']:+.3f}, {g['ci_high']:+.3f}] "
                 f"(better / worse {g['better']} / {g['worse']})")
    for name, j in rk.get("judges", {}).items():
        g = j["spearman_gain"]
        lines.append(f"  {name}'s fitness net on the same candidates: Spearman {j['spearman']:.2f}, grasp "
                     f"AUC {j['grasp_auc']:.2f}, its pick {j['trials_picked']:.2f} trials; {row} minus "
                     f"{name}, Spearman paired over {g['objects']} objects: {g['diff']:+.3f} "
                     f"[{g['ci_low']:+.3f}, {g['ci_high']:+.3f}] (95% bootstrap; better / worse "
                     f"{g['better']} / {g['worse']})")
    return rk, "\n".join(lines)


def _neighbourhood(args, generators: dict, objs, hulls, cfg, store) -> tuple[dict, str]:
    k = args.neighbourhood
    sims = {}
    for name, m in generators.items():
        got = store.load(f"neighbourhood {k}", name)
        if got is not None:
            sims[name] = got["outcomes"]
            continue
        _say(f"neighbourhood of {name}: {k} candidates per object, all simulated")
        sims[name] = E.candidate_outcomes(m, objs, cfg, candidates=k, key=args.seed,
                                          backend=args.backend, object_hulls=hulls,
                                          progress=not args.quiet, executor=args.executor)[3]
        store.save(f"neighbourhood {k}", name, outcomes=sims[name])
    stats = {name: E.neighbourhood_stats(v) for name, v in sims.items()}
    first, *others = sims
    gains = {name: E.paired_gain(sims[first], sims[name], seed=args.seed) for name in others}
    lines = [f"Generators on {len(objs)} objects, {k} candidates each (own design + {k - 1} "
             "latent perturbations), trials passed of 11 and grasp success:",
             "| generator | own design: trials | own: grasp | all candidates: trials | all: grasp |",
             "|---|---|---|---|---|"]
    lines += [f"| {n} | {s['trials_own']:.2f} | {s['grasp_own']:.3f} | {s['trials_mean']:.2f} | "
              f"{s['grasp_mean']:.3f} |" for n, s in stats.items()]
    for name, g in gains.items():
        lines.append(f"{first} minus {name}, paired over objects (95% bootstrap interval; "
                     "objects better / worse):")
        lines += [f"  {m:12s} {v['diff']:+.3f}  [{v['ci_low']:+.3f}, {v['ci_high']:+.3f}]  "
                  f"{v['better']} / {v['worse']}" for m, v in g.items()]
    result = {"stats": stats, "gains": gains, "outcomes": {n: v.tolist() for n, v in sims.items()}}
    return result, "\n".join(lines)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    error, tables, extras = _check(args)
    if error:
        return _fail(error)
    if args.xla_threads < 0:
        return _fail(f"--xla-threads must be >= 0, got {args.xla_threads}")
    reproducible.reproducible_xla(args.xla_threads)  # before JAX computes: the same designs everywhere
    try:
        ray_executor.executor_from_cli(args)
    except F2FError as exc:  # the extra missing, or no cluster at --ray-address
        return _fail(str(exc))
    start = time.perf_counter()
    run_dir = Path(args.run_dir).expanduser() if args.run_dir else None
    if run_dir is not None and not run_dir.is_dir():
        return _fail(f"--run-dir {run_dir}: no such directory")
    cfg = config.get(args.config) if args.config else (_run_config(run_dir) if run_dir else None)
    cfg = cfg or config.default()
    if args.sim_preset is not None:
        cfg = config.with_sim_preset(cfg, args.sim_preset)
    out_dir = Path(args.out) if args.out else (run_dir / "eval" if run_dir else Path("runs/eval"))
    try:
        objects, names, what = _objects(args, run_dir, cfg)
    except ValueError as exc:
        return _fail(str(exc))
    if len(objects) == 0:
        return _fail(f"no objects to evaluate ({what})")
    where = " on ray" if args.executor == "ray" else ""
    _say(f"{len(objects)} {what}; simulator: {args.backend}{where}; output: {out_dir}")

    rows = _Rows()
    _baseline_rows(rows, cfg)
    _model_rows(rows, args, run_dir, extras)
    # designs once, hulls once, then the tables
    progress = not args.quiet
    objs, hulls, notes, kept = E.prepare_objects(objects, cfg, progress=progress, return_kept=True)
    names = [names[i] for i in kept]
    for note in notes:
        _say(note)
    # every finished step (a row's designs, a row's outcomes in a table) is kept in OUT/.steps:
    # the same command after a kill, or one that adds rows, does only what is missing
    if args.no_resume:
        shutil.rmtree(out_dir / steps.DIRECTORY, ignore_errors=True)
    rows.store = steps.StepStore(out_dir, steps.common_digest(objs, cfg, backend=args.backend,
                                                              seed=args.seed), rows.recipes)
    designers = {name: steps.StoredDesigner(rows.store, name, d, say=_say)
                 for name, d in rows.designers.items()}
    results = {"objects": len(objs), "names": names, "source": what, "backend": args.backend,
               "config": args.config or ("run" if run_dir and _run_config(run_dir) else "default")}
    made, printed = _table_results(args, designers, rows, objs, hulls, cfg, notes, tables, out_dir)
    results.update(made)
    if rows.ranked is not None:
        results["fitness_ranking"], text = _fitness_ranking(args, rows, objs, hulls, cfg)
        printed.append(text)
    if rows.generators:
        results["neighbourhood"], text = _neighbourhood(args, rows.generators, objs, hulls, cfg, rows.store)
        printed.append(text)
    if rows.store.loaded:
        _say(f"took up {rows.store.loaded} steps finished by an earlier call (in {out_dir / steps.DIRECTORY}; "
             "--no-resume starts afresh)")
    results["seconds"] = round(time.perf_counter() - start, 1)
    with atomic_path(out_dir / "results.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1))
    rows.store.finish()
    print("\n".join(printed))
    print(f"{len(objs)} objects ({what}); wall time {results['seconds']:.0f} s; "
          f"files in {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
