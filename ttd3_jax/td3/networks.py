"""Actor and twin-critic MLPs (flax.linen), spec row A7: 256-256 ReLU, tanh actor.

The two critics share one module definition; their parameters are stacked on a
leading axis of size 2 and evaluated with ``vmap``, so both critics run as one
fused computation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """Dense ReLU layers, then a linear output (tanh-squashed if ``squash``)."""

    hidden: Sequence[int]
    out: int
    squash: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        x = nn.Dense(self.out)(x)
        return jnp.tanh(x) if self.squash else x


class Networks(NamedTuple):
    actor: MLP  # obs (..., n_obs) -> action (..., n_act) in [-1, 1]
    critic: MLP  # [obs, action] (..., n_obs + n_act) -> Q (..., 1)


def make_networks(action_size: int, hidden: Sequence[int] = (256, 256)) -> Networks:
    return Networks(actor=MLP(tuple(hidden), action_size, squash=True), critic=MLP(tuple(hidden), 1))


def init_params(nets: Networks, key: jax.Array, obs_size: int, action_size: int):
    """Actor params and twin-critic params (leading axis 2)."""
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, obs_size))
    act = jnp.zeros((1, action_size))
    actor = nets.actor.init(k_actor, obs)
    critic = jax.vmap(lambda k: nets.critic.init(k, jnp.concatenate([obs, act], -1)))(
        jax.random.split(k_critic, 2)
    )
    return actor, critic


def twin_q(nets: Networks, critic_params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Both critics' values, shape (2, ...) for obs (..., n_obs) and action (..., n_act)."""
    x = jnp.concatenate([obs, action], -1)
    return jax.vmap(lambda p: nets.critic.apply(p, x)[..., 0])(critic_params)
