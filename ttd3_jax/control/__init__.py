"""Controllers and their closed-loop evaluation: the protocol, metrics, baselines, robustness.

Layer 2: imports :mod:`ttd3_jax.sim` only.
"""
