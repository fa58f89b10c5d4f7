"""Fixed train/test splits of object names, by seed, kept on disk as JSON.

A name's side is decided by ranking ``sha256(seed, name)``: the split depends only on the set of
names and the seed (not on their order, the Python hash seed or the numpy version), and adding a
few objects to a set moves at most a few old names across.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from f2f_jax.config import held_out_count
from f2f_jax.fileio import atomic_path


def _rank_key(name: str, seed: int) -> bytes:
    return hashlib.sha256(f"{seed}\x00{name}".encode()).digest()


def make_split(names, test_fraction: float = 0.2, seed: int = 0) -> dict[str, list[str]]:
    """Disjoint train/test lists of ``names``, each sorted.

    names: object names (unique; order does not matter).  test_fraction in (0, 1): the test
    share, rounded, with at least one name on each side when there are two or more names.
    Returns {"train": [...], "test": [...]}.  Raises ValueError for duplicate names or a
    fraction outside (0, 1).
    """
    names = [str(n) for n in names]
    if len(set(names)) != len(names):
        dupes = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"make_split: duplicate names {dupes[:5]}{' ...' if len(dupes) > 5 else ''}")
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"make_split: test_fraction must be in (0, 1), got {test_fraction}")
    n = len(names)
    n_test = held_out_count(n, test_fraction)
    ranked = sorted(names, key=lambda s: _rank_key(s, seed))
    return {"train": sorted(ranked[n_test:]), "test": sorted(ranked[:n_test])}


def _check_split(split, source: str) -> dict[str, list[str]]:
    if not isinstance(split, dict) or not {"train", "test"} <= set(split):
        raise ValueError(f"{source}: a split needs 'train' and 'test' lists")
    out = {}
    for side in ("train", "test"):
        values = split[side]
        if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
            raise ValueError(f"{source}: '{side}' must be a list of names")
        out[side] = list(values)
    both = set(out["train"]) & set(out["test"])
    if both:
        raise ValueError(f"{source}: {len(both)} names are in both train and test, e.g. {sorted(both)[:3]}")
    return out


def save_split(path, split: dict) -> Path:
    """Write a split as JSON atomically (temporary file in the same folder, then a rename)."""
    path = Path(path)
    split = _check_split(split, f"save_split({path})")
    with atomic_path(path) as tmp:
        with open(tmp, "x") as f:
            json.dump(split, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
    return path


def load_split(path) -> dict[str, list[str]]:
    """Read a split written by ``save_split``; ValueError naming the file if it is malformed."""
    path = Path(path)
    try:
        split = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    return _check_split(split, str(path))
