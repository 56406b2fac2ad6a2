"""T-TD3 / TD3: configuration, networks (and their observation normalisation), replay
buffer, σ schedules, losses, the two vector steps (:mod:`~ttd3_jax.td3.dpg`, the paper's;
:mod:`~ttd3_jax.td3.model_based`), and the trainer that picks one.

Layer 3: imports nothing else of the package: the trainer knows an env only as an
:class:`~ttd3_jax.td3.env_spec.EnvSpec` (built by :mod:`ttd3_jax.run.tasks`).
"""
