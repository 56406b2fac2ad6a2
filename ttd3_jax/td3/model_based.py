"""The actor update through the simulator (``model_horizon`` H > 0; the ``fast`` preset, not
in the paper): the actor learns from the gradient of an H-step rollout's return
back-propagated through the differentiable env (:func:`model_loss`).  The actor never reads
the critics.  With ``updates_per_step`` G > 0 the rollout's transitions go to the buffer and
the twin critics train as in TD3, each update moving T-TD3's σ from its minibatch's rewards
(:func:`~ttd3_jax.td3.core.update_sigma`), and every ``policy_delay`` updates the targets.
With G = 0 (the ``fast`` preset) no critic trains and nothing is stored: σ moves once per
rollout, from the rollout's own rewards as T-TD3's minibatch (docs/paper-notes.md), and the
random warm-up is the first rollouts (:func:`warming_up`), so the init program holds no env
step.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from ttd3_jax.td3 import core
from ttd3_jax.td3 import networks as nn
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.core import Finished, Setup, StepMetrics, TrainState


def model_loss(actor, s: Setup, ts: TrainState, hp: Hyper, key: jax.Array):
    """``model_horizon`` steps of all envs under the noisy current policy, differentiable in
    ``actor``: returns −mean_envs Σ_{k<H} γ^k r_k (scaled rewards; an episode's return stops
    where it ends), and as aux the env state and running returns after the rollout, its
    transitions (H, n, ...) and the :class:`~ttd3_jax.td3.core.Finished` episodes."""
    stats, std, warm = core.obs_stats(s, ts), core.exploration_std(s, ts), warming_up(s, ts)

    def body(carry, k):
        state, ep_ret, alive, disc, ret, fin = carry
        k_noise, k_reset = jax.random.split(k)
        pi = nn.policy(s.nets, actor, stats, state.obs)
        a = jnp.clip(pi + std * jax.random.normal(k_noise, pi.shape), -1.0, 1.0)
        if s.config.warmup_in_rollouts:  # the warm-up: uniform-random actions
            rand = jax.random.uniform(jax.random.fold_in(k_noise, 1), pi.shape, minval=-1.0, maxval=1.0)
            a = jnp.where(warm, rand, a)
        state, tr, ep_ret, f = core.env_step(s, state, ep_ret, hp=hp, actions=a, key=k_reset)
        ret = ret + disc * alive * tr.reward
        fin = Finished(fin.return_sum + f.return_sum, fin.count + f.count)
        return (state, ep_ret, alive * (1.0 - tr.done), disc * hp.gamma, ret, fin), jax.lax.stop_gradient(tr)

    zero, n = jnp.zeros(()), s.config.num_envs
    carry = (ts.env_state, ts.ep_return, jnp.ones(n), jnp.ones(()), jnp.zeros(n), Finished(zero, zero))
    carry, trs = jax.lax.scan(body, carry, jax.random.split(key, s.config.model_horizon))
    state, ep_ret, _, _, ret, fin = carry
    return -jnp.mean(ret), (jax.lax.stop_gradient((state, ep_ret)), trs, fin)


def warming_up(s: Setup, ts: TrainState) -> jax.Array:
    """Whether the next rollout is one of the warm-up's (``TrainConfig.warmup_rollouts``)."""
    c = s.config
    return ts.n_tr < c.warmup_rollouts * c.model_horizon * c.num_envs


def model_actor_update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array):
    """One actor update from a differentiable rollout; its transitions go to the buffer and
    the envs continue from where it ended.  Returns ``(ts, loss, finished, the rollout's
    (scaled) rewards, flat)``."""
    grad = jax.value_and_grad(model_loss, has_aux=True)
    (loss, ((env_state, ep_return), trs, fin)), g = grad(ts.actor, s, ts, hp, key)
    g, _ = optax.clip_by_global_norm(hp.model_grad_clip).update(g, optax.EmptyState())
    actor, actor_opt = core.adam_step(s, ts.actor, ts.actor_opt, g, core.actor_lr(s, ts, hp))
    if s.config.warmup_in_rollouts:  # a warm-up rollout leaves the actor and its Adam state alone
        keep = warming_up(s, ts)
        actor, actor_opt = jax.tree.map(lambda old, new: jnp.where(keep, old, new), (ts.actor, ts.actor_opt),
                                        (actor, actor_opt))  # fmt: skip
    ts = ts.replace(actor=actor, actor_opt=actor_opt, env_state=env_state, ep_return=ep_return)
    ts = jax.lax.scan(lambda t, tr: (core.store(s, t, tr), None), ts, trs)[0]
    return ts, loss, fin, trs.reward.reshape(-1)


def update(s: Setup, hp: Hyper, ts: TrainState, x):
    """One critic step, the σ update and, every d-th update, the target step (the actor
    learns from the rollout, not here)."""
    key, j = x
    ts, _, rewards, c_loss, q_mean = core.critic_update(s, ts, hp, key)
    ts = core.update_sigma(s, ts, hp, rewards)
    ts = jax.lax.cond(core.delay_due(s.config, ts, j), lambda ts: core.polyak(ts, hp), lambda ts: ts, ts)
    return ts, (c_loss, q_mean)


def vector_step(s: Setup, hp: Hyper, ts: TrainState, _=None):
    """An H-step rollout that updates the actor, then G critic updates (each followed by σ's
    update from its minibatch), or with G = 0 one σ update from the rollout's own rewards;
    returns the state and ``(StepMetrics, Finished)`` (the actor loss is the rollout's; the
    critics' metrics are nan without critics)."""
    c = s.config
    key, k_noise, k_upd = jax.random.split(ts.key, 3)
    ts, m_loss, finished, rewards = model_actor_update(s, ts.replace(key=key), hp, k_noise)
    if not c.trains_critics:
        ts, nan = core.update_sigma(s, ts, hp, rewards), jnp.full((), jnp.nan)
        return ts, (StepMetrics(nan, m_loss, nan), finished)
    xs = (jax.random.split(k_upd, c.updates_per_step), jnp.arange(c.updates_per_step))
    ts, (c_loss, q) = jax.lax.scan(lambda t, x: update(s, hp, t, x), ts, xs)
    return ts, (StepMetrics(jnp.mean(c_loss), m_loss, jnp.mean(q)), finished)
