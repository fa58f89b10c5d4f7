"""Tables 1 and 2 over several runs: mean ± sd per cell, each row against a reference row.

    python experiments/seed_table.py runs/s0/eval runs/s1/eval runs/s2/eval --out runs/seeds
    python experiments/seed_table.py runs/s*/eval --labels "seed 0,seed 1,seed 2" --versus Imprint
    python experiments/seed_table.py runs/s0/eval runs/s1/eval runs/s1/eval-ablations \
        --labels "seed 0,seed 1,seed 1"     # rows evaluated later join their run

Each argument is an ``experiments/evaluate.py`` output (its --out directory, default RUN_DIR/eval,
or the results.json in it).  Rows are matched by name across runs, so name every run's ``--extra``
rows alike.  --objects held-out or fresh recounts every row on the runs' own held-out objects or
on the new ones of ``evaluate.py --fresh``.  --paired "A minus B" (repeatable) prints generator A's
gain over B on the candidates ``research/generator_candidates.py --neighbourhood K`` simulated for
both (its OUT/candidates.json, read beside results.json), run by run and pooled over the runs (the
fresh objects the runs share are resampled as one cluster each):

    python experiments/seed_table.py runs/s*/eval --paired "Fit2Form minus control"

Writes table1_seeds.{md,csv,png} (and table2_seeds.* where the runs have Table 2; paired_seeds.md
with --paired) into --out and prints the markdown.  Reads only what evaluate.py wrote: nothing is
simulated.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from f2f_jax.tables.seeds import (
    OBJECT_SUBSETS,
    combine_results,
    load_results,
    paired_markdown,
    paired_over_runs,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", nargs="+", help="evaluate.py output directories (or results.json files)")
    p.add_argument("--labels", default=None,
                   help="comma-separated run labels, one per result (default: the directories' names); "
                        "results with the same label are one run's rows from several evaluate.py calls")
    p.add_argument("--versus", default="Imprint",
                   help="row every other row is compared with, run by run ('' for none; default Imprint)")
    p.add_argument("--objects", choices=OBJECT_SUBSETS, default="all",
                   help="all the objects each run evaluated (default), only the run's held-out ones, "
                        "or only the new ones of evaluate.py --fresh")
    p.add_argument("--paired", action="append", default=[], metavar='"A minus B"',
                   help="generator A minus generator B on the candidates of research/"
                        "generator_candidates.py --neighbourhood, run by run and pooled (repeatable)")
    p.add_argument("--out", default=None,
                   help="where to write the tables (default: print only)")
    args = p.parse_args(argv)
    paths = [Path(r) for r in args.results]
    if args.labels is not None:
        labels = [s.strip() for s in args.labels.split(",")]
        if len(labels) != len(paths):
            p.error(f"--labels gives {len(labels)} labels for {len(paths)} results")
    else:
        labels = [_label(path) for path in paths]
    pairs = []
    for item in args.paired:
        after, sep, before = item.partition(" minus ")
        if not sep or not after.strip() or not before.strip():
            p.error(f'--paired {item!r}: expected "A minus B" (generator names as evaluate.py printed them)')
        pairs.append((after.strip(), before.strip()))
    try:
        results = [load_results(path) for path in paths]
        tables = combine_results(results, labels, objects=args.objects)
        paired = [paired_markdown(a, b, paired_over_runs(results, labels, a, b, objects=args.objects))
                  for a, b in pairs]
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if not tables:
        print(f"error: none of the runs evaluated {args.objects} objects", file=sys.stderr)
        return 1
    versus = args.versus or None
    for kind, table in tables.items():
        if versus is not None and versus not in table.values:
            print(f"error: {kind} has no row {versus!r} to compare with (rows: "
                  f"{', '.join(table.rows())}); pass --versus ROW or --versus ''", file=sys.stderr)
            return 1
    for table in tables.values():
        print(table.to_markdown(versus))
        if args.out:
            written = table.write(args.out, versus)
            print(f"wrote {', '.join(str(v) for v in written.values())}", file=sys.stderr)
    for text in paired:
        print("\n" + text)
    if paired and args.out:
        out = Path(args.out) / "paired_seeds.md"
        out.write_text("\n\n".join(paired) + "\n")
        print(f"wrote {out}", file=sys.stderr)
    return 0


def _label(path: Path) -> str:
    """A run's label from its path: the run directory's name for RUN_DIR/eval (or its
    results.json), else the directory's own name."""
    path = path.expanduser().resolve()
    if path.name == "results.json":
        path = path.parent
    return path.parent.name if path.name == "eval" else path.name


if __name__ == "__main__":
    sys.exit(main())
