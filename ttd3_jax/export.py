"""``python -m ttd3_jax.export``: the command line of :mod:`ttd3_jax.cli.export`."""

import sys

from ttd3_jax.cli.export import main

if __name__ == "__main__":
    sys.exit(main())
