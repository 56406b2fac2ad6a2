"""``python -m ttd3_jax.train``: the command line of :mod:`ttd3_jax.cli.train`."""

from ttd3_jax.cli.train import exit_with, main

if __name__ == "__main__":
    exit_with(main())
