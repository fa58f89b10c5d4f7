"""The pretraining grasp dataset of an object set: ``f2f_jax.cli.make_dataset`` (``--help`` lists the flags)."""

import sys

from f2f_jax.cli.make_dataset import main

if __name__ == "__main__":
    sys.exit(main())
