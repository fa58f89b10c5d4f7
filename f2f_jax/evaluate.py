"""The paper's evaluation tables for any set of finger designers.

A **designer** is a callable ``objects [N, 40, 40, 40] float32 -> (lefts, rights)``, two numpy
arrays ``[N, 40, 40, 40]`` float32 of finger TSDFs in the finger frame of ``f2f_jax.config``.
This module provides the paper's rows as designers (``wsg_fmf_designer``, the paper's WSG50
fingers; ``wsg50_designer``, flat pads; ``imprint_designer``,
``models_designer`` for a trained generator, ``random_embedding_designer`` for RandEmb+FN) and
``pair_designer`` to turn any per-object function (such as ``f2f_jax.design``) into one.

    designers = {"WSG50": wsg50_designer(cfg), "Imprint": imprint_designer(cfg)}
    t1 = table1(designers, objects, cfg)          # grasp, S1..S4, S avg, R-30..R+30, R avg
    t2 = table2(designers, objects, cfg)          # grasp success under the paper's perturbations
    t1.write("runs/eval", "table1")               # table1.md (ours beside the paper), .csv, .png

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
import functools
import hashlib
import io
import logging
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from f2f_jax import sim
from f2f_jax.config import TRIAL_NAMES, Config
from f2f_jax.data.sources import wsg_fmf_fingers
from f2f_jax.errors import DecompositionError, F2FError, VolumeError
from f2f_jax.fileio import atomic_path
from f2f_jax.designer import simulate_candidates
from f2f_jax.geometry.pieces import object_pieces as make_hulls
from f2f_jax.geometry import imprint_fingers, is_feasible, largest_component, postprocess, wsg50_fingers
from f2f_jax.nets import FingerGenerator, FitnessNet, fitness_input
from f2f_jax.nets.inference import LATENT_NOISE, predict, propose
from f2f_jax.train.steps import generate_batched

log = logging.getLogger(__name__)

Designer = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

# --------------------------------------------------------------------------------------------
# The paper's tables (fit2form-corl2020.tex, Table 1 and the appendix's Table 2), in percent
# --------------------------------------------------------------------------------------------

TABLE1_COLUMNS: tuple[str, ...] = (
    "grasp", "S1", "S2", "S3", "S4", "S avg", "R-30", "R-20", "R-10", "R+10", "R+20", "R+30", "R avg",
)
_STABILITY = ("S1", "S2", "S3", "S4")
_ROBUSTNESS = ("R-30", "R-20", "R-10", "R+10", "R+20", "R+30")

PAPER_OBJECTS = 5127  # the paper's evaluation objects (8 unseen ShapeNet categories + Dex-Net)

PAPER_TABLE1: dict[str, dict[str, float]] = {name: dict(zip(TABLE1_COLUMNS, values)) for name, values in (
    ("WSG50", (25.8, 3.3, 2.1, 2.1, 1.9, 2.4, 12.2, 14.3, 17.6, 17.5, 14.6, 12.9, 14.8)),
    ("Imprint", (78.0, 64.9, 59.0, 57.3, 57.8, 59.8, 66.6, 68.9, 70.7, 70.0, 68.7, 67.0, 68.7)),
    ("RandEmb+FN", (21.3, 12.4, 6.5, 6.8, 6.6, 8.1, 12.7, 13.9, 16.4, 16.2, 13.4, 11.9, 14.1)),
    ("ImpGN", (28.9, 13.3, 10.4, 10.5, 10.3, 11.1, 17.1, 20.0, 23.2, 23.0, 19.5, 16.3, 19.8)),
    ("Fit2Form/ImpGN", (81.8, 65.6, 54.8, 59.0, 56.6, 59.0, 72.0, 73.9, 76.2, 75.1, 74.2, 73.4, 74.1)),
    ("Fit2Form GS", (85.2, 64.3, 57.0, 58.6, 53.3, 58.3, 71.0, 75.2, 78.5, 78.0, 74.0, 69.7, 74.4)),
    ("Fit2Form GS + R", (81.8, 62.8, 51.9, 53.3, 50.9, 54.7, 70.6, 72.9, 75.5, 74.6, 71.9, 69.5, 72.5)),
    ("Fit2Form GS + S", (87.5, 70.8, 66.0, 62.6, 64.1, 65.9, 75.7, 78.1, 81.4, 81.2, 78.3, 75.3, 78.3)),
    ("Fit2Form", (87.6, 69.0, 61.6, 60.5, 61.7, 63.2, 76.1, 78.3, 81.1, 81.1, 79.2, 76.8, 78.8)),
)}


@dataclass(frozen=True)
class Condition:
    """One column of Table 2: a change of the physics or of where the object lies.

    object_mass: kg (None: the config's 50 g); friction: finger-object coefficient (None: the
    config's 0.2); x_range, y_range: (lo, hi) m of the object's shift along x (the closing
    direction) and y, each drawn per object as sign * uniform(lo, hi) with a random sign
    (the paper's "x in +-[0.1, 0.5], y in +-[0.1, 1] cm"); None: no shift.
    """

    name: str
    object_mass: float | None = None
    friction: float | None = None
    x_range: tuple[float, float] | None = None
    y_range: tuple[float, float] | None = None

    def config(self, cfg: Config) -> Config:
        """``cfg`` with this condition's mass and friction (``SimConfig.object_mass`` and
        ``SimConfig.finger_friction``, which ``sim.evaluate`` passes to ``scene.build_model``).

        The paper changes the object's lateral friction; in PyBullet that multiplies into every
        contact of the object, here only the finger-object coefficient changes (the floor keeps
        ``object_friction``): what a grasp holds on to is the same, sliding on the floor is not.
        """
        changes = {}
        if self.object_mass is not None:
            changes["object_mass"] = float(self.object_mass)
        if self.friction is not None:
            changes["finger_friction"] = float(self.friction)
        return cfg.replace(sim=dataclasses.replace(cfg.sim, **changes)) if changes else cfg

    @property
    def moves_object(self) -> bool:
        return self.x_range is not None or self.y_range is not None


TABLE2_CONDITIONS: tuple[Condition, ...] = (
    Condition("Original"),
    Condition("m 100g", object_mass=0.100),
    Condition("m 150g", object_mass=0.150),
    Condition("mu 0.1", friction=0.1),
    Condition("mu 0.05", friction=0.05),
    Condition("x ±0.5, y ±1 cm", x_range=(0.001, 0.005), y_range=(0.001, 0.010)),
    Condition("x ±0.5, y ±2 cm", x_range=(0.001, 0.005), y_range=(0.001, 0.020)),
)
TABLE2_COLUMNS: tuple[str, ...] = tuple(c.name for c in TABLE2_CONDITIONS)

PAPER_TABLE2: dict[str, dict[str, float]] = {name: dict(zip(TABLE2_COLUMNS, values)) for name, values in (
    ("WSG50", (25.8, 2.2, 1.5, 6.7, 2.0, 24.8, 21.8)),
    ("Imprint", (78.0, 57.9, 49.4, 68.4, 63.9, 75.6, 72.8)),
    ("Fit2Form", (88.9, 63.9, 51.6, 76.3, 73.0, 86.3, 83.6)),
)}

# What a checkpoint's ``Models.objectives`` is called in Table 1.
OBJECTIVE_ROWS = {"full": "Fit2Form", "GS": "Fit2Form GS", "GS+R": "Fit2Form GS + R",
                  "GS+S": "Fit2Form GS + S"}


# --------------------------------------------------------------------------------------------
# Designers
# --------------------------------------------------------------------------------------------

def _objects_array(objects, r: int = 40) -> np.ndarray:
    arr = np.asarray(objects, np.float32)
    if arr.ndim != 4 or arr.shape[1:] != (r, r, r):
        raise VolumeError(f"objects: expected shape [N, {r}, {r}, {r}], got {arr.shape}")
    return arr


def _empty_finger(r: int = 40) -> np.ndarray:
    """A finger with no solid voxel: infeasible, scored 0 without simulation."""
    return np.ones((r, r, r), np.float32)


def _fixed_pair_designer(left: np.ndarray, right: np.ndarray) -> Designer:
    """The same finger pair for every object."""

    def design(objects):
        n = len(_objects_array(objects))
        return np.repeat(left[None], n, 0), np.repeat(right[None], n, 0)

    return design


def wsg50_designer(cfg: Config | None = None) -> Designer:
    """The WSG50's flat fingertips (``geometry.wsg50_fingers``) for every object."""
    return _fixed_pair_designer(*wsg50_fingers(cfg))


def wsg_fmf_designer(cfg: Config | None = None) -> Designer:
    """The paper's WSG50 row: Schunk's standard WSG-FMF fingers (``data.sources.wsg_fmf_fingers``,
    the mesh of the pybullet extra) for every object.  Raises MissingExtraError without it."""
    return _fixed_pair_designer(*wsg_fmf_fingers(cfg))


def imprint_designer(cfg: Config | None = None) -> Designer:
    """Imprint fingers (``geometry.imprint_fingers``: the object's two views along the closing
    axis, negated and split) of every object."""

    def design(objects):
        pairs = [imprint_fingers(o, cfg) for o in _objects_array(objects)]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])

    return design


def _postprocess(fingers: np.ndarray) -> np.ndarray:
    """Largest face-connected component of each finger, as co-training does: [B, R, R, R]."""
    return np.stack([largest_component(f) for f in np.asarray(fingers, np.float32)])


def models_designer(models, *, batch: int = 8) -> Designer:
    """A trained generator (``nets.inference.Models``): ``Models.generate`` then the largest
    connected component of each finger, as in training (an infeasible result stays infeasible
    and scores 0).  batch: objects per call (``train.steps.generate_batched``)."""

    def design(objects):
        lefts, rights = generate_batched(models.config.net, models.generator,
                                         _objects_array(objects), batch)
        return _postprocess(lefts), _postprocess(rights)

    return design


@functools.lru_cache(maxsize=8)
def _randemb_optimizer(net, steps: int, lr: float, objective: str):
    """Jitted ``(gvars, fvars, obj [R,R,R], z0 [S,2,D]) -> (z [S,2,D], score [S])``: Adam on the
    finger latents (projected onto the latent box [-1, 1]^D) to maximise the fitness net's
    prediction for the decoded fingers.  net: the NetConfig (cached per config: one compile)."""
    gen, fit = FingerGenerator(net), FitnessNet(net)
    opt = optax.adam(lr)

    def decode(gvars, z):  # [M, D] -> [M, R, R, R]
        return gen.apply(gvars, z, method=lambda m, z: m.decoder(z, train=False))

    def score(gvars, fvars, obj, z):  # [S]
        s, _, d = z.shape
        fingers = decode(gvars, z.reshape(2 * s, d)).reshape(s, 2, *obj.shape)
        objs = jnp.broadcast_to(obj, (s, *obj.shape))
        p = jax.nn.sigmoid(fit.apply(fvars, fitness_input(objs, fingers[:, 0], fingers[:, 1]),
                                     train=False))
        return p[:, 0] if objective == "grasp" else p.mean(-1)

    def run(gvars, fvars, obj, z0):
        def step(carry, _):
            z, opt_state = carry
            grads = jax.grad(lambda z: -score(gvars, fvars, obj, z).sum())(z)
            updates, opt_state = opt.update(grads, opt_state, z)
            z = jnp.clip(optax.apply_updates(z, updates), -1.0, 1.0)
            return (z, opt_state), None

        (z, _), _ = jax.lax.scan(step, (z0, opt.init(z0)), None, length=steps)
        return z, decode(gvars, z.reshape(-1, z.shape[-1]))

    return jax.jit(run)


def random_embedding_designer(models, key, *, samples: int = 8, steps: int = 200, lr: float = 0.02,
                              objective: str = "grasp") -> Designer:
    """The paper's RandEmb+FN baseline: test-time optimisation of random finger embeddings with
    the shape decoder and the fitness net, without the generator's embedding network.

    Per object: ``samples`` random (left, right) latent pairs uniform in the latent box
    [-1, 1]^D, each optimised by Adam (``lr``) for ``steps`` steps (paper: 200) to maximise the
    fitness net's predicted grasp success (``objective="grasp"``) or the mean of its 11 outputs
    ("mean"); then decoded, reduced to their largest connected components, and the feasible pair
    the fitness net scores best is kept (the best infeasible one if none is feasible: it scores 0).
    key: a JAX PRNG key; object i uses ``fold_in(key, i)``, so a design does not depend on batching.
    """
    if objective not in ("grasp", "mean"):
        raise ValueError(f"objective: 'grasp' or 'mean', got {objective!r}")
    if samples < 1 or steps < 0:
        raise ValueError(f"samples must be >= 1 and steps >= 0, got {samples} and {steps}")
    run = _randemb_optimizer(models.config.net, int(steps), float(lr), objective)
    d = models.config.net.latent_dim
    out_index = 0 if objective == "grasp" else slice(None)

    def design(objects):
        objs = _objects_array(objects)
        lefts, rights = [], []
        for i, obj in enumerate(objs):
            z0 = jax.random.uniform(jax.random.fold_in(key, i), (samples, 2, d), minval=-1.0,
                                    maxval=1.0)
            _, fingers = run(models.generator, models.fitness, obj, z0)
            # decoded from z.reshape(2S, D): row 2s is sample s's left finger, row 2s + 1 its right
            fingers = _postprocess(np.asarray(fingers)).reshape(samples, 2, *obj.shape)
            left, right = fingers[:, 0], fingers[:, 1]
            pred = np.asarray(models.predict(np.repeat(obj[None], samples, 0), left, right))
            score = pred[:, out_index] if objective == "grasp" else pred.mean(-1)
            ok = np.array([is_feasible(left[k]) and is_feasible(right[k]) for k in range(samples)])
            best = int(np.argmax(np.where(ok, score, -np.inf))) if ok.any() else int(np.argmax(score))
            lefts.append(left[best])
            rights.append(right[best])
        return np.stack(lefts), np.stack(rights)

    return design


def _pair(pair) -> tuple[np.ndarray, np.ndarray]:
    left, right = (pair.left, pair.right) if hasattr(pair, "left") else pair
    return np.asarray(left, np.float32), np.asarray(right, np.float32)


def pair_designer(fn: Callable[[np.ndarray], Any], *, batched: bool = False, progress: bool = False,
                  desc: str = "design") -> Designer:
    """Any design function as a designer: ``fn(obj [R, R, R]) -> pair`` where the pair is
    ``(left, right)`` or has ``.left`` and ``.right`` (``f2f_jax.design``'s FingerPair); with
    ``batched=True``, ``fn(objects [N, R, R, R]) -> N pairs`` in one call (falling back to one
    object at a time if that call raises F2FError).  A per-object call that raises F2FError
    gives an empty (infeasible, scored 0) pair and a warning.

        search = pair_designer(lambda o: f2f_jax.design(o, params=models, candidates=64,
                                                        verify=True), batched=True)
    """

    def design(objects):
        objs = _objects_array(objects)
        if batched:
            try:
                pairs = [_pair(p) for p in fn(objs)]
                if len(pairs) != len(objs):
                    raise VolumeError(f"{desc}: {len(pairs)} pairs for {len(objs)} objects")
                return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])
            except F2FError as exc:
                warnings.warn(f"{desc}: the batch failed ({exc}); designing one object at a time",
                              RuntimeWarning, stacklevel=2)
                fn_one = lambda o: fn(o[None])[0]  # noqa: E731
        else:
            fn_one = fn
        items = enumerate(objs)
        if progress:
            from tqdm.auto import tqdm

            items = tqdm(items, total=len(objs), desc=desc, unit="obj")
        lefts, rights = [], []
        for i, obj in items:
            try:
                left, right = _pair(fn_one(obj))
            except F2FError as exc:
                warnings.warn(f"{desc}: object {i}: {exc}; scored as infeasible", RuntimeWarning,
                              stacklevel=2)
                left = right = _empty_finger(obj.shape[0])
            lefts.append(np.asarray(left, np.float32))
            rights.append(np.asarray(right, np.float32))
        return np.stack(lefts), np.stack(rights)

    return design


@dataclass
class Design:
    """A designer's fingers for an object set: lefts, rights [N, R, R, R] float32; seconds."""

    lefts: np.ndarray
    rights: np.ndarray
    seconds: float = 0.0


def make_designs(designers: Mapping[str, Designer | Design], objects, *,
                 progress: bool = True) -> dict[str, Design]:
    """Run each designer once on ``objects [N, R, R, R]``; a ``Design`` passes through (so one
    set of designs can serve both tables).  Raises VolumeError naming a designer whose output
    has the wrong shape or NaN values."""
    objs = _objects_array(objects)
    out = {}
    for name, designer in designers.items():
        if isinstance(designer, Design):
            d = designer
        else:
            start = time.perf_counter()
            if progress:
                log.info("designing %d objects with %s", len(objs), name)
            lefts, rights = designer(objs)
            d = Design(np.asarray(lefts, np.float32), np.asarray(rights, np.float32),
                       time.perf_counter() - start)
        for side, arr in (("lefts", d.lefts), ("rights", d.rights)):
            if arr.shape != objs.shape:
                raise VolumeError(f"designer {name!r}: {side} have shape {arr.shape}, expected "
                                  f"{objs.shape}")
            if not np.all(np.isfinite(arr)):
                raise VolumeError(f"designer {name!r}: {side} contain NaN/inf values")
        out[name] = d
    return out


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------

@dataclass
class Table:
    """One evaluation table: our figures beside the paper's.

    kind: "table1" or "table2"; columns: value columns; values: {designer: {column: percent}};
    feasible: {designer: fraction of objects whose two fingers are both feasible};
    outcomes: {designer: [N, 11] uint8} (table1) or {designer: [C, N, 11] uint8} (table2, one
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

    def row_names(self) -> list[str]:
        """The paper's rows in the paper's order, then our rows that are not in the paper."""
        return list(self.paper) + [name for name in self.values if name not in self.paper]

    # -- writers ------------------------------------------------------------------------------
    def _headers(self) -> list[str]:
        if self.kind == "table1":
            return ["Grasp", *_STABILITY, "S avg", *(f"{c[1:]}°" for c in _ROBUSTNESS), "R avg"]
        return list(self.columns)

    def to_markdown(self) -> str:
        """A markdown table: per designer an "ours" line and a "paper" line ("not run" where we
        did not evaluate the row, "not in paper" for our extra rows)."""
        title = ("Table 1: grasp success, stability and robustness (%)" if self.kind == "table1"
                 else "Table 2: grasp success under perturbed system parameters (%)")
        head = ["designer", "source", *self._headers(), "feasible", "objects"]
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
                lines.append("| | paper | " + " | ".join(paper) + f" | {feas} | {PAPER_OBJECTS} |")
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
                        row["objects"] = str(PAPER_OBJECTS)
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
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=15 if len(names) > 4 else 0, fontsize=8)
        ax.set_ylim(0, 105)
        ax.set_ylabel("% of objects")
        ax.set_title(("Table 1" if self.kind == "table1" else "Table 2: grasp success") +
                     f" ({self.n_objects} objects; black ticks: paper)", fontsize=9)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        path = Path(path)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
        return path

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


def table1_values(outcomes: np.ndarray) -> dict[str, float]:
    """[N, 11] outcomes -> {column: percent}: the mean of each trial over all N objects (absolute,
    not conditional on the grasp), S avg = mean of S1..S4, R avg = mean of R-30..R+30."""
    out = np.asarray(outcomes, np.float64)
    if out.ndim != 2 or out.shape[1] != len(TRIAL_NAMES) or len(out) == 0:
        raise ValueError(f"outcomes: expected [N >= 1, {len(TRIAL_NAMES)}], got {out.shape}")
    rate = dict(zip(TRIAL_NAMES, 100.0 * out.mean(0)))
    values = {c: rate[c] for c in ("grasp", *_STABILITY)}
    values["S avg"] = float(np.mean([rate[c] for c in _STABILITY]))
    values.update({c: rate[c] for c in _ROBUSTNESS})
    values["R avg"] = float(np.mean([rate[c] for c in _ROBUSTNESS]))
    return {c: float(values[c]) for c in TABLE1_COLUMNS}


def prepare_objects(objects, cfg: Config, *, object_hulls=None, cache_dir=None,
                    progress: bool = True):
    """Object volumes and their collision hulls, computed once for all designers and conditions.

    objects: [N, R, R, R]; object_hulls: optional precomputed list of N ``Hulls``.
    Returns (kept objects [M, R, R, R], hulls list of M, notes).  An object whose hulls cannot be
    made (a DecompositionError) is dropped with a note: it says nothing about any finger.
    """
    objs = _objects_array(objects, cfg.geometry.resolution)
    if object_hulls is not None:
        hulls = list(object_hulls)
        if len(hulls) != len(objs):
            raise ValueError(f"object_hulls: {len(hulls)} for {len(objs)} objects")
        return objs, hulls, []
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
    return objs[keep], hulls, notes


def _simulate_designs(designs: dict[str, Design], objs, hulls, cfg, backend, progress,
                      object_xy=None, executor: str = "threads"):
    """One sim.evaluate call over every designer's pairs (threads stay busy).
    Returns ({designer: [N, 11] uint8}, {designer: feasible fraction}, seconds, failed count)."""
    names = list(designs)
    n = len(objs)
    start = time.perf_counter()
    out, info = sim.evaluate(
        np.concatenate([objs] * len(names)),
        np.concatenate([designs[k].lefts for k in names]),
        np.concatenate([designs[k].rights for k in names]),
        backend=backend, cfg=cfg, progress=progress, object_hulls=hulls * len(names),
        return_info=True, executor=executor,
        **({} if object_xy is None else {"object_xy": np.concatenate([object_xy] * len(names))}))
    seconds = time.perf_counter() - start
    outcomes = {k: out[j * n:(j + 1) * n] for j, k in enumerate(names)}
    feasible = {k: float(1.0 - info.infeasible[j * n:(j + 1) * n].mean()) for j, k in enumerate(names)}
    return outcomes, feasible, seconds, int(np.count_nonzero(info.failed))


def _counting_note() -> str:
    return ("Rates are absolute, over all evaluated objects (as the paper's code counts): a failed "
            "first grasp or an infeasible finger scores 0 in all 11 trials, so S and R include "
            "the grasp's failures.")


def table1(designers: Mapping[str, Designer | Design], objects, cfg: Config | None = None, *,
           backend: str = "mujoco", progress: bool = True, object_hulls=None,
           cache_dir=None, executor: str = "threads") -> Table:
    """The paper's Table 1 for our designers on ``objects`` [N, 40, 40, 40].

    designers: {row name: designer or precomputed Design}; rows named as in the paper
        ("WSG50", "Imprint", "RandEmb+FN", "ImpGN", "Fit2Form/ImpGN", "Fit2Form GS", ...,
        "Fit2Form") print beside its figures, other names as extra rows.
    Columns (percent): grasp, S1..S4, S avg (mean of S1..S4), R-30..R+30, R avg (mean of the six).
    Rates are absolute over all objects, not conditional on a successful grasp (see the module
    docstring); infeasible designs score 0 and ``Table.feasible`` gives each row's feasible share.
    object_hulls / cache_dir / executor: as in ``sim.evaluate``; backend: "mujoco", "mjx" or "warp".
    """
    from f2f_jax.config import default

    cfg = cfg or default()
    objs, hulls, notes = prepare_objects(objects, cfg, object_hulls=object_hulls,
                                         cache_dir=cache_dir, progress=progress)
    designs = make_designs(designers, objs, progress=progress)
    outcomes, feasible, seconds, failed = _simulate_designs(designs, objs, hulls, cfg, backend,
                                                            progress, executor=executor)
    if failed:
        notes.append(f"{failed} candidate(s) could not be simulated (model build errors): scored 0")
    notes.append(_counting_note())
    return Table(kind="table1", columns=TABLE1_COLUMNS,
                 values={k: table1_values(v) for k, v in outcomes.items()}, feasible=feasible,
                 outcomes=outcomes, n_objects=len(objs), paper=PAPER_TABLE1,
                 design_seconds={k: d.seconds for k, d in designs.items()}, sim_seconds=seconds,
                 notes=notes)


def position_offsets(n: int, condition: Condition, seed: int = 0) -> np.ndarray | None:
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
           conditions: Sequence[Condition] = TABLE2_CONDITIONS, backend: str = "mujoco",
           progress: bool = True, object_hulls=None, cache_dir=None, seed: int = 0,
           executor: str = "threads") -> Table:
    """The paper's Table 2 (appendix): grasp success (percent) of each designer under perturbed
    system parameters: the original setting, object mass 100 g and 150 g, finger-object friction
    0.1 and 0.05, and the object shifted by x in +-[0.1, 0.5] cm with y in +-[0.1, 1] cm or
    +-[0.1, 2] cm (x: the closing direction; ``position_offsets``, seeded by ``seed``).

    The fingers are designed once for the nominal objects (the designer does not see the
    perturbation).  Shifts exist on the "mujoco" backend only: with a batched backend those
    conditions run on "mujoco" (said in the notes).  ``Table.outcomes[name]`` is [C, N, 11];
    ``feasible`` as in ``table1``; executor: as in ``sim.evaluate``.
    """
    from f2f_jax.config import default

    cfg = cfg or default()
    objs, hulls, notes = prepare_objects(objects, cfg, object_hulls=object_hulls,
                                         cache_dir=cache_dir, progress=progress)
    designs = make_designs(designers, objs, progress=progress)
    per_condition, feasible, seconds = {}, {}, 0.0
    items = conditions
    if progress:
        from tqdm.auto import tqdm

        items = tqdm(conditions, desc="table 2 conditions", unit="cond")
    for cond in items:
        cond_backend = "mujoco" if cond.moves_object else backend
        if cond_backend != backend:
            notes.append(f"{cond.name}: simulated with plain MuJoCo (MJX places every object at "
                         "the grasp location)")
        out, feasible, sec, failed = _simulate_designs(
            designs, objs, hulls, cond.config(cfg), cond_backend, progress,
            object_xy=position_offsets(len(objs), cond, seed), executor=executor)
        per_condition[cond.name] = out
        seconds += sec
        if failed:
            notes.append(f"{cond.name}: {failed} candidate(s) could not be simulated: scored 0")
    names = list(designs)
    values = {k: {c.name: float(100.0 * per_condition[c.name][k][:, 0].mean()) for c in conditions}
              for k in names}
    outcomes = {k: np.stack([per_condition[c.name][k] for c in conditions]) for k in names}
    notes.append("Friction is the finger-object coefficient (the paper changes the object's "
                 "lateral friction); shifts are drawn once per object, the same for every designer.")
    return Table(kind="table2", columns=tuple(c.name for c in conditions), values=values,
                 feasible=feasible, outcomes=outcomes, n_objects=len(objs), paper=PAPER_TABLE2,
                 design_seconds={k: d.seconds for k, d in designs.items()}, sim_seconds=seconds,
                 notes=notes)


# --------------------------------------------------------------------------------------------
# Does the fitness net rank the designs of one object?
# --------------------------------------------------------------------------------------------

def ranking_stats(predicted: np.ndarray, simulated: np.ndarray) -> dict[str, float]:
    """How well predicted success ranks several candidate designs of the same objects.

    predicted: [N, K, 11] fitness-net probabilities; simulated: [N, K, 11] 0/1 outcomes of the
    same candidates.  A candidate's score is its mean predicted probability, its value the number
    of trials it passed.  Returns:

    - ``spearman``: Spearman rank correlation of score and value within each object, averaged over
      the objects whose candidates differ in value (nan when none do); ``objects_ranked`` counts them.
    - ``trials_first``, ``trials_mean``, ``trials_picked``, ``trials_best``, ``trials_worst``:
      trials passed (of 11) by candidate 0, by the average candidate, by the one the fitness net
      scores highest, by the best and the worst simulated one (means over objects).
    - ``grasp_auc``: AUC of the predicted grasp probability for the simulated grasp over all
      N x K candidates pooled (nan when every grasp succeeded or every one failed); it rewards
      telling easy objects from hard ones too, which ``spearman`` does not.

    The gap between ``trials_picked`` and ``trials_mean`` is what the fitness net's guidance is
    worth to a generator that climbs it; ``trials_best`` - ``trials_first`` is the room there is.
    """
    from scipy.stats import rankdata

    p = np.asarray(predicted, np.float64)
    s = np.asarray(simulated, np.float64)
    if p.shape != s.shape or p.ndim != 3:
        raise ValueError(f"predicted {p.shape} and simulated {s.shape}: expected two [N, K, 11] arrays")
    score, value = p.mean(-1), s.sum(-1)
    rhos = []
    for sc, va in zip(score, value):
        if np.ptp(va) == 0 or np.ptp(sc) == 0:
            continue
        rhos.append(np.corrcoef(rankdata(sc), rankdata(va))[0, 1])
    rows = np.arange(len(score))
    grasp, prob = s[..., 0].ravel(), p[..., 0].ravel()
    pos, neg = prob[grasp == 1], prob[grasp == 0]
    if len(pos) and len(neg):  # Mann-Whitney: P(score of a held grasp > score of a failed one)
        ranks = rankdata(np.concatenate([pos, neg]))
        auc = (ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg))
    else:
        auc = float("nan")
    return {
        "spearman": float(np.mean(rhos)) if rhos else float("nan"),
        "objects_ranked": len(rhos),
        "trials_first": float(value[:, 0].mean()),
        "trials_mean": float(value.mean()),
        "trials_picked": float(value[rows, score.argmax(1)].mean()),
        "trials_best": float(value.max(1).mean()),
        "trials_worst": float(value.min(1).mean()),
        "grasp_auc": float(auc),
    }


def candidate_outcomes(models, objects, cfg: Config | None = None, *, candidates: int = 8,
                       noise: float | None = None, key=0, backend: str = "mujoco",
                       object_hulls=None, progress: bool | None = None,
                       executor: str = "threads"):
    """``f2f_jax.design``'s candidates for every object, all simulated.

    Per object the generator's own output and ``candidates - 1`` latent perturbations (``noise``,
    default ``nets.inference.LATENT_NOISE``), post-processed; infeasible ones score 0 by the protocol.
    objects: [N, 40, 40, 40]; object_hulls: optional, one per object; executor: as in
    ``sim.evaluate``.
    Returns (lefts, rights [N, K, 40, 40, 40], feasible [N, K], simulated [N, K, 11] uint8).
    """
    if candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    cfg = cfg or models.config
    objs = _objects_array(objects, cfg.geometry.resolution)
    lefts, rights = propose(models, objs, key, candidates, LATENT_NOISE if noise is None else noise)
    feasible = postprocess(lefts, rights, cfg.geometry)
    simulated = simulate_candidates(dataclasses.replace(models, config=cfg), objs, lefts, rights,
                                    feasible, backend, progress, object_hulls, executor=executor)
    return lefts, rights, feasible, simulated


def fitness_ranking(models, objects, cfg: Config | None = None, *, candidates: int = 16,
                    noise: float | None = None, key=0, backend: str = "mujoco",
                    object_hulls=None, progress: bool | None = None,
                    executor: str = "threads") -> dict[str, float]:
    """``ranking_stats`` of a trained run's fitness net on ``candidates`` designs per object.

    The candidates are ``candidate_outcomes``' (the generator's own output and K - 1 latent
    perturbations), all simulated and scored by the fitness net.  This is the measurement behind
    the co-training's premise: a generator that climbs the fitness net can only improve on what
    the net ranks right.  objects: [N, 40, 40, 40]; object_hulls: one per object.
    """
    if candidates < 2:
        raise ValueError(f"candidates must be >= 2 to rank anything, got {candidates}")
    cfg = cfg or models.config
    objs = _objects_array(objects, cfg.geometry.resolution)
    lefts, rights, feasible, simulated = candidate_outcomes(
        models, objs, cfg, candidates=candidates, noise=noise, key=key, backend=backend,
        object_hulls=object_hulls, progress=progress, executor=executor)
    predicted = predict(models, objs, lefts, rights)
    n, k = feasible.shape
    out = ranking_stats(predicted, simulated)
    out.update(objects=n, candidates=k, feasible=float(feasible.mean()))
    return out


# --------------------------------------------------------------------------------------------
# Is one generator better than another?  Paired over objects, on each one's design neighbourhood.
# --------------------------------------------------------------------------------------------

def neighbourhood_stats(simulated: np.ndarray) -> dict[str, float]:
    """Summary of [N, K, 11] outcomes of K candidates per object (candidate 0: the generator's own).

    ``trials_own`` / ``grasp_own``: trials passed (of 11) and grasp success of the own designs;
    ``trials_mean`` / ``grasp_mean``: the same over all K candidates.  The K-candidate means score
    the generator's output and its latent neighbourhood, not one 0/1 draw per object, so they
    separate two generators with far fewer objects than the own designs alone do.
    """
    s = np.asarray(simulated, np.float64)
    if s.ndim != 3:
        raise ValueError(f"simulated {s.shape}: expected [N, K, 11]")
    return {"trials_own": float(s[:, 0].sum(-1).mean()), "grasp_own": float(s[:, 0, 0].mean()),
            "trials_mean": float(s.sum(-1).mean()), "grasp_mean": float(s[..., 0].mean()),
            "objects": s.shape[0], "candidates": s.shape[1]}


def paired_gain(after: np.ndarray, before: np.ndarray, *, n_boot: int = 10000,
                seed: int = 0) -> dict[str, dict[str, float]]:
    """How much ``after`` beats ``before`` on the same objects, with a bootstrap over objects.

    after, before: [N, K, 11] simulated outcomes of two generators' K candidates on the same N
    objects (K may differ).  For each measure (``trials_mean``, ``grasp_mean``, ``trials_own``,
    ``grasp_own``, as in ``neighbourhood_stats``) the per-object difference is averaged; returned
    per measure: before, after, diff, ci_low / ci_high (95% percentile bootstrap of the mean
    difference, objects resampled ``n_boot`` times), better / worse (objects that moved).
    """
    a, b = np.asarray(after, np.float64), np.asarray(before, np.float64)
    if a.ndim != 3 or b.ndim != 3 or a.shape[0] != b.shape[0] or a.shape[2] != b.shape[2]:
        raise ValueError(f"after {a.shape} and before {b.shape}: expected [N, K, 11] outcomes of "
                         "the same N objects")
    per_object = {
        "trials_mean": lambda s: s.sum(-1).mean(1), "grasp_mean": lambda s: s[..., 0].mean(1),
        "trials_own": lambda s: s[:, 0].sum(-1), "grasp_own": lambda s: s[:, 0, 0],
    }
    rng = np.random.default_rng(seed)
    resample = rng.integers(0, a.shape[0], (n_boot, a.shape[0]))
    out = {}
    for name, f in per_object.items():
        d = f(a) - f(b)
        boot = d[resample].mean(1)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        out[name] = {"before": float(f(b).mean()), "after": float(f(a).mean()),
                     "diff": float(d.mean()), "ci_low": float(lo), "ci_high": float(hi),
                     "better": int((d > 0).sum()), "worse": int((d < 0).sum())}
    return out
