"""Tables 1 and 2: every designer's pairs simulated in one call, counted as the paper counts.

Every figure is a percentage over the evaluated objects, the way the paper (and its code) counts:
an **absolute** rate, not one conditional on a successful grasp.  The original's simulator returns
all-zero scores when the first grasp fails (and for infeasible fingers) and its evaluation averages
each score over every object; ``sim.evaluate`` does the same (trials after a failed grasp are 0),
so ``S_k <= grasp`` holds row by row and a row's R values are grasps that succeeded both at yaw 0
and at the turned pose.  Infeasible designs are simulated as failures (all 0) and each row also
reports its feasible fraction.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES, Config, default
from f2f_jax.errors import DecompositionError, VolumeError
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry.pieces import object_pieces as make_hulls
from f2f_jax.tables import paper as figures  # the paper's numbers; `paper` is a Table field
from f2f_jax.tables.designers import Design, Designer, make_designs, objects_array

log = logging.getLogger(__name__)



TITLES = {"table1": "Table 1: grasp success, stability and robustness (%)",
          "table2": "Table 2: grasp success under perturbed system parameters (%)"}


def column_headers(kind: str, columns: Sequence[str]) -> list[str]:
    """A table's value columns as its markdown header names them (Table 1's turns in degrees)."""
    if kind == "table1":
        return ["Grasp", *figures.STABILITY, "S avg", *(f"{c[1:]}°" for c in figures.ROBUSTNESS), "R avg"]
    return list(columns)


@dataclass
class Table:
    """One evaluation table: our figures beside the paper's.

    kind: "table1" or "table2"; columns: value columns; values: {designer: {column: percent}};
    feasible: {designer: fraction of objects whose two fingers are both feasible};
    outcomes: {designer: [N, 11] uint8} (table1) or {designer: [C, N, 1] uint8} (table2, one
    slice per condition); n_objects: objects evaluated; paper: the published figures
    (PAPER_TABLE1 / PAPER_TABLE2); design_seconds, sim_seconds: wall times; notes: what the
    reader must know (dropped objects, the counting rule).
    """

    kind: str
    columns: tuple[str, ...]
    values: dict[str, dict[str, float]]
    feasible: dict[str, float]
    outcomes: dict[str, np.ndarray]
    n_objects: int
    paper: dict[str, dict[str, float]]
    design_seconds: dict[str, float] = field(default_factory=dict)
    sim_seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    title: str = ""  # the markdown heading; "" for the kind's (TITLES)

    def row_names(self) -> list[str]:
        """The paper's rows in the paper's order, then our rows that are not in the paper."""
        return list(self.paper) + [name for name in self.values if name not in self.paper]

    # -- writers ------------------------------------------------------------------------------

    def to_markdown(self) -> str:
        """A markdown table: per designer an "ours" line and a "paper" line ("not run" where we
        did not evaluate the row, "not in paper" for our extra rows)."""
        title = self.title or TITLES[self.kind]
        head = ["designer", "source", *column_headers(self.kind, self.columns), "feasible", "objects"]
        lines = [f"### {title}", "", "| " + " | ".join(head) + " |",
                 "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|"]
        dash = ["–"] * (len(self.columns) - 1)
        for name in self.row_names():
            if name in self.values:
                ours = [f"{self.values[name][c]:.1f}" for c in self.columns]
                ours += [f"{100 * self.feasible[name]:.0f}%", str(self.n_objects)]
            else:
                ours = ["not run", *dash, "–", "–"]
            lines.append(f"| {name} | ours | " + " | ".join(ours) + " |")
            if name in self.paper:
                paper = [f"{self.paper[name][c]:.1f}" for c in self.columns]
                feas = "100%" if name == "Fit2Form" else "–"  # the appendix states it for Fit2Form
                lines.append("| | paper | " + " | ".join(paper) + f" | {feas} | {figures.PAPER_OBJECTS} |")
            else:
                lines.append("| | paper | not in paper | " + " | ".join(dash + ["–", "–"]) + " |")
        lines.append("")
        lines += [f"- {note}" for note in self.notes]
        return "\n".join(lines) + "\n"

    def csv_rows(self) -> list[dict[str, str]]:
        """One dict per (designer, source): designer, source ("ours"/"paper"), status ("ok",
        "not run", "not in paper"), every column (percent, "" where none), feasible, objects."""
        rows = []
        for name in self.row_names():
            for source, table in (("ours", self.values), ("paper", self.paper)):
                row = {"table": self.kind, "designer": name, "source": source}
                if name in table:
                    row["status"] = "ok"
                    row.update({c: f"{table[name][c]:.2f}" for c in self.columns})
                    if source == "ours":
                        row["feasible"] = f"{self.feasible[name]:.4f}"
                        row["objects"] = str(self.n_objects)
                    else:
                        row["feasible"] = "1.0000" if name == "Fit2Form" else ""
                        row["objects"] = str(figures.PAPER_OBJECTS)
                else:
                    row["status"] = "not run" if source == "ours" else "not in paper"
                    row.update({c: "" for c in self.columns})
                    row["feasible"] = row["objects"] = ""
                rows.append(row)
        return rows

    def to_csv(self) -> str:
        buf = io.StringIO()
        names = ["table", "designer", "source", "status", *self.columns, "feasible", "objects"]
        writer = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.csv_rows())
        return buf.getvalue()

    def plot(self, path) -> Path:
        """A grouped bar chart PNG of our rows (table1: grasp, S avg, R avg per designer; table2:
        grasp success per condition per designer) with the paper's figures as black ticks."""
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        groups = ["grasp", "S avg", "R avg"] if self.kind == "table1" else list(self.columns)
        names = [n for n in self.row_names() if n in self.values]
        fig = Figure(figsize=(max(6.0, 1.1 * len(names) * max(1, len(groups) / 3) + 3), 4.2),
                     dpi=110)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        width = 0.8 / max(1, len(groups))
        x = np.arange(len(names))
        colours = colormaps["tab10"]
        for k, col in enumerate(groups):
            xs = x - 0.4 + width * (k + 0.5)
            vals = [self.values[n][col] for n in names]
            ax.bar(xs, vals, width * 0.95, label=col, color=colours(k % 10))
            for xk, v in zip(xs, vals):
                ax.text(xk, v + 1, f"{v:.0f}", ha="center", va="bottom", fontsize=6)
            paper = [(xk, self.paper[n][col]) for xk, n in zip(xs, names) if n in self.paper]
            if paper:
                px, py = zip(*paper)
                ax.scatter(px, py, marker="_", s=120, color="black", zorder=3,
                           label="paper" if k == 0 else None)
        title = (("Table 1" if self.kind == "table1" else "Table 2: grasp success") +
                 f" ({self.n_objects} objects; black ticks: paper)")
        return save_bar_chart(fig, ax, names, title, path)

    def write(self, directory, stem: str | None = None) -> dict[str, Path]:
        """Write ``<stem>.md``, ``<stem>.csv`` and ``<stem>.png`` (stem default: the kind) into
        ``directory`` atomically.  Returns {"md", "csv", "png"} paths."""
        directory = Path(directory)
        stem = stem or self.kind
        paths = {"md": directory / f"{stem}.md", "csv": directory / f"{stem}.csv"}
        with atomic_path(paths["md"]) as tmp:
            tmp.write_text(self.to_markdown(), encoding="utf-8")
        with atomic_path(paths["csv"]) as tmp:
            tmp.write_text(self.to_csv(), encoding="utf-8")
        paths["png"] = self.plot(directory / f"{stem}.png")
        return paths


def save_bar_chart(fig, ax, names: Sequence[str], title: str, path) -> Path:
    """Finish a table's grouped bar chart (one group per row ``names``, percent axis, legend
    outside) and write it as a PNG to ``path`` atomically."""
    ax.set_xticks(np.arange(len(names)))
    ax.set_xticklabels(names, rotation=15 if len(names) > 4 else 0, fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("% of objects")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def table1_values(outcomes: np.ndarray) -> dict[str, float]:
    """[N, 11] outcomes -> {column: percent}: the mean of each trial over all N objects (absolute,
    not conditional on the grasp), S avg = mean of S1..S4, R avg = mean of R-30..R+30."""
    out = np.asarray(outcomes, np.float64)
    if out.ndim != 2 or out.shape[1] != len(TRIAL_NAMES) or len(out) == 0:
        raise ValueError(f"outcomes: expected [N >= 1, {len(TRIAL_NAMES)}], got {out.shape}")
    rate = dict(zip(TRIAL_NAMES, 100.0 * out.mean(0)))
    values = {c: rate[c] for c in ("grasp", *figures.STABILITY)}
    values["S avg"] = float(np.mean([rate[c] for c in figures.STABILITY]))
    values.update({c: rate[c] for c in figures.ROBUSTNESS})
    values["R avg"] = float(np.mean([rate[c] for c in figures.ROBUSTNESS]))
    return {c: float(values[c]) for c in figures.TABLE1_COLUMNS}


def prepare_objects(objects, cfg: Config, *, object_hulls=None, cache_dir=None,
                    progress: bool = True, return_kept: bool = False):
    """Object volumes and their collision hulls, computed once for all designers and conditions.

    objects: [N, R, R, R]; object_hulls: optional precomputed list of N ``Hulls``.
    Returns (kept objects [M, R, R, R], hulls list of M, notes), and with ``return_kept`` the
    kept objects' indices [M] as a fourth item.  An object whose hulls cannot be made (a
    DecompositionError) is dropped with a note: it says nothing about any finger.
    """
    objs = objects_array(objects, cfg.geometry.resolution)
    if object_hulls is not None:
        hulls = list(object_hulls)
        if len(hulls) != len(objs):
            raise ValueError(f"object_hulls: {len(hulls)} for {len(objs)} objects")
        return (objs, hulls, [], list(range(len(objs)))) if return_kept else (objs, hulls, [])
    items = range(len(objs))
    if progress:
        from tqdm.auto import tqdm

        items = tqdm(items, desc="object hulls", unit="obj")
    keep, hulls, notes = [], [], []
    for i in items:
        try:
            hulls.append(make_hulls(objs[i], cfg, cache_dir=cache_dir))
            keep.append(i)
        except (DecompositionError, VolumeError) as exc:
            notes.append(f"object {i} dropped: its collision hulls failed ({exc})")
            log.warning(notes[-1])
    if not keep:
        raise DecompositionError("no object could be decomposed into collision hulls")
    return (objs[keep], hulls, notes, keep) if return_kept else (objs[keep], hulls, notes)


def grasp_only(cfg: Config) -> Config:
    """``cfg`` simulating the first grasp and lift only (no pushes, no turned grasps): outcome
    vectors of length 1, whose one entry equals the full protocol's first (the grasp is
    simulated first and the later trials start from it)."""
    return cfg.replace(sim=dataclasses.replace(cfg.sim, stability_directions=(), robustness_angles_deg=()))


def _simulate_designs(designers: Mapping[str, Designer | Design], objs, hulls, cfg, backend, progress,
                      object_xy=None, executor: str = "threads", *, store=None, step: str = "table1",
                      made: dict | None = None):
    """Every designer's pairs on ``objs``, simulated.

    Without ``store``: every row designed (``make_designs``), then one sim.evaluate call over all
    pairs (threads stay busy).  With a ``StepStore``: each row's outcomes for ``step`` taken from
    the store when an earlier call finished them (the row is then not even designed), the others
    designed, simulated and saved, row by row on plain MuJoCo threads (a kill loses one row at
    most), all together on a batched backend or Ray (which fill better with more).  made: {name:
    Design} already made in this process (filled in; shared by Table 2's conditions).
    Returns ({designer: [N, T] uint8}, {designer: feasible fraction}, simulation seconds, failed
    count, {designer: design seconds})."""
    made = {} if made is None else made
    names = list(designers)

    def design(names_):
        todo = {k: designers[k] for k in names_ if k not in made}
        made.update(make_designs(todo, objs, progress=progress))
        return {k: made[k] for k in names_}

    def simulate(designs):
        n, keys = len(objs), list(designs)
        start = time.perf_counter()
        out, info = sim.evaluate_with_info(
            np.concatenate([objs] * len(keys)),
            np.concatenate([designs[k].lefts for k in keys]),
            np.concatenate([designs[k].rights for k in keys]),
            backend=backend, cfg=cfg, progress=progress, object_hulls=hulls * len(keys),
            executor=executor,
            **({} if object_xy is None else {"object_xy": np.concatenate([object_xy] * len(keys))}))
        seconds = time.perf_counter() - start
        return ({k: out[j * n:(j + 1) * n] for j, k in enumerate(keys)},
                {k: float(1.0 - info.infeasible[j * n:(j + 1) * n].mean()) for j, k in enumerate(keys)},
                seconds, {k: int(np.count_nonzero(info.failed[j * n:(j + 1) * n])) for j, k in enumerate(keys)})

    if store is None:
        designs = design(names)
        outcomes, feasible, seconds, failed = simulate(designs)
        return (outcomes, feasible, seconds, sum(failed.values()),
                {k: d.seconds for k, d in designs.items()})
    outcomes, feasible, seconds, failed, design_seconds = {}, {}, 0.0, 0, {}
    found = {name: store.load(step, name) for name in names}
    missing = [name for name in names if found[name] is None]
    # plain MuJoCo threads lose nothing by going row by row; a batch (MJX, warp) or a cluster
    # (ray) fills better with every missing row at once, saved when that call ends
    groups = ([[name] for name in missing] if backend == "mujoco" and executor == "threads"
              else [missing] if missing else [])
    for group in groups:
        designs = design(group)
        out, feas, sec, fail = simulate(designs)
        for name in group:
            found[name] = dict(outcomes=out[name], feasible=feas[name], seconds=sec / len(group),
                               failed=fail[name], design_seconds=designs[name].seconds)
            store.save(step, name, **found[name])
    for name in names:
        got = found[name]
        outcomes[name] = np.asarray(got["outcomes"], np.uint8)
        feasible[name] = float(got["feasible"])
        seconds += float(got["seconds"])
        failed += int(got["failed"])
        design_seconds[name] = float(got["design_seconds"])
    return outcomes, feasible, seconds, failed, design_seconds


def _counting_note() -> str:
    return ("Rates are absolute, over all evaluated objects (as the paper's code counts): a failed "
            "first grasp or an infeasible finger scores 0 in all 11 trials, so S and R include "
            "the grasp's failures.")


def table1(designers: Mapping[str, Designer | Design], objects, cfg: Config | None = None, *,
           backend: str = "mujoco", progress: bool = True, object_hulls=None,
           cache_dir=None, executor: str = "threads", store=None, made: dict | None = None,
           step: str = "table1", title: str = "") -> Table:
    """The paper's Table 1 for our designers on ``objects`` [N, 40, 40, 40].

    designers: {row name: designer or precomputed Design}; rows named as in the paper
        ("WSG50", "Imprint", "RandEmb+FN", "ImpGN", "Fit2Form/ImpGN", "Fit2Form GS", ...,
        "Fit2Form") print beside its figures, other names as extra rows.
    Columns (percent): grasp, S1..S4, S avg (mean of S1..S4), R-30..R+30, R avg (mean of the six).
    Rates are absolute over all objects, not conditional on a successful grasp (see the module
    docstring); infeasible designs score 0 and ``Table.feasible`` gives each row's feasible share.
    object_hulls / cache_dir / executor: as in ``sim.evaluate``; backend: "mujoco", "mjx" or "warp".
    store: a ``tables.steps.StepStore`` keeping each row's outcomes as it finishes (resumable
    evaluations; None: one simulation call over all rows); made: {name: Design} made earlier in
    this process, reused and filled in (so Table 2 designs no row twice).  step: the store's name
    for these outcomes (another for the same rows on other objects or fingers); title: the
    markdown heading ("": Table 1's).
    """
    cfg = cfg or default()
    objs, hulls, notes = prepare_objects(objects, cfg, object_hulls=object_hulls,
                                         cache_dir=cache_dir, progress=progress)
    outcomes, feasible, seconds, failed, design_seconds = _simulate_designs(
        designers, objs, hulls, cfg, backend, progress, executor=executor, store=store, made=made,
        step=step)
    if failed:
        notes.append(f"{failed} candidate(s) could not be simulated (model build errors): scored 0")
    notes.append(_counting_note())
    return Table(kind="table1", columns=figures.TABLE1_COLUMNS,
                 values={k: table1_values(v) for k, v in outcomes.items()}, feasible=feasible,
                 outcomes=outcomes, n_objects=len(objs), paper=figures.PAPER_TABLE1,
                 design_seconds=design_seconds, sim_seconds=seconds, notes=notes, title=title)


def position_offsets(n: int, condition: figures.Condition, seed: int = 0) -> np.ndarray | None:
    """[n, 2] object shifts (m) for a condition that moves the object, else None.

    Each axis: sign * uniform(lo, hi), the sign +-1 with equal odds, drawn from
    ``default_rng([seed, crc of the condition's name])``: the same shifts for every designer.
    """
    if not condition.moves_object:
        return None
    rng = np.random.default_rng([seed, int(hashlib.sha1(condition.name.encode()).hexdigest()[:8], 16)])
    out = np.zeros((n, 2))
    for axis, bounds in enumerate((condition.x_range, condition.y_range)):
        if bounds is not None:
            lo, hi = bounds
            out[:, axis] = rng.choice([-1.0, 1.0], n) * rng.uniform(lo, hi, n)
    return out


def table2(designers: Mapping[str, Designer | Design], objects, cfg: Config | None = None, *,
           conditions: Sequence[figures.Condition] = figures.TABLE2_CONDITIONS, backend: str = "mujoco",
           progress: bool = True, object_hulls=None, cache_dir=None, seed: int = 0,
           executor: str = "threads", store=None, made: dict | None = None) -> Table:
    """The paper's Table 2 (appendix): grasp success (percent) of each designer under perturbed
    system parameters: the original setting, object mass 100 g and 150 g, finger-object friction
    0.1 and 0.05, and the object shifted by x in +-[0.1, 0.5] cm with y in +-[0.1, 1] cm or
    +-[0.1, 2] cm (x: the closing direction; ``position_offsets``, seeded by ``seed``).

    The fingers are designed once for the nominal objects (the designer does not see the
    perturbation).  Shifts exist on the "mujoco" backend only: with a batched backend those
    conditions run on "mujoco" (said in the notes).  The table scores the first grasp only, so
    only that trial is simulated (the pushes and turned grasps that follow a held grasp cannot
    change it): ``Table.outcomes[name]`` is [C, N, 1]; ``feasible`` as in ``table1``; executor:
    as in ``sim.evaluate``; store, made: as in ``table1`` (a row's outcomes kept per condition).
    """
    cfg = cfg or default()
    objs, hulls, notes = prepare_objects(objects, cfg, object_hulls=object_hulls,
                                         cache_dir=cache_dir, progress=progress)
    made = {} if made is None else made
    per_condition, feasible, seconds, design_seconds = {}, {}, 0.0, {}
    items = conditions
    if progress:
        from tqdm.auto import tqdm

        items = tqdm(conditions, desc="table 2 conditions", unit="cond")
    for cond in items:
        cond_backend = "mujoco" if cond.moves_object else backend
        if cond_backend != backend:
            notes.append(f"{cond.name}: simulated with plain MuJoCo (MJX places every object at "
                         "the grasp location)")
        out, feasible, sec, failed, design_seconds = _simulate_designs(
            designers, objs, hulls, grasp_only(cond.config(cfg)), cond_backend, progress,
            object_xy=position_offsets(len(objs), cond, seed), executor=executor, store=store,
            step=f"table2/{cond.name}", made=made)
        per_condition[cond.name] = out
        seconds += sec
        if failed:
            notes.append(f"{cond.name}: {failed} candidate(s) could not be simulated: scored 0")
    names = list(designers)
    values = {k: {c.name: float(100.0 * per_condition[c.name][k][:, 0].mean()) for c in conditions}
              for k in names}
    outcomes = {k: np.stack([per_condition[c.name][k] for c in conditions]) for k in names}
    notes.append("Friction is the finger-object coefficient (the paper changes the object's "
                 "lateral friction); shifts are drawn once per object, the same for every designer.")
    return Table(kind="table2", columns=tuple(c.name for c in conditions), values=values,
                 feasible=feasible, outcomes=outcomes, n_objects=len(objs), paper=figures.PAPER_TABLE2,
                 design_seconds=design_seconds, sim_seconds=seconds, notes=notes)


