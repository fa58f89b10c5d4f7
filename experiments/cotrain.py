"""Fit2Form end to end: objects, dataset, pretraining, co-training: ``f2f_jax.cli.cotrain`` (``--help`` lists the flags)."""

import sys

from f2f_jax.cli.cotrain import main

if __name__ == "__main__":
    sys.exit(main())
