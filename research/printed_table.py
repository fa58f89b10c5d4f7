"""Table 1 as printed: do the rows keep their places when every finger is made as a printer would?

    python research/printed_table.py --run-dir runs/cotrain --design-search 16 --fresh 48 --seed 7 \
        --tolerance 0.3 --copies 4 --no-randemb
    python research/printed_table.py --config tiny --objects 2 --copies 2 --quiet   # baselines, smoke

Every row of ``experiments/evaluate.py``'s Table 1 (the same flags name the same rows, objects and
saved steps) is scored again with both fingers of every design moved by a smooth random field of
standard deviation ``--tolerance`` mm (a printer's error; 0.3 moves the surface ~0.15 mm on
average, ``designer.printed_copies``), ``--copies`` copies per object, the same fields for every
row (paired), drawn from --seed.  A simulated trial turns on tenths of a millimetre of finger, so
the rows chosen by simulation (--design-search) report their own luck in Table 1; here they are
scored on fingers they were not chosen with.

Writes table1_printed.{md,csv,png} and printed.json (the table's values, feasibility, seconds)
into --out (default RUN_DIR/eval, or runs/eval) and prints the markdown.  The moved outcomes are
saved steps: the same command again simulates nothing.  Results: docs/design.md (tolerance) and
docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from f2f_jax import tables as E
from f2f_jax.cli import evaluate as ev
from f2f_jax.designer import printed_copies
from f2f_jax.errors import F2FError
from f2f_jax.fileio import atomic_path
from f2f_jax.tables import rows as R
from f2f_jax.tables import steps


def _say(msg: str) -> None:
    print(f"printed_table: {msg}", file=sys.stderr, flush=True)


def printed_table1(designers: dict, objs, hulls, cfg, tolerance_mm: float, copies: int, seed: int,
                   **kw) -> E.Table:
    """Table 1 of ``designers`` with both fingers of every design moved by a smooth field of
    ``tolerance_mm`` mm, ``copies`` copies per object; copy j of object i is moved by the same
    fields in every row (paired), drawn from ``seed``.  Rows whose moved outcomes an earlier call
    saved (``kw["store"]``) are not designed."""
    j, n = copies, len(objs)

    def moved(name):
        def designer(_objects):  # the table's objects are objs repeated j times
            base = E.make_designs({name: designers[name]}, objs, progress=False)[name]
            lefts, rights = printed_copies(base.lefts, base.rights, tolerance_mm, cfg.geometry, j,
                                           [seed, 3])
            return E.Design(lefts, rights, base.seconds)
        return designer

    title = (f"Table 1 as printed: both fingers moved by a smooth field of {tolerance_mm:g} mm, "
             f"{j} copies per object (%)")
    table = E.table1({name: moved(name) for name in designers}, np.concatenate([objs] * j), cfg,
                     **{**kw, "object_hulls": list(hulls) * j, "made": {}},
                     step=f"table1 printed {tolerance_mm!r} mm x {j}", title=title)
    table.notes.append(f"{n} objects x {j} moved copies each: every rate is over all {n * j} "
                       "(object, copy) pairs; the copies' fields are the same in every row")
    return table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ev.add_run_arguments(p)
    ev.add_row_arguments(p)
    p.add_argument("--tolerance", type=float, default=0.3, metavar="MM",
                   help="standard deviation of the moving field in mm (default 0.3)")
    p.add_argument("--copies", type=int, default=4, metavar="J",
                   help="moved copies per object and row (default 4)")
    args = p.parse_args(argv)
    if not (0 < args.tolerance and math.isfinite(args.tolerance)):
        p.error("--tolerance MM needs a finite MM > 0 (the moving field's standard deviation, mm)")
    if args.copies < 1:
        p.error("--copies J needs J >= 1")
    try:
        setup, extras = ev.start_study(args, say=_say)
    except (F2FError, ValueError) as exc:
        p.error(str(exc))
    start = time.perf_counter()
    rows = R.Rows()
    R.baseline_rows(rows, setup.cfg, say=_say)
    ev.model_rows(rows, setup, extras)
    setup.prepare(rows)
    designers = {name: steps.StoredDesigner(rows.store, name, d, say=_say)
                 for name, d in rows.designers.items()}
    table = printed_table1(designers, setup.objs, setup.hulls, setup.cfg, args.tolerance,
                           args.copies, args.seed, backend=args.backend,
                           progress=not args.quiet, executor=args.executor, store=rows.store)
    table.notes[:0] = setup.notes
    files = table.write(setup.out_dir, "table1_printed")
    results = {"objects": len(setup.objs), "names": setup.names, "source": setup.what,
               "backend": args.backend, "config": setup.config_name,
               "table1_printed": {"tolerance_mm": args.tolerance, "copies": args.copies,
                                  "values": table.values, "feasible": table.feasible,
                                  "sim_seconds": round(table.sim_seconds, 2),
                                  "files": {k: str(v) for k, v in files.items()}},
               "seconds": round(time.perf_counter() - start, 1)}
    with atomic_path(setup.out_dir / "printed.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1))
    rows.store.finish()  # the designs go, the moved outcomes stay
    if rows.store.loaded:
        _say(f"took up {rows.store.loaded} steps finished by an earlier call")
    print(table.to_markdown())
    print(f"{len(setup.objs)} objects ({setup.what}); wall time {results['seconds']:.0f} s; "
          f"files in {setup.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
