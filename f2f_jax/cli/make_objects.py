"""Turn an object source into an object set on disk: TSDF volumes, names and a fixed split.

    python experiments/make_objects.py --source builtin --n 100 --out runs/objects
    python experiments/make_objects.py --source pybullet --out runs/pybullet      # needs .[pybullet]
    python experiments/make_objects.py --source ~/meshes/ycb --n 50 --out runs/ycb --seed 1

Writes OUT/objects.npz (``tsdf`` float16 [N, 40, 40, 40], ``names``), OUT/split.json
(train/test by seed), OUT/source.json and, unless ``--preview 0``, OUT/objects.png (a grid of
the first shapes).  Meshes that cannot become a volume are skipped and listed.  Rerunning with
the same arguments reuses what is there.
"""

import argparse
import json
import logging
import sys
from pathlib import Path

from f2f_jax import config
from f2f_jax.data import load_or_make_objects, object_split
from f2f_jax.errors import F2FError


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", default="builtin", help="builtin | pybullet | a directory of mesh files")
    p.add_argument("--n", type=int, default=None,
                   help="number of objects (required for builtin; else a seeded subset, default all)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="builtin generator / subset / split seed")
    p.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    p.add_argument("--preview", type=int, default=24, help="shapes drawn to OUT/objects.png (0: none)")
    args = p.parse_args(argv)
    if args.source == "builtin" and args.n is None:
        p.error("--n is required for the builtin source")
    if args.n is not None and args.n <= 0:
        p.error("--n must be positive")
    cfg = config.get(args.config).geometry
    out = Path(args.out)

    skipped = _Collect()
    loggers = [logging.getLogger("f2f_jax.data.object_set"), logging.getLogger("f2f_jax.data.sources")]
    for lg in loggers:
        lg.addHandler(skipped)
    try:
        tsdfs, names = load_or_make_objects(args.source, args.n, args.seed, out, cfg)
    except (F2FError, FileNotFoundError, ImportError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        for lg in loggers:
            lg.removeHandler(skipped)
    for msg in skipped.messages:
        print(f"skipped: {msg}", file=sys.stderr)

    if args.preview > 0:
        from f2f_jax.render import render_volumes  # matplotlib only when drawing

        k = min(args.preview, len(names))
        render_volumes(out / "objects.png", tsdfs[:k], [n.split("/")[-1] for n in names[:k]], cfg=cfg)
    split = object_split(out)
    print(json.dumps({"out": str(out), "objects": len(names), "skipped": len(skipped.messages),
                      "train": len(split["train"]), "test": len(split["test"])}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
