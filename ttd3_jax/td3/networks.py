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


class AdvantageCritic(nn.Module):
    """Deep advantage updating's critic (Tallec, Blier, Ollivier 2019): a value net V(obs) and
    an advantage net Ā(obs, action), each a ``body`` of the critic architecture; Q is put
    together from them by :func:`twin_q_adv`."""

    body: nn.Module  # the architecture of both nets (one output)

    def setup(self):
        self.v_net, self.a_net = self.body.clone(), self.body.clone()

    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        return self.value(obs), self.advantage(obs, action)

    def value(self, obs: jax.Array) -> jax.Array:
        return self.v_net(obs)[..., 0]

    def advantage(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Ā(obs, action), not yet normalised (:func:`twin_q_adv` subtracts Ā(obs, π(obs)))."""
        return self.a_net(jnp.concatenate([obs, action], -1))[..., 0]


class Networks(NamedTuple):
    actor: MLP  # obs (..., n_obs) -> action (..., n_act) in [-1, 1]
    # [obs, action] (..., n_obs + n_act) -> Q (..., 1): MLP or ResidualMLP; AdvantageCritic if dt > 0
    critic: nn.Module
    dt: float = 0.0  # > 0: the control step δ (s) of deep advantage updating, Q = V + δ A


CRITIC_ARCHS = ("mlp", "residual")


def make_networks(action_size: int, hidden: Sequence[int] = (256, 256), critic_arch: str = "mlp",
                  actor_obs_size: int | None = None, advantage_dt: float = 0.0) -> Networks:  # fmt: skip
    """The actor (reading the first ``actor_obs_size`` observation entries, or all) and the
    critic architecture ``critic_arch`` (one of ``CRITIC_ARCHS``); ``advantage_dt`` > 0: an
    :class:`AdvantageCritic` of that architecture for the control step δ = ``advantage_dt`` s."""
    critic = ResidualMLP(tuple(hidden), 1) if critic_arch == "residual" else MLP(tuple(hidden), 1)
    if advantage_dt > 0:
        critic = AdvantageCritic(critic)
    actor = MLP(tuple(hidden), action_size, squash=True, in_size=actor_obs_size)
    return Networks(actor=actor, critic=critic, dt=advantage_dt)


def init_params(nets: Networks, key: jax.Array, obs_size: int, action_size: int):
    """Actor params and twin-critic params (leading axis 2)."""
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, obs_size))
    act = jnp.zeros((1, action_size))
    actor = nets.actor.init(k_actor, obs)
    if nets.dt > 0:
        init = lambda k: nets.critic.init(k, obs, act)  # noqa: E731
    else:
        init = lambda k: nets.critic.init(k, jnp.concatenate([obs, act], -1))  # noqa: E731
    critic = jax.vmap(init)(jax.random.split(k_critic, 2))
    return actor, critic


def policy(nets: Networks, actor_params, stats: ObsStats | None, obs: jax.Array) -> jax.Array:
    """The deterministic policy π(obs) for raw observations (..., n_obs)."""
    return nets.actor.apply(actor_params, normalize(stats, obs))


def twin_q(nets: Networks, critic_params, stats: ObsStats | None, obs: jax.Array,
           action: jax.Array) -> jax.Array:  # fmt: skip
    """Both critics' values, shape (2, ...), for raw obs (..., n_obs) and action (..., n_act)."""
    x = jnp.concatenate([normalize(stats, obs), action], -1)
    return jax.vmap(lambda p: nets.critic.apply(p, x)[..., 0])(critic_params)


def twin_v(nets: Networks, critic_params, stats: ObsStats | None, obs: jax.Array) -> jax.Array:
    """Both advantage critics' values V_i(obs), shape (2, ...) (``nets.dt`` > 0)."""
    x = normalize(stats, obs)
    return jax.vmap(lambda p: nets.critic.apply(p, x, method=AdvantageCritic.value))(critic_params)


def twin_adv(nets: Networks, critic_params, stats: ObsStats | None, obs: jax.Array,
             action: jax.Array) -> jax.Array:  # fmt: skip
    """Both critics' unnormalised advantages Ā_i(obs, action), shape (2, ...)."""
    x = normalize(stats, obs)
    adv = lambda p: nets.critic.apply(p, x, action, method=AdvantageCritic.advantage)  # noqa: E731
    return jax.vmap(adv)(critic_params)


def twin_q_adv(nets: Networks, critic_params, stats: ObsStats | None, obs: jax.Array, action: jax.Array,
               ref_action: jax.Array) -> jax.Array:  # fmt: skip
    """Deep advantage updating's Q_i = V_i(s) + δ (Ā_i(s, a) − Ā_i(s, π(s))), shape (2, ...), with
    ``ref_action`` = π(s): the advantage of the policy's own action is 0, so Q_i(s, π(s)) = V_i(s)."""
    adv = twin_adv(nets, critic_params, stats, obs, action)
    adv = adv - twin_adv(nets, critic_params, stats, obs, ref_action)
    return twin_v(nets, critic_params, stats, obs) + nets.dt * adv
