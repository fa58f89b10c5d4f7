"""The rows an evaluation of a run scores, and the objects it scores them on: what
``experiments/evaluate.py`` (the paper's tables) and the studies beside it (``research/``) share.

    cfg = run_config(run_dir) or config.default()
    objects, names, what = evaluation_objects(run_dir, cfg, fresh=48, seed=7)
    rows = Rows()
    baseline_rows(rows, cfg)                                   # WSG50, Flat pads, Imprint
    nets, why = load_nets(run_dir)
    row = model_rows(rows, nets, seed=0, randemb=(4, 200), design_search=16)

``rows.designers`` are the designers of Table 1 by name, ``rows.table2`` the names Table 2 has,
``rows.recipes`` what makes each row's fingers (with the objects and config it names the row's
saved steps, ``steps.StepStore``).
"""

from __future__ import annotations

import collections
import functools
import json
from pathlib import Path

import numpy as np

from f2f_jax.data import builtin_objects, held_out_objects
from f2f_jax.errors import F2FError
from f2f_jax.geometry import mesh_to_tsdf
from f2f_jax.tables import designers as D
from f2f_jax.tables.paper import OBJECTIVE_ROWS
from f2f_jax.tables.seeds import FRESH_PREFIX, fresh_source


def _quiet(_msg: str) -> None:
    pass


def run_config(run_dir: Path):
    """The Config recorded in a run's run.json, or None."""
    from f2f_jax.train.checkpoint import config_from_dict

    path = Path(run_dir) / "run.json"
    if not path.exists():
        return None
    return config_from_dict(json.loads(path.read_text())["config"])


def load_nets(run_dir: Path):
    """(TrainedNets of the directory's newest checkpoint, None) or (None, why not)."""
    from f2f_jax.train.checkpoint import load_trained_nets

    try:
        return load_trained_nets(Path(run_dir)), None
    except (F2FError, FileNotFoundError) as exc:
        return None, str(exc)


def nets_recipe(nets) -> str:
    """What a checkpoint's designs depend on: its nets' sizes and every parameter."""
    from f2f_jax.tables.steps import tree_digest

    return f"{nets.config.net!r} {tree_digest({'g': nets.generator, 'f': nets.fitness})}"


def builtin_tsdfs(n: int, seed: int, cfg, progress: bool = True):
    """``n`` built-in objects of ``seed`` as volumes [n, R, R, R] and their names."""
    from tqdm.auto import tqdm

    meshes = builtin_objects(n, seed=seed)
    tsdfs = [mesh_to_tsdf(m, cfg.geometry)
             for m in tqdm(meshes, desc="objects -> TSDF", unit="obj", disable=not progress)]
    return np.stack(tsdfs), [m.metadata.get("name", f"object{i}") for i, m in enumerate(meshes)]


def evaluation_objects(run_dir: Path | None, cfg, *, objects: int | None = None,
                       fresh: int | None = None, seed: int = 0, progress: bool = True):
    """(object volumes [N, R, R, R], names, what they are): the run's held-out objects (the first
    ``objects`` of them) and ``fresh`` new built-in objects of ``seed`` (named ``fresh/...``), or
    without a run ``objects`` (default 12) built-in objects of ``seed``.  Raises ValueError with
    the message for the user."""
    if run_dir is None:
        tsdfs, names = builtin_tsdfs(objects or 12, seed, cfg, progress)
        return tsdfs, names, f"built-in objects (seed {seed})"
    source = Path(run_dir) / "objects" / "source.json"
    meta = json.loads(source.read_text()) if source.exists() else {}
    if fresh and meta.get("source") == "builtin" and meta.get("seed") == seed:
        raise ValueError(f"--fresh with --seed {seed}: the run made its built-in objects with "
                         "that seed, so they would not be new; pick another --seed")
    try:
        tsdfs, names = held_out_objects(run_dir, cfg.geometry)
    except FileNotFoundError as exc:
        raise ValueError(str(exc)) from None
    what = f"held-out objects of {run_dir}"
    if fresh:
        new, new_names = builtin_tsdfs(fresh, seed, cfg, progress)
        tsdfs = np.concatenate([tsdfs[:objects], new])
        names = list(names[:objects]) + [f"{FRESH_PREFIX}{n}" for n in new_names]
        what += f" + {fresh_source(fresh, seed)}"
    elif objects is not None:
        tsdfs, names = tsdfs[:objects], names[:objects]
    return tsdfs, names, what


def parse_extras(items) -> list[tuple[str, Path]]:
    """``--extra NAME=RUN_DIR`` items as (name, directory); raises ValueError with the message."""
    extras = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name.strip() or not path.strip():
            raise ValueError(f"--extra {item!r}: expected NAME=RUN_DIR")
        if not Path(path).expanduser().is_dir():
            raise ValueError(f"--extra {item!r}: no such directory {path}")
        extras.append((name.strip(), Path(path).expanduser()))
    return extras


class Rows:
    """The designers of Table 1, the rows of Table 2, the notes under the tables and what makes
    each row's fingers."""

    def __init__(self):
        self.designers, self.table2, self.notes = {}, [], []
        self.pool_origins = []  # FingerPair.origin of the design pool's picks, one per object
        self.pool_name, self.store = None, None  # the pool row; a StepStore, once made
        # {row: what makes its fingers}: with the objects and config, names its saved steps
        self.recipes: dict[str, str] = {}


def baseline_rows(rows: Rows, cfg, say=_quiet) -> None:
    """WSG50 (Schunk's WSG-FMF fingers; skipped with a note without the pybullet extra), Flat
    pads and Imprint; WSG50 and Imprint are in Table 2."""
    try:
        rows.designers["WSG50"] = D.wsg_fmf_designer(cfg)
        rows.recipes["WSG50"] = "WSG-FMF fingers"
        rows.table2.append("WSG50")
        rows.notes.append("WSG50: Schunk's standard WSG-FMF fingers (the mesh pybullet_data ships; "
                          "faces meet at the object's mid-plane at full closure, as every finger "
                          "here); Flat pads: ideal flat fingertips (ours, not in the paper)")
    except ImportError as exc:  # MissingExtraError: the mesh ships with pybullet
        say(f"WSG50 row (WSG-FMF fingers) skipped: {exc}")
        rows.notes.append(f"WSG50 (WSG-FMF fingers) not run: {exc}")
    rows.designers["Flat pads"] = D.wsg50_designer(cfg)
    rows.designers["Imprint"] = D.imprint_designer(cfg)
    rows.recipes.update({"Flat pads": "flat pads", "Imprint": "imprint"})
    rows.table2.append("Imprint")


def search_rows(rows: Rows, nets, recipe: str, k: int, *, backend: str = "mujoco",
                executor: str = "threads", quiet: bool = False) -> None:
    """'Fit2Form + search (K, verify)': ``f2f_jax.design`` on the generator's K candidates;
    'Design pool (K + imprints, verify)': the same with the imprints (design()'s default)."""
    from f2f_jax.designer import design

    search = functools.partial(design, params=nets, candidates=k, verify=True, backend=backend,
                               executor=executor, progress=False if quiet else None)
    name = f"Fit2Form + search ({k}, verify)"  # the generator's candidates only
    rows.designers[name] = D.pair_designer(functools.partial(search, imprint=False), batched=True,
                                           desc=name)
    rows.recipes[name] = f"search {k} without imprints, {recipe}"
    rows.table2.append(name)
    pool_name = f"Design pool ({k} + imprints, verify)"
    rows.recipes[pool_name] = f"search {k} with imprints, {recipe}"
    rows.pool_name = pool_name

    def pool(objs):
        pairs = search(objs, imprint=True)
        rows.pool_origins = [pair.origin for pair in pairs]
        if rows.store is not None:
            rows.store.save("origins", pool_name, origins=np.array(rows.pool_origins))
        return pairs

    rows.designers[pool_name] = D.pair_designer(pool, batched=True, desc=pool_name)
    rows.table2.append(pool_name)


def model_row_name(nets) -> str:
    """The Table 1 row of a checkpoint's generator: "Fit2Form", "Fit2Form GS", ... or "ImpGN"."""
    return OBJECTIVE_ROWS.get(nets.objectives, f"Fit2Form ({nets.objectives})")


def model_rows(rows: Rows, nets, *, seed: int = 0, randemb: tuple[int, int] | None = None,
               design_search: int | None = None, backend: str = "mujoco",
               executor: str = "threads", quiet: bool = False) -> str:
    """A checkpoint's rows: its generator (in Table 2 too), RandEmb+FN with ``randemb`` =
    (samples, steps) (its shape decoder and fitness net without the generator) and with
    ``design_search`` K the search rows.  Returns the generator's row name."""
    import jax

    row = model_row_name(nets)
    recipe = nets_recipe(nets)
    if randemb is not None:
        samples, steps = randemb
        rows.designers["RandEmb+FN"] = D.random_embedding_designer(
            nets, jax.random.key(seed), samples=samples, steps=steps)
        rows.recipes["RandEmb+FN"] = f"randemb {steps} steps {samples} samples seed {seed}, {recipe}"
    rows.designers[row] = D.nets_designer(nets)
    rows.recipes[row] = f"generator, {recipe}"
    rows.table2.append(row)
    if design_search:
        search_rows(rows, nets, recipe, design_search, backend=backend, executor=executor,
                    quiet=quiet)
    return row


def extra_rows(rows: Rows, extras, say=_quiet) -> dict:
    """Each --extra (name, run dir) checkpoint's generator as a Table 1 row; returns {name: nets}
    of those with a usable checkpoint."""
    loaded = {}
    for name, path in extras:
        nets, why = load_nets(path)
        if nets is None:
            say(f"--extra {name}: no usable checkpoint in {path} ({why}): row skipped")
            continue
        rows.designers[name] = D.nets_designer(nets)
        rows.recipes[name] = f"generator, {nets_recipe(nets)}"
        loaded[name] = nets
    return loaded


def pool_note(rows: Rows, say=_quiet) -> None:
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
        say(rows.notes[-1])
