"""Atomic file writes: a reader (or a rerun after a kill) sees the old file or the new one whole."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path`` (atomic on
    one file system), on any exception it is removed.  Not mkstemp: its 0600 mode would stick to
    the final file.  The temporary name keeps the suffix, for writers that dispatch on it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
