"""The grasp-result store: an append-only directory of immutable, compressed HDF5 chunk files.

Each ``append`` writes one chunk to a temporary file and renames it into place, so a reader (or
a rerun after a kill) sees whole chunks or nothing.  Rows hold the three volumes of a triple as
float16 (enough for a TSDF in [-1, 1]), the 11 outcomes and a few labels.  ``keys`` are a caller's
names for the work a chunk holds ("obj0017"): ``done_keys`` lets a killed job skip what it
already stored, so a rerun continues where it stopped without duplicates.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

_CHUNK = re.compile(r"^chunk-(\d{6})\.h5$")
VOLUME_FIELDS = ("object", "left", "right")


@dataclass(frozen=True)
class Chunk:
    index: int
    path: Path
    rows: int
    keys: tuple[str, ...]


class GraspStore:
    """Append-only store of (object, left, right) -> outcome rows.

    root: a directory (created on first append).  Not safe for two concurrent writers; any
    number of readers.
    """

    def __init__(self, root):
        self.root = Path(root)
        self._cache: list[Chunk] | None = None

    # -- reading -------------------------------------------------------------------------
    def chunks(self) -> list[Chunk]:
        """Complete chunks in append order (temporary files from a killed write are ignored)."""
        if not self.root.is_dir():
            return []
        names = sorted(p.name for p in self.root.iterdir() if _CHUNK.match(p.name))
        known = {c.path.name: c for c in (self._cache or [])}
        out = []
        for name in names:
            if name in known:
                out.append(known[name])
                continue
            path = self.root / name
            with h5py.File(path, "r") as f:
                keys = tuple(k.decode() for k in f["key"][()]) if "key" in f else ()
                out.append(Chunk(int(_CHUNK.match(name).group(1)), path, int(f["outcome"].shape[0]), keys))
        self._cache = out
        return out

    def __len__(self) -> int:
        return sum(c.rows for c in self.chunks())

    def done_keys(self) -> set[str]:
        return {k for c in self.chunks() for k in c.keys}

    def read(self, fields=("object", "left", "right", "outcome", "kind"), *, start: int = 0,
             stop: int | None = None) -> dict[str, np.ndarray]:
        """Rows [start, stop) of the store as arrays (volumes as float32)."""
        stop = len(self) if stop is None else stop
        parts: dict[str, list] = {f: [] for f in fields}
        offset = 0
        for c in self.chunks():
            lo, hi = max(start - offset, 0), min(stop - offset, c.rows)
            if lo < hi:
                with h5py.File(c.path, "r") as f:
                    for name in fields:
                        data = f[name][lo:hi]
                        if name in VOLUME_FIELDS:
                            data = data.astype(np.float32)
                        elif data.dtype.kind in "SO":
                            data = np.array([d.decode() if isinstance(d, bytes) else d for d in data])
                        parts[name].append(data)
            offset += c.rows
        return {
            name: (np.concatenate(v) if v else np.zeros((0,), np.float32))
            for name, v in parts.items()
        }

    # -- writing -------------------------------------------------------------------------
    def append(self, objects, lefts, rights, outcomes, *, kind, names=None, keys=(),
               cycle: int = -1) -> Chunk:
        """Write one chunk atomically.

        objects, lefts, rights: [N, R, R, R] volumes; outcomes: [N, 11] of 0/1;
        kind: a label per row or one for all ("imprint", "wsg50", "cut", "generated");
        names: object name per row; keys: names of the work this chunk completes (``done_keys``).
        """
        vols = [np.asarray(v) for v in (objects, lefts, rights)]
        outcomes = np.asarray(outcomes)
        n = outcomes.shape[0]
        if outcomes.ndim != 2 or any(v.shape[0] != n or v.ndim != 4 for v in vols):
            raise ValueError(f"append: volumes {[v.shape for v in vols]} and outcomes {outcomes.shape} "
                             "must be [N, R, R, R] x3 and [N, T]")
        kinds = [kind] * n if isinstance(kind, str) else list(kind)
        names = [""] * n if names is None else list(names)
        if len(kinds) != n or len(names) != n:
            raise ValueError("append: kind and names need one entry per row")
        self.root.mkdir(parents=True, exist_ok=True)
        chunks = self.chunks()
        index = chunks[-1].index + 1 if chunks else 0
        path = self.root / f"chunk-{index:06d}.h5"
        tmp = self.root / f".chunk-{index:06d}.h5.{os.getpid()}.tmp"
        r = vols[0].shape[1]
        with h5py.File(tmp, "w") as f:
            for name, v in zip(VOLUME_FIELDS, vols):
                f.create_dataset(name, data=v.astype(np.float16), chunks=(1, r, r, r),
                                 compression="gzip", compression_opts=4, shuffle=True)
            f.create_dataset("outcome", data=outcomes.astype(np.uint8))
            f.create_dataset("kind", data=np.array(kinds, dtype="S"))
            f.create_dataset("name", data=np.array(names, dtype="S"))
            f.create_dataset("cycle", data=np.full(n, cycle, np.int32))
            f.create_dataset("key", data=np.array(list(keys), dtype="S"))
            f.flush()
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        self._cache = None
        return self.chunks()[-1]

    def clean_temporary(self) -> int:
        """Delete leftovers of killed writes; returns how many."""
        if not self.root.is_dir():
            return 0
        stale = [p for p in self.root.iterdir() if p.name.startswith(".chunk-") and p.name.endswith(".tmp")]
        for p in stale:
            p.unlink(missing_ok=True)
        return len(stale)
