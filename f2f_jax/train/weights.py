"""Trained weights as one portable file: what the package ships and what a run exports.

A weights file is an ``.npz`` of the generator's and the fitness net's variables, one array per
leaf under its path (``generator/params/decoder/Conv_0/kernel``), and a ``.json`` beside it with
the config that sized the nets and the provenance: the commit and command that trained them, the
seed, the objects and the run's held-out table.  Unlike an orbax checkpoint it needs nothing but
numpy to read, holds no optimiser state, and is a few MB.

``python experiments/cotrain.py --cycles 20 --export f2f_jax/weights/default`` trains the model
the package ships (``SHIPPED``) and writes it; ``load_weights()`` reads it back as
``TrainedNets``, checking its layout against the nets its config builds.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import subprocess
from pathlib import Path

import jax
import numpy as np

from f2f_jax.errors import CheckpointError
from f2f_jax.fileio import atomic_path
from f2f_jax.nets.inference import TrainedNets

# The model the package ships, and the command that rebuilds it (from the repository's root).
SHIPPED = Path(__file__).resolve().parent.parent / "weights" / "default"
REBUILD = "python experiments/cotrain.py --cycles 20 --export f2f_jax/weights/default"
FORMAT = 1  # bump when the file's layout (not the nets') changes
_SEP = "/"


def _paths(base) -> tuple[Path, Path]:
    base = Path(base)
    if base.suffix in (".npz", ".json"):
        base = base.with_suffix("")
    return base.with_suffix(".npz"), base.with_suffix(".json")


def flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    """Nested dicts of arrays (or of ``jax.ShapeDtypeStruct``) -> {"a/b/c": array}."""
    flat = {}
    for name, value in tree.items():
        if _SEP in str(name):
            raise ValueError(f"a variable's name holds {_SEP!r}: {name!r}")
        path = f"{prefix}{_SEP}{name}" if prefix else str(name)
        if isinstance(value, dict):
            flat.update(flatten(value, path))
        elif isinstance(value, jax.ShapeDtypeStruct):  # a layout (jax.eval_shape), not data
            flat[path] = value
        else:
            flat[path] = np.asarray(value)
    return flat


def unflatten(flat: dict[str, np.ndarray]) -> dict:
    """{"a/b/c": array} -> nested dicts (the inverse of ``flatten``)."""
    tree: dict = {}
    for path, value in flat.items():
        node = tree
        *parents, leaf = path.split(_SEP)
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def _commit() -> str | None:
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return out + ("+local changes" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def save_weights(nets: TrainedNets, base, provenance: dict | None = None) -> tuple[Path, Path]:
    """Write ``nets`` as ``base.npz`` and ``base.json`` (atomic writes); returns both paths.

    provenance: what trained them (command, seed, objects, held-out table, ...), stored in the
    JSON beside the config; the commit, the date and the file's digest are added here."""
    from f2f_jax.train.checkpoint import config_to_dict

    npz, meta_path = _paths(base)
    npz.parent.mkdir(parents=True, exist_ok=True)
    arrays = {**flatten(jax.device_get(nets.generator), "generator"),
              **flatten(jax.device_get(nets.fitness), "fitness")}
    with atomic_path(npz) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    meta = dict(format=FORMAT, config=config_to_dict(nets.config), objectives=nets.objectives,
                sha256=hashlib.sha256(npz.read_bytes()).hexdigest(), bytes=npz.stat().st_size,
                parameters=int(sum(a.size for a in arrays.values())),
                written=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                commit=_commit(), provenance=provenance or {}, rebuild=REBUILD)
    with atomic_path(meta_path) as tmp:
        Path(tmp).write_text(json.dumps(meta, indent=2) + "\n")
    return npz, meta_path


def weights_info(base=None) -> dict:
    """The JSON beside a weights file (default: the shipped one)."""
    _, meta_path = _paths(SHIPPED if base is None else base)
    if not meta_path.is_file():
        raise CheckpointError(f"no weights at {meta_path.with_suffix('')}: rebuild them with "
                              f"`{REBUILD}`")
    return json.loads(meta_path.read_text())


def load_weights(base=None) -> TrainedNets:
    """``TrainedNets`` from a weights file (default: the ones the package ships).

    Raises CheckpointError when the file is missing, damaged, or does not match the nets its
    config builds today (the nets' layout changed since it was written): the message names the
    command that rebuilds it."""
    from f2f_jax.train.checkpoint import config_from_dict
    from f2f_jax.train.state import init_fitness, init_generator

    npz, _ = _paths(SHIPPED if base is None else base)
    meta = weights_info(npz)
    rebuild = REBUILD if base is None else "python experiments/cotrain.py ... --export PATH"
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{npz}: weights file format {meta.get('format')!r}, this version "
                              f"reads {FORMAT}; rebuild them with `{rebuild}`")
    try:
        data = npz.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"{npz}: {exc}; rebuild them with `{rebuild}`") from None
    if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
        raise CheckpointError(f"{npz} does not match the digest in its JSON (damaged or replaced); "
                              f"rebuild it with `{rebuild}`")
    with np.load(io.BytesIO(data)) as z:  # the bytes whose digest was checked, read once
        flat = {name: z[name] for name in z.files}
    tree = unflatten(flat)
    cfg = config_from_dict(meta["config"])
    # the layout the code builds today, without computing it (shapes only)
    expect = {"generator": jax.eval_shape(lambda: init_generator(cfg, 0)),
              "fitness": jax.eval_shape(lambda: init_fitness(cfg, 1))}
    want = {k: (tuple(v.shape), np.dtype(v.dtype)) for k, v in flatten(expect).items()}
    got = {k: (tuple(v.shape), v.dtype) for k, v in flat.items()}
    if want != got:
        diff = sorted(set(want.items()) ^ set(got.items()))[:3]
        raise CheckpointError(f"{npz} was written for other nets than this version builds "
                              f"(first differences: {diff}); rebuild it with `{rebuild}`")
    return TrainedNets(config=cfg, generator=tree["generator"], fitness=tree["fitness"],
                       objectives=meta.get("objectives", "full"),
                       source=f"{npz} (shipped weights, commit {meta.get('commit')})"
                       if base is None else f"{npz} (weights, commit {meta.get('commit')})")


def export_run(run_dir, base, command: str | None = None) -> tuple[Path, Path]:
    """The newest checkpoint of a finished co-training run as a weights file, with the run's
    seed, objects and held-out table (``summary.json``) as provenance."""
    from f2f_jax.train.checkpoint import load_trained_nets

    run_dir = Path(run_dir)
    nets = load_trained_nets(run_dir)
    provenance: dict = dict(command=command, checkpoint=nets.source)
    for name in ("run.json", "summary.json"):
        path = run_dir / name
        if path.is_file():
            provenance[name.removesuffix(".json")] = json.loads(path.read_text())
    for name in ("source.json", "split.json"):  # which objects, and which were held out
        path = run_dir / "objects" / name
        if path.is_file():
            provenance[f"objects_{name.removesuffix('.json')}"] = json.loads(path.read_text())
    return save_weights(nets, base, provenance)
