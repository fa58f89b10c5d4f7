"""An object set on disk: TSDF volumes and a fixed split: ``f2f_jax.cli.make_objects`` (``--help`` lists the flags)."""

import sys

from f2f_jax.cli.make_objects import main

if __name__ == "__main__":
    sys.exit(main())
