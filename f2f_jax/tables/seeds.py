"""Tables 1 and 2 over several runs (seeds): every figure as mean ± spread, and each row against a
reference row run by run.

One co-training run is one draw of training randomness and of held-out objects: the default run's
held-out grasp success moved by 0.3 between seeds (benchmarks/RESULTS.md), so a row of one run
says little.  ``experiments/evaluate.py`` writes ``results.json`` per run; this module reads
several and combines them:

    tables = combine_results([load_results(d) for d in dirs], labels=["seed 0", "seed 1", "seed 2"])
    tables["table1"].to_markdown(versus="Imprint")   # mean ± sd per cell, then row - Imprint

A run's rows are matched by name (name ``--extra`` rows the same way in every run); a row that
some runs lack is averaged over the runs that have it and says how many.  ``objects="held-out"``
or ``"fresh"`` recounts every row on the run's own held-out objects or on the new ones that
``evaluate.py --fresh`` added (named ``fresh/...``), from the per-object outcomes results.json keeps.
``paired_over_runs`` pools one generator's paired gain over another (``research/
generator_candidates.py --neighbourhood``, its candidates.json read beside results.json) over the
runs, with the fresh objects the runs share resampled as one each.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from f2f_jax.fileio import atomic_path
from f2f_jax.tables import paper as figures
from f2f_jax.tables.table import TITLES, column_headers, save_bar_chart, table1_values

KINDS = ("table1", "table2")
_PAPER = {"table1": figures.PAPER_TABLE1, "table2": figures.PAPER_TABLE2}
_COLUMNS = {"table1": figures.TABLE1_COLUMNS, "table2": figures.TABLE2_COLUMNS}
OBJECT_SUBSETS = ("all", "held-out", "fresh")
FRESH_PREFIX = "fresh/"  # evaluate.py's prefix for the names of the objects --fresh adds


def fresh_source(n: int, seed: int) -> str:
    """How evaluate.py's results.json ``source`` names the objects of ``--fresh N --seed S``;
    ``_FRESH_SOURCE`` reads it back."""
    return f"{n} new built-in objects (seed {seed})"


_FRESH_SOURCE = re.compile(r"(\d+) new built-in objects \(seed (-?\d+)\)")  # fresh_source, read back


def _in_subset(names: Sequence[str], objects: str) -> np.ndarray:
    """Which of a run's object names are in ``objects`` ("held-out" or "fresh")."""
    return np.array([n.startswith(FRESH_PREFIX) == (objects == "fresh") for n in names])


# Table 1's row-against-row comparison: the summary columns, and the mean of the ten stability and
# robustness trials (where imprints do not max out, the test of Fit2Form against Imprint).
SR_MEAN = "S+R mean"
_VERSUS_COLUMNS = {"table1": ("grasp", "S avg", "R avg", SR_MEAN), "table2": figures.TABLE2_COLUMNS}


def _cell(values: Mapping[str, float], column: str) -> float:
    if column == SR_MEAN:
        trials = figures.STABILITY + figures.ROBUSTNESS
        return float(np.mean([values[c] for c in trials]))
    return values[column]


def _summary(x: np.ndarray) -> dict[str, float]:
    """mean, sd (sample standard deviation; 0 for one value), min, max and count of [n] values."""
    return {"mean": float(x.mean()), "sd": float(x.std(ddof=1)) if len(x) > 1 else 0.0,
            "min": float(x.min()), "max": float(x.max()), "runs": len(x)}


def load_results(path) -> dict:
    """``results.json`` of one ``experiments/evaluate.py`` run: ``path`` is the file or the
    directory holding it (the run's ``--out``, default ``RUN_DIR/eval``)."""
    path = Path(path).expanduser()
    file = path / "results.json" if path.is_dir() else path
    if not file.exists():
        raise FileNotFoundError(f"{file}: no results.json there; run experiments/evaluate.py "
                                "(its --out, default RUN_DIR/eval) first")
    try:
        results = json.loads(file.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{file}: not a results.json of experiments/evaluate.py ({exc})") from None
    if isinstance(results, dict) and (beside := file.parent / "candidates.json").exists():  # --paired
        results["neighbourhood"] = json.loads(beside.read_text()).get("neighbourhood", results.get("neighbourhood"))
    if not isinstance(results, dict) or not any(k in results for k in KINDS):
        raise ValueError(f"{file}: holds neither table1 nor table2 (was evaluate.py run with "
                         "--tables 1 or 2?)")
    return results


@dataclass
class SeedTable:
    """One table over several runs.

    kind: "table1" or "table2"; columns: value columns; labels: one per run; values: {row: [None
    or {column: percent}] one entry per run}; objects: objects counted per run; subset: which of
    each run's objects ("all", "held-out" or "fresh").
    """

    kind: str
    columns: tuple[str, ...]
    labels: list[str]
    values: dict[str, list[dict[str, float] | None]]
    objects: list[int]
    subset: str = "all"

    def rows(self) -> list[str]:
        """The paper's rows first (its order), then the others as the runs list them."""
        paper = [n for n in _PAPER[self.kind] if n in self.values]
        return paper + [n for n in self.values if n not in paper]

    def per_run(self, row: str, column: str) -> np.ndarray:
        """[runs that have ``row``] percent values of one cell."""
        return np.array([v[column] for v in self.values[row] if v is not None], np.float64)

    def stats(self, row: str, column: str) -> dict[str, float]:
        """mean, sd (sample standard deviation over runs; 0 for one run), min, max, runs."""
        return _summary(self.per_run(row, column))

    def versus(self, row: str, reference: str, column: str) -> dict[str, float] | None:
        """``row`` minus ``reference`` in one column (or ``SR_MEAN``), run by run (runs having
        both): mean, sd, min, max, runs, at_least (runs where the row is >= the reference).  None
        when no run has both."""
        diffs = [_cell(a, column) - _cell(b, column) for a, b in zip(self.values[row], self.values[reference])
                 if a is not None and b is not None]
        if not diffs:
            return None
        d = np.array(diffs, np.float64)
        return {**_summary(d), "at_least": int((d >= 0).sum())}

    # -- writers ------------------------------------------------------------------------------

    def to_markdown(self, versus: str | None = None) -> str:
        """Mean ± sd over runs per cell (the paper's figure beneath, where it has the row), then,
        with ``versus``, every row minus that row, run by run, as mean ± sd and how many runs the
        row was at least as good."""
        n = len(self.labels)
        which = "" if self.subset == "all" else f", {self.subset} objects only"
        lines = [f"### {TITLES[self.kind]}: mean ± sd over {n} run{'s' * (n != 1)}{which}", "",
                 "Runs: " + ", ".join(f"{label} ({k} objects)" for label, k in
                                      zip(self.labels, self.objects)), ""]
        head = ["designer", "source", *column_headers(self.kind, self.columns), "runs"]
        lines += ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|"]
        paper = _PAPER[self.kind]
        for row in self.rows():
            cells = [self.stats(row, c) for c in self.columns]
            lines.append(f"| {row} | ours | " + " | ".join(f"{s['mean']:.1f} ± {s['sd']:.1f}" for s in cells)
                         + f" | {cells[0]['runs']} |")
            if row in paper:
                lines.append("| | paper | " + " | ".join(f"{paper[row][c]:.1f}" for c in self.columns)
                             + " | – |")
        if versus is not None:
            if versus not in self.values:
                raise KeyError(f"no row {versus!r} to compare with; rows: {', '.join(self.rows())}")
            columns = _VERSUS_COLUMNS[self.kind]
            lines += ["", f"Each row minus {versus}, run by run, in points (mean ± sd; in brackets "
                      f"the runs where the row is at least as good; {SR_MEAN}: the mean of the ten "
                      "stability and robustness trials):" if self.kind == "table1" else
                      f"Each row minus {versus}, run by run, in points (mean ± sd; in brackets the "
                      "runs where the row is at least as good):", "",
                      "| designer | " + " | ".join(columns) + " |",
                      "|---|" + "|".join(["---:"] * len(columns)) + "|"]
            for row in self.rows():
                if row == versus:
                    continue
                cells = [self.versus(row, versus, c) for c in columns]
                lines.append(f"| {row} | " + " | ".join(
                    "–" if d is None else f"{d['mean']:+.1f} ± {d['sd']:.1f} ({d['at_least']}/{d['runs']})"
                    for d in cells) + " |")
        return "\n".join(lines) + "\n"

    def to_csv(self) -> str:
        """One line per (row, statistic): mean, sd, min, max and each run's value by label."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(["table", "designer", "statistic", *self.columns, "runs"])
        for row in self.rows():
            cells = [self.stats(row, c) for c in self.columns]
            for stat in ("mean", "sd", "min", "max"):
                writer.writerow([self.kind, row, stat, *(f"{s[stat]:.2f}" for s in cells), cells[0]["runs"]])
            for label, v in zip(self.labels, self.values[row]):
                if v is not None:
                    writer.writerow([self.kind, row, label, *(f"{v[c]:.2f}" for c in self.columns), 1])
        return buf.getvalue()

    def plot(self, path) -> Path:
        """Bars of the mean over runs (table1: grasp, S avg, R avg; table2: every condition),
        each run's value as a dot, the paper's figure as a black tick."""
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        groups = ["grasp", "S avg", "R avg"] if self.kind == "table1" else list(self.columns)
        names = self.rows()
        fig = Figure(figsize=(max(6.0, 1.1 * len(names) * max(1, len(groups) / 3) + 3), 4.2), dpi=110)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        width = 0.8 / max(1, len(groups))
        x = np.arange(len(names))
        colours = colormaps["tab10"]
        paper = _PAPER[self.kind]
        for k, col in enumerate(groups):
            xs = x - 0.4 + width * (k + 0.5)
            means = [self.stats(n, col)["mean"] for n in names]
            sds = [self.stats(n, col)["sd"] for n in names]
            ax.bar(xs, means, width * 0.95, yerr=sds, capsize=2, label=col, color=colours(k % 10),
                   error_kw=dict(lw=0.8))
            for xk, n in zip(xs, names):
                runs = self.per_run(n, col)
                ax.scatter(np.full(len(runs), xk), runs, s=6, color="0.25", zorder=3)
            ticks = [(xk, paper[n][col]) for xk, n in zip(xs, names) if n in paper]
            if ticks:
                px, py = zip(*ticks)
                ax.scatter(px, py, marker="_", s=120, color="black", zorder=4,
                           label="paper" if k == 0 else None)
        which = "" if self.subset == "all" else f", {self.subset} objects"
        n = len(self.labels)
        title = (f"{'Table 1' if self.kind == 'table1' else 'Table 2: grasp success'}: mean ± sd over "
                 f"{n} run{'s' * (n != 1)}{which} (dots: runs; black ticks: paper)")
        return save_bar_chart(fig, ax, names, title, path)

    def write(self, directory, versus: str | None = None) -> dict[str, Path]:
        """``<kind>_seeds.md``, ``.csv`` and ``.png`` in ``directory`` (``<kind>_seeds_fresh.*``
        and ``<kind>_seeds_held-out.*`` for a subset), each written atomically."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        stem = f"{self.kind}_seeds" + ("" if self.subset == "all" else f"_{self.subset}")
        paths = {"md": directory / f"{stem}.md", "csv": directory / f"{stem}.csv"}
        with atomic_path(paths["md"]) as tmp:
            tmp.write_text(self.to_markdown(versus), encoding="utf-8")
        with atomic_path(paths["csv"]) as tmp:
            tmp.write_text(self.to_csv(), encoding="utf-8")
        paths["png"] = self.plot(directory / f"{stem}.png")
        return paths


def combine_results(results: Sequence[Mapping], labels: Sequence[str] | None = None, *,
                    objects: str = "all") -> dict[str, SeedTable]:
    """{kind: SeedTable} for each table that at least one run holds.

    results: ``load_results`` of each run; labels: one per run (default "run 1", "run 2", ...);
    objects: "all" (the tables as evaluate.py printed them), "held-out" or "fresh" (every row
    recounted on those objects from the per-object outcomes; a run with none of them is left out
    of that table).  A run without a table contributes nothing to it; a table's rows are those
    of any run.  Results given the same label are one run evaluated in several calls: their rows
    are united (``merge_results``).
    """
    if objects not in OBJECT_SUBSETS:
        raise ValueError(f"objects must be one of {OBJECT_SUBSETS}, got {objects!r}")
    if not results:
        raise ValueError("no runs to combine")
    labels = list(labels) if labels is not None else [f"run {i + 1}" for i in range(len(results))]
    if len(labels) != len(results):
        raise ValueError(f"{len(labels)} labels for {len(results)} runs")
    grouped: dict[str, list[Mapping]] = {}
    for label, r in zip(labels, results):
        grouped.setdefault(label, []).append(r)
    labels = list(grouped)
    results = [merge_results(group, label) for label, group in grouped.items()]
    tables = {}
    for kind in KINDS:
        have = []
        for label, r in zip(labels, results):
            if kind in r:
                rows, n = _table_values(r, kind, objects, label)
                if n:
                    have.append((label, rows, n))
        if not have:
            continue
        columns = _COLUMNS[kind]
        values: dict[str, list] = {}
        for i, (label, rows, _) in enumerate(have):
            for row, cells in rows.items():
                missing = [c for c in columns if c not in cells]
                if missing:
                    raise ValueError(f"{label}: {kind} row {row!r} lacks columns {missing}")
                values.setdefault(row, [None] * len(have))[i] = {c: float(cells[c]) for c in columns}
        tables[kind] = SeedTable(kind=kind, columns=columns, labels=[label for label, *_ in have],
                                 values=values, objects=[n for *_, n in have], subset=objects)
    return tables


def merge_results(results: Sequence[Mapping], label: str = "run") -> dict:
    """One run's results from several ``evaluate.py`` calls on the same objects (rows evaluated
    later, e.g. an ablation trained after the first evaluation): their tables' rows united.

    The calls must have evaluated the same objects in the same order (``names``), and a row that
    two of them hold must have the same per-object outcomes (the simulator is deterministic, so
    the baselines every call repeats agree); otherwise ValueError, as the rows would not be
    comparable.
    """
    if not results:
        raise ValueError(f"{label}: no results to merge")
    merged = copy.deepcopy(dict(results[0]))
    for r in results[1:]:
        if r.get("names") != merged.get("names") or r.get("objects") != merged.get("objects"):
            raise ValueError(f"{label}: results merged under one label evaluated different objects "
                             f"({r.get('objects')} and {merged.get('objects')} objects, not the same list; run "
                             "evaluate.py with the same --run-dir, --objects, --fresh and --seed)")
        for kind in KINDS:
            if kind not in r:
                continue
            if kind not in merged:
                merged[kind] = copy.deepcopy(r[kind])
                continue
            into, table = merged[kind], r[kind]
            per_object = "outcomes" if kind == "table1" else "grasp"
            for row, cells in table["values"].items():
                if row in into["values"]:
                    same = (into.get(per_object, {}).get(row) == table.get(per_object, {}).get(row)
                            and all(abs(into["values"][row].get(c, np.nan) - v) < 1e-9
                                    for c, v in cells.items()))
                    if not same:
                        raise ValueError(f"{label}: {kind} row {row!r} differs between the results "
                                         "merged under this label (different runs or objects?)")
                    continue
                into["values"][row] = dict(cells)
                if per_object in table and row in table[per_object]:
                    into.setdefault(per_object, {})[row] = table[per_object][row]
    return merged


def _table_values(results: Mapping, kind: str, objects: str, label: str) -> tuple[dict, int]:
    """({row: {column: percent}}, objects counted) of one run's table, on the chosen objects."""
    table = results[kind]
    if objects == "all":
        return table["values"], int(results.get("objects", 0))
    names = results.get("names")
    per_object = table.get("outcomes" if kind == "table1" else "grasp")
    if names is None or per_object is None:
        raise ValueError(f"{label}: its results.json keeps no per-object {kind} outcomes to "
                         f"recount on {objects} objects")
    keep = _in_subset(names, objects)
    if not keep.any():
        return {}, 0

    def bits(strings) -> np.ndarray:
        arr = np.array([[int(ch) for ch in s] for s in strings], np.uint8)
        if len(arr) != len(names):
            raise ValueError(f"{label}: {kind} has outcomes of {len(arr)} objects for {len(names)} names")
        return arr[keep]

    if kind == "table1":
        return {row: table1_values(bits(out)) for row, out in per_object.items()}, int(keep.sum())
    return ({row: {c: 100.0 * float(bits(cells[c]).mean()) for c in _COLUMNS[kind]}
             for row, cells in per_object.items()}, int(keep.sum()))


def _fresh_set(results: Mapping) -> str | None:
    """Which fresh objects a run evaluated ("48 seed 7"), read from evaluate.py's ``source``;
    None where it says none."""
    m = _FRESH_SOURCE.search(str(results.get("source", "")))
    return f"{m.group(1)} seed {m.group(2)}" if m else None


def paired_over_runs(results: Sequence[Mapping], labels: Sequence[str], after: str, before: str, *,
                     objects: str = "all", n_boot: int = 10000, seed: int = 0) -> dict:
    """Generator ``after`` minus generator ``before`` on the candidates ``research/
    generator_candidates.py --neighbourhood`` simulated for both, run by run and pooled over the runs.

    results / labels as for ``combine_results`` (results with one label are one run; the first of
    them that holds both generators' outcomes counts).  Returns {"runs": {label:
    ``stats.paired_gain``}, "objects": {label: count}, "pooled": {measure: diff, ci_low, ci_high, better, worse, objects,
    clusters}, "skipped": [labels without both]}; ``objects`` "held-out" or "fresh" keeps only
    those objects (as ``combine_results``).

    The pooled interval is a cluster bootstrap: the fresh objects of ``evaluate.py --fresh N
    --seed S`` are the same shapes in every run that used the same N and S, so each of them is
    one cluster of its per-run differences (resampled together), and each run's held-out object
    is a cluster of its own.  Resampling object-run pairs one by one would count the shared fresh
    objects as independent draws and narrow the interval.
    """
    from f2f_jax.tables.stats import PAIRED_MEASURES, paired_gain

    if objects not in OBJECT_SUBSETS:
        raise ValueError(f"objects must be one of {OBJECT_SUBSETS}, got {objects!r}")
    if len(labels) != len(results):
        raise ValueError(f"{len(labels)} labels for {len(results)} runs")
    runs: dict[str, dict] = {}
    pooled_d: dict[str, list] = {m: [] for m in PAIRED_MEASURES}
    keys: list[str] = []
    counts: dict[str, int] = {}
    for label, r in zip(labels, results):
        if label in runs:
            continue
        outcomes = (r.get("neighbourhood") or {}).get("outcomes") or {}
        if after not in outcomes or before not in outcomes:
            continue
        a, b = np.asarray(outcomes[after], np.float64), np.asarray(outcomes[before], np.float64)
        names = r.get("names") or [str(i) for i in range(len(a))]
        if len(names) != len(a) or len(a) != len(b):
            raise ValueError(f"{label}: neighbourhood outcomes of {len(a)} and {len(b)} objects for "
                             f"{len(names)} names")
        if objects != "all":
            keep = _in_subset(names, objects)
            a, b, names = a[keep], b[keep], [n for n, k in zip(names, keep) if k]
            if not len(a):
                continue
        runs[label] = paired_gain(a, b, n_boot=n_boot, seed=seed)
        counts[label] = len(a)
        fresh = _fresh_set(r)
        for m, f in PAIRED_MEASURES.items():
            pooled_d[m].append(f(a) - f(b))
        keys += [f"{n}@{fresh}" if fresh and n.startswith(FRESH_PREFIX) else f"{n}@{label}" for n in names]
    skipped = [lab for lab in dict.fromkeys(labels) if lab not in runs]
    if not runs:
        raise ValueError(f"no run holds neighbourhood outcomes of both {after!r} and {before!r} "
                         "(research/generator_candidates.py --neighbourhood K with both in one call)")
    cluster_names, cluster = np.unique(np.array(keys), return_inverse=True)
    n_clusters = len(cluster_names)
    rng = np.random.default_rng(seed)
    resample = rng.integers(0, n_clusters, (n_boot, n_clusters))
    size = np.bincount(cluster, minlength=n_clusters).astype(np.float64)
    weight = np.stack([np.bincount(row, minlength=n_clusters) for row in resample]).astype(np.float64)
    pooled = {}
    for m, parts in pooled_d.items():
        d = np.concatenate(parts)
        sums = np.bincount(cluster, weights=d, minlength=n_clusters)
        boot = (weight @ sums) / (weight @ size)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        pooled[m] = {"diff": float(d.mean()), "ci_low": float(lo), "ci_high": float(hi),
                     "better": int((d > 0).sum()), "worse": int((d < 0).sum()),
                     "objects": len(d), "clusters": n_clusters}
    return {"runs": runs, "objects": counts, "pooled": pooled, "skipped": skipped}


def paired_markdown(after: str, before: str, gains: Mapping) -> str:
    """``paired_over_runs``'s figures as a markdown table: trials of 11, own design and all
    candidates, run by run and pooled (95% bootstrap intervals; objects better / worse)."""
    def cell(g):
        return (f"{g['diff']:+.2f} [{g['ci_low']:+.2f}, {g['ci_high']:+.2f}] "
                f"({g['better']} / {g['worse']})")

    lines = [f"{after} minus {before}, paired over objects (trials of 11):", "",
             "| run | objects | own design | all candidates |", "|---|---|---|---|"]
    for label, g in gains["runs"].items():
        lines.append(f"| {label} | {gains['objects'][label]} | {cell(g['trials_own'])} | {cell(g['trials_mean'])} |")
    p = gains["pooled"]
    lines.append(f"| pooled | {p['trials_own']['objects']} ({p['trials_own']['clusters']} distinct) | "
                 f"{cell(p['trials_own'])} | {cell(p['trials_mean'])} |")
    if gains["skipped"]:
        lines += ["", f"Runs without both generators' outcomes: {', '.join(gains['skipped'])}."]
    return "\n".join(lines)
