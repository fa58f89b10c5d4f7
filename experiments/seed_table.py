"""Tables 1 and 2 over several runs (seeds), mean ± sd: ``f2f_jax.cli.seed_table`` (``--help`` lists the flags)."""

import sys

from f2f_jax.cli.seed_table import main

if __name__ == "__main__":
    sys.exit(main())
