"""``python -m f2f_jax.nets --summary [--config tiny|default]``: parameter counts and shapes."""

from __future__ import annotations

import argparse

from f2f_jax import config
from f2f_jax.nets import summarize


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m f2f_jax.nets", description=__doc__)
    parser.add_argument("--summary", action="store_true",
                        help="print parameter counts per module and output shapes")
    parser.add_argument("--config", default="default", choices=sorted(config.CONFIGS))
    parser.add_argument("--batch", type=int, default=2, help="batch size of the shapes shown")
    args = parser.parse_args(argv)
    if not args.summary:
        parser.print_help()
        return 0
    cfg = config.get(args.config).net
    rows = summarize(cfg, batch=args.batch)
    print(f"config {args.config}: latent {cfg.latent_dim}, batch {args.batch}")
    print(f"{'module':<28}{'params':>14}  output shapes")
    total = 0
    for row in rows:
        outputs = "" if row["outputs"] is None else str(row["outputs"])
        print(f"{row['name']:<28}{row['params']:>14,}  {outputs}")
        if "/" not in row["name"] and row["name"] not in ("ShapeAutoEncoder", "FingerGenerator",
                                                                "HeightGenerator"):
            total += row["params"]
    # the distinct networks: encoder + decoder + embedding + fitness (AE and FG share them); the
    # height-map generator replaces G with net.generator = "heights"
    print(f"{'total (E + D + G + F)':<28}{total:>14,}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
