"""ttd3_jax: T-TD3 / TD3 for quadrotor trajectory tracking, end to end in JAX.

Layers, each importing only those above it in this list (docs/architecture.md):

1. :mod:`ttd3_jax.sim`: dynamics, reference tracks, the tracking env and its config;
2. :mod:`ttd3_jax.control`: the controller protocol, closed loop, metrics, baselines;
3. :mod:`ttd3_jax.td3`: the trainer (config, networks, buffer, noise, losses, steps);
4. the application: :mod:`~ttd3_jax.spec` (the run spec and presets), :mod:`~ttd3_jax.runs`,
   :mod:`~ttd3_jax.checkpoint`, :mod:`~ttd3_jax.runner`, :mod:`~ttd3_jax.sharding`,
   :mod:`~ttd3_jax.report`, :mod:`~ttd3_jax.cache`, :mod:`~ttd3_jax.brax_compat` (Brax's trainers and
   registry), :mod:`~ttd3_jax.adapters` (Gymnasium and gymnax);
5. the command lines :mod:`ttd3_jax.train` and :mod:`ttd3_jax.evaluate`.
"""
