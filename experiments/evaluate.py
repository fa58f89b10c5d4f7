"""The paper's Tables 1 and 2 for a co-training run: ``f2f_jax.cli.evaluate`` (``--help`` lists the flags)."""

import sys

from f2f_jax.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
