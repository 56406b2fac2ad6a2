"""Actor and twin-critic MLPs (flax.linen), spec row A7: 256-256 ReLU, tanh actor, and
their input layer, the running observation normalisation.

The two critics share one module definition; their parameters are stacked on a
leading axis of size 2 and evaluated with ``vmap``, so both critics run as one
fused computation.  Both networks read raw observations through :func:`normalize` (the
only place it is applied): the buffer keeps raw observations and minibatches are
normalised with the current statistics when used, as Brax's trainers do.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

STD_MIN = 1e-3  # floor on the std (features that barely move are not blown up)
CLIP = 10.0  # normalised values are clipped to ±CLIP


@struct.dataclass
class ObsStats:
    """Running statistics of every observation collected (Chan et al.'s parallel update)."""

    count: jax.Array  # () observations seen
    mean: jax.Array  # (n_obs,)
    m2: jax.Array  # (n_obs,) sum of squared deviations from the mean


def init_obs_stats(obs_size: int) -> ObsStats:
    return ObsStats(count=jnp.zeros(()), mean=jnp.zeros(obs_size), m2=jnp.zeros(obs_size))


def update_obs_stats(s: ObsStats, x: jax.Array) -> ObsStats:
    """Merge a batch ``x`` (n, n_obs) into the statistics."""
    n = x.shape[0]
    b_mean = jnp.mean(x, axis=0)
    b_m2 = jnp.sum((x - b_mean) ** 2, axis=0)
    count = s.count + n
    delta = b_mean - s.mean
    mean = s.mean + delta * (n / count)
    m2 = s.m2 + b_m2 + delta**2 * (s.count * n / count)
    return ObsStats(count=count, mean=mean, m2=m2)


def obs_std(s: ObsStats) -> jax.Array:
    return jnp.maximum(jnp.sqrt(s.m2 / jnp.maximum(s.count, 1.0)), STD_MIN)


def normalize(s: ObsStats | None, x: jax.Array) -> jax.Array:
    """Normalised observations (..., n_obs); ``s=None`` (a run without normalisation) leaves
    ``x`` unchanged."""
    if s is None:
        return x
    return jnp.clip((x - s.mean) / obs_std(s), -CLIP, CLIP)


class MLP(nn.Module):
    """Dense ReLU layers, then a linear output (tanh-squashed if ``squash``).  With
    ``in_size`` it reads only the first ``in_size`` inputs (an actor that does not see the
    critics' privileged observation)."""

    hidden: Sequence[int]
    out: int
    squash: bool = False
    in_size: int | None = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        if self.in_size is not None:
            x = x[..., : self.in_size]
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        x = nn.Dense(self.out)(x)
        return jnp.tanh(x) if self.squash else x


class ResidualMLP(nn.Module):
    """A critic made for resolution (SimBa, Lee et al. 2024): a Dense embedding of width
    w = ``hidden[0]``, one pre-LayerNorm residual block (Dense 4w, ReLU, Dense w) per entry of
    ``hidden``, a final LayerNorm and a linear output."""

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        w = self.hidden[0]
        x = nn.Dense(w)(x)
        for _ in self.hidden:
            x = x + nn.Dense(w)(nn.relu(nn.Dense(4 * w)(nn.LayerNorm()(x))))
        return nn.Dense(self.out)(nn.LayerNorm()(x))


class Networks(NamedTuple):
    actor: MLP  # obs (..., n_obs) -> action (..., n_act) in [-1, 1]
    critic: nn.Module  # [obs, action] (..., n_obs + n_act) -> Q (..., 1): MLP or ResidualMLP


CRITIC_ARCHS = ("mlp", "residual")


def make_networks(action_size: int, hidden: Sequence[int] = (256, 256), critic_arch: str = "mlp",
                  actor_obs_size: int | None = None) -> Networks:  # fmt: skip
    """The actor (reading the first ``actor_obs_size`` observation entries, or all) and the
    critic architecture ``critic_arch`` (one of ``CRITIC_ARCHS``)."""
    critic = ResidualMLP(tuple(hidden), 1) if critic_arch == "residual" else MLP(tuple(hidden), 1)
    actor = MLP(tuple(hidden), action_size, squash=True, in_size=actor_obs_size)
    return Networks(actor=actor, critic=critic)


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


def policy(nets: Networks, actor_params, stats: ObsStats | None, obs: jax.Array) -> jax.Array:
    """The deterministic policy π(obs) for raw observations (..., n_obs)."""
    return nets.actor.apply(actor_params, normalize(stats, obs))


def twin_q(nets: Networks, critic_params, stats: ObsStats | None, obs: jax.Array,
           action: jax.Array) -> jax.Array:  # fmt: skip
    """Both critics' values, shape (2, ...), for raw obs (..., n_obs) and action (..., n_act)."""
    x = jnp.concatenate([normalize(stats, obs), action], -1)
    return jax.vmap(lambda p: nets.critic.apply(p, x)[..., 0])(critic_params)
