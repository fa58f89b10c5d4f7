"""The paper's Table 1 and Table 2 for a co-training run (or the baselines alone).

    python experiments/evaluate.py                          # WSG50, flat pads, Imprint; 12 built-in objects
    python experiments/evaluate.py --run-dir runs/cotrain   # + RandEmb+FN, Fit2Form; held-out objects
    python experiments/evaluate.py --run-dir runs/cotrain --extra "Fit2Form GS=runs/gs" \\
        --extra ImpGN=runs/impgn --design-search 64 --objects 64 --tables 1,2
    python experiments/evaluate.py --run-dir runs/cotrain --executor ray   # trials on a Ray cluster

With --run-dir the held-out objects of the run (DIR/objects, its fixed split) are evaluated and the
run's newest checkpoint gives the rows "Fit2Form" (or "Fit2Form GS", ... after the run's objectives)
and "RandEmb+FN" (its shape decoder and fitness net without the generator).  Without a checkpoint
only the baselines are run: "WSG50" (Schunk's standard WSG-FMF fingers, the paper's baseline; the
mesh comes with the pybullet extra, and the row is skipped with a note without it), "Flat pads"
(ideal flat fingertips, ours) and "Imprint".  Each --extra NAME=RUN_DIR adds a Table 1 row from
another run's checkpoint (ablations).  Table 2 has the paper's rows: WSG50, Imprint and the run's
own row.
--fresh N adds N never-seen built-in objects to the run's held-out ones.
--checkpoint DIR takes the nets from DIR/checkpoints instead of the run's newest: RUN_DIR/pretrained
scores the run's pretrained generator and fitness net on its held-out objects.
The studies that once ran here run beside it on the same objects and saved steps (their
--out is this one's): ``research/generator_candidates.py`` (--fitness-ranking K: does the fitness
net rank a run's candidates as the simulator does; --neighbourhood K: is one generator better
than another, paired over objects) and ``research/printed_table.py`` (Table 1 with every row's
fingers moved as a printer would).
Writes table1.{md,csv,png}, table2.{md,csv,png} and results.json
into --out (default DIR/eval, or runs/eval without a run) and prints the markdown.

Nothing finished is lost to a kill: each row's designs and its outcomes in each table are saved
in OUT/.steps as they end (``f2f_jax.tables.steps``), and the same command run again does only
what is missing.  A command that adds rows (another --extra, --design-search, Table 2) reuses the rows
already simulated with the same objects, settings and code; --no-resume starts afresh.  The
designs are deleted once results.json is written; the outcomes (bytes per object) stay.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from f2f_jax import config
from f2f_jax import tables as E
from f2f_jax.cli import reproducible, sim_options
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.tables import rows as R
from f2f_jax.tables import steps


def _fail(msg: str) -> int:
    print(f"evaluate: error: {msg}", file=sys.stderr)
    return 2


def _say(msg: str) -> None:
    print(f"evaluate: {msg}", file=sys.stderr, flush=True)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The flags that say what is evaluated, on what and with which simulator: this command's and
    the studies' beside it (``research/``), so that they name the same rows, objects and steps."""
    p.add_argument("--run-dir", default=None, help="a co-training run directory (objects + checkpoints)")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="with --run-dir: the nets of DIR/checkpoints instead of the run's newest, e.g. "
                        "RUN_DIR/pretrained (the end of its pretraining: its ImpGN and pretrained "
                        "fitness net) on the run's held-out objects")
    p.add_argument("--extra", action="append", default=[], metavar="NAME=RUN_DIR",
                   help="another run's checkpoint as a Table 1 row (repeatable), e.g. 'Fit2Form GS=runs/gs'")
    p.add_argument("--objects", type=int, default=None,
                   help="cap on held-out objects (default: all of them; 12 built-in ones without a run)")
    p.add_argument("--fresh", type=int, default=None, metavar="N",
                   help="with --run-dir: add N new built-in objects (drawn with --seed, which must "
                        "differ from the run's) to its held-out ones")
    p.add_argument("--out", default=None, help="output directory (default RUN_DIR/eval, or runs/eval)")
    p.add_argument("--config", default=None,
                   help="tiny | default | workstation | paper: the simulator settings (default: the run's, else default)")
    p.add_argument("--backend", choices=list(config.BACKENDS), default="mujoco")
    p.add_argument("--sim-preset", default=None, choices=sorted(config.SIM_PRESETS),
                   help="simulation preset (config.SIM_PRESETS; default: the run's config's)")
    p.add_argument("--seed", type=int, default=0, help="built-in objects, RandEmb keys, position shifts")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--no-resume", action="store_true",
                   help="start afresh: delete the steps an earlier call saved in OUT/.steps instead of "
                        "taking them up (by default a killed or extended evaluation continues)")
    reproducible.add_cli_argument(p)
    sim_options.add_cli_arguments(p)


def add_row_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of the rows a run's checkpoint adds: RandEmb+FN and the search rows."""
    p.add_argument("--design-search", type=int, default=None, metavar="K",
                   help="add the rows 'Fit2Form + search (K, verify)' (f2f_jax.design with the "
                        "generator's K candidates) and 'Design pool (K + imprints, verify)' (the "
                        "same plus the imprint pair and its variants: design()'s default)")
    p.add_argument("--randemb-steps", type=int, default=200,
                   help="RandEmb+FN optimisation steps (paper: 200)")
    p.add_argument("--randemb-samples", type=int, default=4, help="RandEmb+FN random starts per object")
    p.add_argument("--no-randemb", action="store_true", help="skip the RandEmb+FN row (slow on a CPU)")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(p)
    p.add_argument("--tables", default="1,2", help="which tables: 1, 2 or 1,2")
    add_row_arguments(p)
    return p


def check_run_arguments(args) -> tuple[str | None, list[tuple[str, Path]]]:
    """(error or None, the --extra rows as (name, run dir)) of ``add_run_arguments``' flags."""
    executor_problem = sim_options.backend_problem(args, args.backend)
    checks = [
        (args.config is not None and args.config not in config.CONFIGS,
         f"unknown --config {args.config!r}; choose one of {', '.join(config.CONFIGS)}"),
        (args.objects is not None and args.objects < 1, "--objects must be at least 1"),
        (args.fresh is not None and (args.fresh < 1 or not args.run_dir),
         "--fresh N needs N >= 1 and --run-dir"),
        (args.checkpoint is not None and not args.run_dir,
         "--checkpoint DIR needs --run-dir (whose held-out objects it is scored on)"),
        (args.checkpoint is not None and not (Path(args.checkpoint).expanduser() / "checkpoints").is_dir(),
         f"--checkpoint {args.checkpoint}: no checkpoints/ directory in it (e.g. RUN_DIR/pretrained)"),
        (executor_problem is not None, executor_problem),
        (args.xla_threads < 0, f"--xla-threads must be >= 0, got {args.xla_threads}"),
    ]
    if hasattr(args, "design_search"):
        checks += [
            (args.randemb_steps < 0 or args.randemb_samples < 1,
             "--randemb-steps must be >= 0 and --randemb-samples >= 1"),
            (args.design_search is not None and args.design_search < 1, "--design-search K needs K >= 1"),
        ]
    for bad, message in checks:
        if bad:
            return message, []
    try:
        return None, R.parse_extras(args.extra)
    except ValueError as exc:
        return str(exc), []


def _check(args) -> tuple[str | None, list[int], list[tuple[str, Path]]]:
    """(error or None, the tables asked for, the --extra rows as (name, run dir))."""
    try:
        tables = sorted({int(t) for t in args.tables.split(",") if t.strip()})
    except ValueError:
        return f"--tables {args.tables!r}: a comma-separated list of 1 and 2", [], []
    if not tables or not set(tables) <= {1, 2}:
        return f"--tables {args.tables!r}: choose 1, 2 or 1,2", [], []
    error, extras = check_run_arguments(args)
    return error, tables, extras


def start_study(args, say=_say) -> tuple["Setup", list[tuple[str, Path]]]:
    """What a study over a run's rows does before it simulates (``research/``'s scripts take
    evaluate's flags): the run arguments checked, the XLA flags set, the executor started and the
    objects set up.  Returns (Setup, extras); raises ValueError or F2FError with the message."""
    error, extras = check_run_arguments(args)
    if error:
        raise ValueError(error)
    reproducible.reproducible_xla(args.xla_threads)  # before JAX computes: the same designs everywhere
    sim_options.executor_from_cli(args)
    return Setup(args, say=say), extras


class Setup:
    """What an evaluation of ``add_run_arguments``' flags works on: config, output folder,
    objects (prepared: hulls made, unusable ones dropped), their names and source, and the step
    store once ``store(rows)`` made it."""

    def __init__(self, args, say=_say):
        self.args, self.say = args, say
        self.run_dir = Path(args.run_dir).expanduser() if args.run_dir else None
        if self.run_dir is not None and not self.run_dir.is_dir():
            raise ValueError(f"--run-dir {self.run_dir}: no such directory")
        run_cfg = R.run_config(self.run_dir) if self.run_dir else None
        cfg = config.get(args.config) if args.config else run_cfg
        self.cfg = cfg or config.default()
        if args.sim_preset is not None:
            self.cfg = config.with_sim_preset(self.cfg, args.sim_preset)
        self.config_name = args.config or ("run" if run_cfg else "default")
        self.out_dir = Path(args.out) if args.out else (
            self.run_dir / "eval" if self.run_dir else Path("runs/eval"))
        self.objects, self.names, self.what = R.evaluation_objects(
            self.run_dir, self.cfg, objects=args.objects, fresh=args.fresh, seed=args.seed,
            progress=not args.quiet)
        if len(self.objects) == 0:
            raise ValueError(f"no objects to evaluate ({self.what})")
        where = " on ray" if args.executor == "ray" else ""
        say(f"{len(self.objects)} {self.what}; simulator: {args.backend}{where}; output: {self.out_dir}")

    def nets(self):
        """The run's nets (those of --checkpoint if given), or None with a note."""
        if self.run_dir is None:
            return None
        source = Path(self.args.checkpoint).expanduser() if self.args.checkpoint else self.run_dir
        nets, why = R.load_nets(source)
        if nets is None:
            self.say(f"no usable checkpoint in {source} ({why}): running the baseline rows only")
        else:
            self.say(f"{R.model_row_name(nets)}: {nets.source}")
        return nets

    def prepare(self, rows: R.Rows) -> None:
        """Hulls of the objects (``objs``, ``hulls``; notes on those dropped) and the step store."""
        self.objs, self.hulls, self.notes, kept = E.prepare_objects(
            self.objects, self.cfg, progress=not self.args.quiet, return_kept=True)
        self.names = [self.names[i] for i in kept]
        for note in self.notes:
            self.say(note)
        # every finished step (a row's designs, a row's outcomes in a table) is kept in OUT/.steps:
        # the same command after a kill, or one that adds rows, does only what is missing
        if self.args.no_resume:
            shutil.rmtree(self.out_dir / steps.DIRECTORY, ignore_errors=True)
        rows.store = steps.StepStore(self.out_dir, steps.common_digest(
            self.objs, self.cfg, backend=self.args.backend, seed=self.args.seed), rows.recipes)
        self.store = rows.store


def model_rows(rows: R.Rows, setup: Setup, extras) -> str | None:
    """The run's checkpoint rows (``add_row_arguments``) and every --extra's; the run's row name."""
    args, nets = setup.args, setup.nets()
    row = None
    if nets is not None:
        row = R.model_rows(rows, nets, seed=args.seed, design_search=args.design_search,
                           randemb=None if args.no_randemb else (args.randemb_samples, args.randemb_steps),
                           backend=args.backend, executor=args.executor, quiet=args.quiet)
    elif args.design_search:
        _say("--design-search needs --run-dir with a checkpoint: skipped")
    R.extra_rows(rows, extras, say=setup.say)
    return row


def _table_results(args, designers, rows: R.Rows, setup: Setup, tables) -> tuple[dict, list]:
    """Tables 1 and 2 as asked: their results.json entries (design_seconds included) and markdown."""
    results, printed = {}, []
    kw = dict(backend=args.backend, progress=not args.quiet, object_hulls=setup.hulls,
              executor=args.executor, store=rows.store, made={})
    design_seconds = {}
    for number in tables:
        if number == 1:
            table = E.table1(designers, setup.objs, setup.cfg, **kw)
        else:
            table = E.table2({k: designers[k] for k in rows.table2}, setup.objs, setup.cfg,
                             seed=args.seed, **kw)
        design_seconds.update(table.design_seconds)
        R.pool_note(rows, say=_say)
        table.notes[:0] = setup.notes + rows.notes
        entry = {"values": table.values, "feasible": table.feasible,
                 "sim_seconds": round(table.sim_seconds, 2)}
        if number == 1:
            entry["outcomes"] = {k: ["".join(map(str, o)) for o in v] for k, v in table.outcomes.items()}
        else:
            entry["grasp"] = {k: {c: "".join(map(str, v[j, :, 0])) for j, c in enumerate(table.columns)}
                              for k, v in table.outcomes.items()}
        entry["files"] = {k: str(v) for k, v in table.write(setup.out_dir, f"table{number}").items()}
        results[f"table{number}"] = entry
        printed.append(table.to_markdown())
    results["design_seconds"] = {k: round(v, 2) for k, v in design_seconds.items()}
    return results, printed


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    error, tables, extras = _check(args)
    if error:
        return _fail(error)
    reproducible.reproducible_xla(args.xla_threads)  # before JAX computes: the same designs everywhere
    try:
        sim_options.executor_from_cli(args)
    except F2FError as exc:  # the extra missing, or no cluster at --ray-address
        return _fail(str(exc))
    start = time.perf_counter()
    try:
        setup = Setup(args)
    except ValueError as exc:
        return _fail(str(exc))
    rows = R.Rows()
    R.baseline_rows(rows, setup.cfg, say=_say)
    model_rows(rows, setup, extras)
    setup.prepare(rows)
    designers = {name: steps.StoredDesigner(rows.store, name, d, say=_say)
                 for name, d in rows.designers.items()}
    results = {"objects": len(setup.objs), "names": setup.names, "source": setup.what,
               "backend": args.backend, "config": setup.config_name}
    made, printed = _table_results(args, designers, rows, setup, tables)
    results.update(made)
    if rows.store.loaded:
        _say(f"took up {rows.store.loaded} steps finished by an earlier call (in "
             f"{setup.out_dir / steps.DIRECTORY}; --no-resume starts afresh)")
    results["seconds"] = round(time.perf_counter() - start, 1)
    with atomic_path(setup.out_dir / "results.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1))
    rows.store.finish()
    print("\n".join(printed))
    print(f"{len(setup.objs)} objects ({setup.what}); wall time {results['seconds']:.0f} s; "
          f"files in {setup.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
