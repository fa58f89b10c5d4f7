"""Rebuild the object pieces that ship with the package for the builtin objects.

    python -m f2f_jax.cli.bundle_pieces                 # builtin objects 0-639 of seed 0
    python -m f2f_jax.cli.bundle_pieces --n 16 --raw-n 4 --out /tmp/pieces.npz

The builtin objects a run, the benchmarks and the tests start from are the same every time, and
coacd spends 5-30 s of a core on each.  Their pieces are made once here (through the disk cache
and its worker processes, ``object_hulls_many``) and written to
``f2f_jax/geometry/builtin_pieces.npz`` under their cache keys, for both forms a volume of them
takes: rounded to float16 as an object set stores it (``load_or_make_objects``: the default run's
64 objects, the tiny run's first 16; ``load_or_make_builtin_range``: the teacher config's 236
more, 64-299, or up to 576 more with ``train.teacher_objects``, 64-639), and, for the first
``--raw-n`` (default 64), as ``mesh_to_tsdf`` makes it (the tests, and the 64 builtin objects of
the agreement, fidelity and throughput benchmarks).  ``object_hulls`` reads them when its cache
has no entry.  Rebuild after anything that changes the volumes or the cache keys (the families, the
TSDF code, ``CoacdSettings``, ``_CACHE_VERSION``); ``tests/test_bundled_pieces.py`` says when.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from f2f_jax.config import GeometryConfig
from f2f_jax.data import builtin_objects
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import mesh_to_tsdf
from f2f_jax.geometry.coacd_pieces import BUNDLE_PATH, CoacdSettings, cache_key
from f2f_jax.geometry.hull_pool import object_hulls_many
from f2f_jax.geometry.tsdf import check_tsdf


def builtin_volumes(n: int, seed: int, g: GeometryConfig, raw_n: int | None = None) -> list[np.ndarray]:
    """The volumes whose pieces are shipped: each of the first n builtin objects as an object set
    stores it (float16), and the first raw_n (default all n) also as ``mesh_to_tsdf`` makes it;
    distinct ones once."""
    raw_n = n if raw_n is None else raw_n
    out, seen = [], set()
    for i, mesh in enumerate(builtin_objects(n, seed=seed)):
        raw = mesh_to_tsdf(mesh, g)
        stored = raw.astype(np.float16).astype(np.float32)  # as load_or_make_objects returns it
        for vol in (raw, stored) if i < raw_n else (stored,):
            key = vol.tobytes()
            if key not in seen:
                seen.add(key)
                out.append(vol)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=640, help="first builtin objects (default 640)")
    p.add_argument("--raw-n", type=int, default=64,
                   help="of those, the first ones also as mesh_to_tsdf makes them (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=BUNDLE_PATH)
    p.add_argument("--workers", type=int, default=None, help="coacd processes (default: one per core)")
    args = p.parse_args(argv)
    if args.n < 1 or args.raw_n < 0:
        p.error("--n must be >= 1, --raw-n >= 0")
    g = GeometryConfig()
    start = time.perf_counter()
    volumes = builtin_volumes(args.n, args.seed, g, args.raw_n)
    made = object_hulls_many(volumes, g, workers=args.workers, progress=True)
    failed = [i for i, h in enumerate(made) if isinstance(h, str)]
    if failed:
        print(f"no pieces for volumes {failed}: {[made[i] for i in failed]}", file=sys.stderr)
        return 1
    k, v = g.object_hulls, g.hull_vertices
    keys = [cache_key(check_tsdf(vol, "object", g), g, k, v, CoacdSettings()) for vol in volumes]
    with atomic_path(args.out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, keys=np.array(keys), vertices=np.stack([h.vertices for h in made]),
                                counts=np.stack([h.counts for h in made]))
    print(f"{len(keys)} volumes of {args.n} builtin objects (seed {args.seed}; {args.raw_n} also "
          f"unrounded) -> {args.out} "
          f"({args.out.stat().st_size / 1024:.0f} KiB) in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
