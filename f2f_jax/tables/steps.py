"""What a long evaluation has finished survives a kill: ``StepStore``.

``experiments/evaluate.py`` designs every row, then simulates Tables 1 and 2 row by row (and
condition by condition); with a design search or a paper-size object set that is hours.  Each
finished step (a row's designs; a row's outcomes in Table 1 or under one Table 2 condition) is
saved under ``OUT/.steps/`` as soon as it ends, named by a hash of everything it depends on:

- the objects (their volumes, after any that could not be decomposed were dropped), the Config
  (simulator preset, physics, sizes), the backend and the seed (``common``);
- the row's recipe: its name and what makes its fingers (a checkpoint's parameters, hashed; the
  search width; RandEmb's steps), given per row by the caller;
- the code of ``f2f_jax`` itself (every module's source), so a changed simulator or designer
  never reuses an old outcome.

The same command run again (or one that adds rows or Table 2) takes up every step whose hash
matches and does only the rest; a step whose inputs changed is simply not found.  Designs are
large (two float32 volumes per object) and are deleted once the caller has written its results
(``finish``); outcomes are a few bytes per object and stay, so adding a row later re-simulates
only that row.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Mapping

import numpy as np

from f2f_jax.fileio import atomic_path

DIRECTORY = ".steps"
_DESIGN = "design"


def code_digest() -> str:
    """sha256 of the source of every module of the installed ``f2f_jax`` package."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def tree_digest(tree) -> str:
    """sha256 of a pytree of arrays (a checkpoint's variables): leaves' dtypes, shapes and bytes
    in the tree's order."""
    import jax

    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        arr = np.asarray(leaf)
        h.update(jax.tree_util.keystr(path).encode())
        h.update(f"{arr.dtype}{arr.shape}".encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


class StepStore:
    """Finished steps of one evaluation, on disk.

    directory: where ``.steps/`` lives (the evaluation's output directory); common: everything
    all rows share (see the module docstring; ``common_digest`` makes it); recipes: {row name:
    what makes that row's fingers}, a string that changes whenever the row's designs would.
    """

    def __init__(self, directory, common: str, recipes: Mapping[str, str]):
        self.root = Path(directory) / DIRECTORY
        self.common = common
        self.recipes = dict(recipes)
        self.loaded = 0  # steps taken up from an earlier call

    def _path(self, step: str, row: str) -> Path:
        if row not in self.recipes:
            raise KeyError(f"no recipe for row {row!r}")
        h = hashlib.sha256(json.dumps([self.common, row, self.recipes[row], step]).encode())
        kind = _DESIGN if step == _DESIGN else "outcome"
        return self.root / f"{kind}-{h.hexdigest()[:32]}.npz"

    def load(self, step: str, row: str) -> dict[str, np.ndarray] | None:
        """The arrays saved for ``step`` of ``row``, or None (never saved, or an unreadable file
        from a kill mid-write: then it is done again)."""
        path = self._path(step, row)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as f:
                out = {k: f[k] for k in f.files}
        except (OSError, ValueError, EOFError):
            return None
        self.loaded += 1
        return out

    def save(self, step: str, row: str, **arrays) -> None:
        """Keep ``arrays`` for ``step`` of ``row`` (written whole or not at all)."""
        path = self._path(step, row)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **{k: np.asarray(v) for k, v in arrays.items()})

    def load_design(self, row: str):
        return self.load(_DESIGN, row)

    def save_design(self, row: str, **arrays) -> None:
        self.save(_DESIGN, row, **arrays)

    def finish(self) -> None:
        """Delete the saved designs (large); the outcomes stay for later calls."""
        if self.root.is_dir():
            for path in self.root.glob(f"{_DESIGN}-*.npz"):
                path.unlink(missing_ok=True)


def common_digest(objects: np.ndarray, cfg, **settings) -> str:
    """The part of every step's name that all rows share: the object volumes, the Config, the
    keyword settings (backend, seed, ...) and ``code_digest()``."""
    h = hashlib.sha256()
    arr = np.ascontiguousarray(np.asarray(objects, np.float32))
    h.update(f"{arr.shape}".encode())
    h.update(arr.tobytes())
    h.update(repr(cfg).encode())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    h.update(code_digest().encode())
    return h.hexdigest()


class StoredDesigner:
    """A designer whose designs are kept in a ``StepStore`` as soon as they are made, and taken
    from it on a later call instead of designing again (a design search simulates for minutes).

    Returns a ``designers.Design`` (``make_designs`` keeps its ``seconds``: the time the designs
    first took, not the time of reading them back).  New designs go through ``make_designs``
    (timed and checked) before they are saved.  say: called with a line before designing.
    """

    def __init__(self, store: StepStore, name: str, designer, say=None):
        self.store, self.name, self.designer, self.say = store, name, designer, say

    def __call__(self, objects):
        from f2f_jax.tables.designers import Design, make_designs

        got = self.store.load_design(self.name)
        if got is not None and got["lefts"].shape == np.shape(objects):
            return Design(got["lefts"], got["rights"], float(got["seconds"]))
        if self.say is not None:
            self.say(f"designing: {self.name}")
        d = make_designs({self.name: self.designer}, objects, progress=False)[self.name]
        self.store.save_design(self.name, lefts=d.lefts, rights=d.rights, seconds=d.seconds)
        return d
