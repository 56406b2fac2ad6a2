"""The paper's actor update (T-TD3 / TD3): the actor follows ∂Q₁/∂a through the first critic
(the deterministic policy gradient), every ``policy_delay`` critic updates.

One vector step (:func:`vector_step`): act with the policy plus Gaussian noise of std σ,
collect and store (:func:`~ttd3_jax.td3.core.collect`), then G times: a critic update
(:func:`~ttd3_jax.td3.core.critic_update`), T-TD3's σ from its minibatch rewards
(:func:`~ttd3_jax.td3.core.update_sigma`) and, when due, :func:`actor_update` and the targets.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax.td3 import core
from ttd3_jax.td3 import networks as nn
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.core import Setup, StepMetrics, TrainState


def actor_loss(actor, *, nets: nn.Networks, critic, stats: nn.ObsStats | None, obs: jax.Array) -> jax.Array:
    """The deterministic policy gradient objective through the first critic: −mean Q_1(s, π(s))."""
    a = nn.policy(nets, actor, stats, obs)
    return -jnp.mean(nn.twin_q(nets, jax.tree.map(lambda p: p[:1], critic), stats, obs, a)[0])


def actor_update(s: Setup, ts: TrainState, hp: Hyper, obs: jax.Array):
    """One actor step along ∂Q₁/∂a and the target update; returns ``(ts, loss)``."""
    loss, g = jax.value_and_grad(actor_loss)(
        ts.actor, nets=s.nets, critic=ts.critic, stats=core.obs_stats(s, ts), obs=obs
    )
    actor, actor_opt = core.adam_step(s, ts.actor, ts.actor_opt, g, core.actor_lr(s, ts, hp))
    return core.polyak(ts.replace(actor=actor, actor_opt=actor_opt), hp), loss


def update(s: Setup, hp: Hyper, ts: TrainState, x):
    """One critic step, the σ update and, every d-th update, the actor + target step
    (``x``: this update's key and its index ``j`` in the vector step)."""
    key, j = x
    ts, batch, rewards, c_loss, q_mean = core.critic_update(s, ts, hp, key)
    ts = core.update_sigma(s, ts, hp, rewards)
    nan = jnp.full((), jnp.nan)
    due = core.delay_due(s.config, ts, j)
    ts, a_loss = jax.lax.cond(due, lambda ts: actor_update(s, ts, hp, batch.obs), lambda ts: (ts, nan), ts)
    return ts, (c_loss, a_loss, q_mean)


def vector_step(s: Setup, hp: Hyper, ts: TrainState, _=None):
    """One env step of all envs under the noisy policy, then G updates; returns the state
    and ``(StepMetrics, Finished)``."""
    c = s.config
    key, k_noise, k_reset, k_upd = jax.random.split(ts.key, 4)
    a = nn.policy(s.nets, ts.actor, core.obs_stats(s, ts), ts.env_state.obs)
    a = a + core.exploration_std(s, ts) * jax.random.normal(k_noise, (c.num_envs, s.env.action_size))
    ts, finished = core.collect(s, ts.replace(key=key), hp, jnp.clip(a, -1.0, 1.0), k_reset)
    xs = (jax.random.split(k_upd, c.updates_per_step), jnp.arange(c.updates_per_step))
    ts, (c_loss, a_loss, q) = jax.lax.scan(lambda t, x: update(s, hp, t, x), ts, xs)
    return ts, (StepMetrics(jnp.mean(c_loss), jnp.nanmean(a_loss), jnp.mean(q)), finished)
