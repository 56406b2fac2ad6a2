"""ttd3_jax: T-TD3 / TD3 for quadrotor trajectory tracking, end to end in JAX.

Layers, each importing only those above it in this list (docs/architecture.md):

0. :mod:`ttd3_jax.checks`: the checks of user input; :mod:`ttd3_jax.compile_flags`: the XLA
   flags every path compiles with (set on import);
1. :mod:`ttd3_jax.sim`: dynamics, reference tracks, the tracking env and its config;
2. :mod:`ttd3_jax.control`: the controller protocol, closed loop, metrics, baselines;
3. :mod:`ttd3_jax.td3`: the trainer (TD3's core, the two actor updates, networks, buffer, σ);
4. :mod:`ttd3_jax.run`: a training run (spec, run directory, loop, checkpoint, cache, memory,
   sharding, report);
5. :mod:`ttd3_jax.interop`: the exported policy, Gymnasium/gymnax front ends, Brax's trainers;
6. :mod:`ttd3_jax.cli`: the command lines, run as ``python -m ttd3_jax.train|evaluate|export``.
"""

from ttd3_jax import compile_flags as _compile_flags

_compile_flags.apply()  # before JAX starts a backend: the XLA flags every path compiles with
