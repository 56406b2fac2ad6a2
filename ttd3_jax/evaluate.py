"""``python -m ttd3_jax.evaluate``: the command line of :mod:`ttd3_jax.cli.evaluate`."""

import sys

from ttd3_jax.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
