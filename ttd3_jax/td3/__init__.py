"""T-TD3 / TD3: configuration, networks, replay buffer, noise schedules, losses, trainer.

Layer 3: imports :mod:`ttd3_jax.sim` and :mod:`ttd3_jax.control` (for evaluation).
"""
