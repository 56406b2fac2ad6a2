"""What the trainer knows about an env: :class:`EnvSpec`.  The trainer imports nothing of the
quadrotor or of Brax; :mod:`ttd3_jax.run.tasks` builds the specs of the tracking env and the
Brax/MJX tasks.

An :class:`EnvSpec` is a single-env object with the Brax ``reset`` / ``step`` API whose
``info`` carries ``"truncation"`` and ``"terminated"`` (a true terminal state, apart from the
time limit), its sizes, the nominal episode length (T-TD3's time unit) and
``evaluate(policy)``, which scores a deterministic ``policy(obs)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple


class EnvSpec(NamedTuple):
    env: object  # single-env object with Brax reset/step
    obs_size: int
    action_size: int
    episode_length: int  # transitions per nominal episode (L_nom)
    evaluate: Callable[[Callable], dict]  # policy (obs -> action) -> metrics (pure; jit it)
    differentiable: bool  # whether gradients flow through env.step (model_horizon > 0)
    actor_obs_size: int  # the leading observation entries the actor reads (the critics read all)
