"""One vector step of the paper's T-TD3 / TD3: collect, store, twin-critic updates, σ, and
every ``policy_delay`` updates the actor step along ∂Q₁/∂a (deterministic policy gradient)
and the Polyak step.

Pure functions, each taking the static :class:`Setup` first, then the :class:`TrainState`,
the :class:`~ttd3_jax.td3.config.Hyper` pytree and a key (``vmap`` over those for sweeps).
One transition: :func:`vector_step` acts (:func:`~ttd3_jax.td3.networks.policy` plus
Gaussian noise of std σ, :mod:`~ttd3_jax.td3.noise`); :func:`env_step` steps the vmapped
envs (true next observation, the env's ``terminated`` apart from truncation) and
auto-resets finished ones; :func:`store` writes the batch to the buffer; :func:`update`
samples a minibatch for :func:`critic_update` (:func:`~ttd3_jax.td3.losses.critic_loss`),
moves σ and, when due, runs :func:`actor_update` and :func:`polyak`.  The model-based
step (:mod:`~ttd3_jax.td3.model_based`) reuses the collection and critic parts.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ttd3_jax.td3 import buffer as rb
from ttd3_jax.td3 import networks as nn
from ttd3_jax.td3 import noise as nz
from ttd3_jax.td3.config import Hyper, TrainConfig
from ttd3_jax.td3.env_spec import EnvSpec
from ttd3_jax.td3.losses import actor_loss, advantage_actor_loss, advantage_critic_loss, critic_loss


@struct.dataclass
class TrainState:
    """Everything a run needs to continue exactly: checkpoint this whole pytree."""

    actor: dict
    critic: dict  # twin critics, leading axis 2
    target_actor: dict
    target_critic: dict
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    buffer: rb.ReplayBuffer
    env_state: object  # batched Brax State of the training envs
    ep_return: jax.Array  # (num_envs,) return of the running episodes, in the env's units
    obs_stats: nn.ObsStats  # running observation statistics (used if normalize_obs)
    noise: nz.NoiseState
    key: jax.Array
    n_tr: jax.Array  # int32, transitions collected
    n_upd: jax.Array  # int32, gradient updates done


class Setup(NamedTuple):
    """The static half of a trainer: config, env, networks and one optimiser per network."""

    config: TrainConfig
    env: EnvSpec
    nets: nn.Networks
    adam: optax.GradientTransformation  # Adam with an injected learning rate, set from ``hp``


class Finished(NamedTuple):
    """Episodes that ended in a batch of steps: the sum and the count of their returns."""

    return_sum: jax.Array
    count: jax.Array


class StepMetrics(NamedTuple):
    critic_loss: jax.Array
    actor_loss: jax.Array
    q_mean: jax.Array


def obs_stats(s: Setup, ts: TrainState) -> nn.ObsStats | None:
    """The normaliser the networks see (``None`` without ``normalize_obs``)."""
    return ts.obs_stats if s.config.normalize_obs else None


def exploration_std(s: Setup, ts: TrainState) -> jax.Array:
    return nz.std(s.config.noise, ts.noise.sigma)


def _where(mask, a, b):
    """Per-env select between two batched pytrees (mask (n,))."""
    return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def reset_envs(s: Setup, key: jax.Array, n_tr: jax.Array) -> object:
    """Fresh episodes for all envs; an env with a curriculum (``EnvSpec.curriculum``) is told
    the fraction of the run done, ``n_tr`` / ``transitions_run``."""
    keys = jax.random.split(key, s.config.num_envs)
    if not s.env.curriculum:
        return jax.vmap(s.env.env.reset)(keys)
    progress = n_tr / s.config.transitions_run
    return jax.vmap(lambda k: s.env.env.reset(k, progress=progress))(keys)


def env_step(s: Setup, env_state, ep_return, *, hp: Hyper, actions: jax.Array, key: jax.Array, n_tr):
    """Step all envs with ``actions`` and auto-reset finished ones (fresh track and start, at
    ``n_tr`` transitions collected: :func:`reset_envs`).

    Returns the new env state, the :class:`~ttd3_jax.td3.buffer.Transition` (true next
    observation, ``terminated`` apart from truncation, the reward scaled by
    ``hp.reward_scale``: the one place it is), the running episode returns (unscaled: the
    env's units) and the :class:`Finished` episodes."""
    nxt = jax.vmap(s.env.env.step)(env_state, actions)
    reward = hp.reward_scale * nxt.reward
    tr = rb.Transition(obs=env_state.obs, action=actions, reward=reward, next_obs=nxt.obs,
                       terminated=nxt.info["terminated"], done=nxt.done)  # fmt: skip
    done = nxt.done > 0
    ep_return = ep_return + nxt.reward
    finished = Finished(jnp.sum(jnp.where(done, ep_return, 0.0)), jnp.sum(done))
    reset = lambda: _where(done, reset_envs(s, key, n_tr), nxt)  # noqa: E731
    new_state = jax.lax.cond(jnp.any(done), reset, lambda: nxt)
    return new_state, tr, jnp.where(done, 0.0, ep_return), finished


def store(s: Setup, ts: TrainState, tr: rb.Transition) -> TrainState:
    """Insert one env batch of transitions; update the observation statistics."""
    stats = nn.update_obs_stats(ts.obs_stats, tr.next_obs) if s.config.normalize_obs else ts.obs_stats
    return ts.replace(obs_stats=stats, buffer=rb.insert(ts.buffer, tr), n_tr=ts.n_tr + s.config.num_envs)


def collect(s: Setup, ts: TrainState, hp: Hyper, actions: jax.Array, key: jax.Array):
    """Step all envs with ``actions``, store the transitions, auto-reset finished envs;
    returns the state and the :class:`Finished` episodes."""
    env_state, tr, ep_return, finished = env_step(s, ts.env_state, ts.ep_return, hp=hp, actions=actions,
                                                  key=key, n_tr=ts.n_tr)  # fmt: skip
    return store(s, ts.replace(env_state=env_state, ep_return=ep_return), tr), finished


def with_lr(opt_state, lr):
    """The optimiser state with its injected learning rate set to ``lr`` (in the dtype of
    the state's, so that the state's type does not depend on where ``lr`` came from)."""
    lr = jnp.asarray(lr, opt_state.hyperparams["learning_rate"].dtype)
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def adam_step(s: Setup, params, opt_state, grads, lr):
    """One Adam step at learning rate ``lr``; returns ``(params, opt_state)``."""
    updates, opt_state = s.adam.update(grads, with_lr(opt_state, lr), params)
    return optax.apply_updates(params, updates), opt_state


def polyak(ts: TrainState, hp: Hyper) -> TrainState:
    """Move both target networks a step ``hp.tau`` towards the current ones."""
    return ts.replace(
        target_actor=optax.incremental_update(ts.actor, ts.target_actor, hp.tau),
        target_critic=optax.incremental_update(ts.critic, ts.target_critic, hp.tau),
    )


def step_hyper(s: Setup, hp: Hyper) -> Hyper:
    """Deep advantage updating's hyperparameters at the env's control step δ: ``hp``'s per-step
    γ, learning rates and τ hold at ``advantage_dt`` s; at δ they are γ^ρ, lr ρ and
    1 − (1 − τ)^ρ, ρ = δ / ``advantage_dt`` (the same horizon, and the same parameter motion
    per second of experience, as at ``advantage_dt``).  The reward needs no factor: the env's
    reward of one step already integrates over its δ s."""
    rho = s.nets.dt / s.config.advantage_dt
    return hp.replace(gamma=hp.gamma**rho, lr_actor=hp.lr_actor * rho, lr_critic=hp.lr_critic * rho,
                      tau=1.0 - (1.0 - hp.tau) ** rho)  # fmt: skip


def critic_grad(s: Setup, ts: TrainState, hp: Hyper, batch: rb.Transition, key: jax.Array, discount):
    """``((loss, mean Q_1), gradient)`` of the twin critics on ``batch``: TD3's loss, or deep
    advantage updating's with ``advantage_dt`` > 0."""
    stats = obs_stats(s, ts)
    if s.config.advantage:
        grad = jax.value_and_grad(advantage_critic_loss, has_aux=True)
        return grad(ts.critic, nets=s.nets, actor=ts.actor, target_critic=ts.target_critic, stats=stats,
                    batch=batch, hp=hp, discount=discount)  # fmt: skip
    target_std = exploration_std(s, ts) if s.config.target_noise == "shared_sigma" else hp.target_sigma
    grad = jax.value_and_grad(critic_loss, has_aux=True)
    return grad(
        ts.critic, nets=s.nets, target_actor=ts.target_actor, target_critic=ts.target_critic,
        stats=stats, batch=batch, key=key, hp=hp, target_std=target_std, discount=discount,
    )  # fmt: skip


def critic_update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array):
    """One twin-critic step on a fresh minibatch (n-step returns with ``n_step`` > 1) and the
    σ update after it (on the rows' one-step rewards); returns ``(ts, batch, loss, mean Q_1)``."""
    c = s.config
    k_batch, k_target = jax.random.split(key)
    if c.n_step > 1:
        batch, discount, rewards = rb.sample_n_step(ts.buffer, k_batch, c.batch_size, n=c.n_step,
                                                    num_envs=c.num_envs, gamma=hp.gamma)  # fmt: skip
    else:
        batch = rb.sample(ts.buffer, k_batch, c.batch_size)
        discount, rewards = None, batch.reward
    (loss, q_mean), g = critic_grad(s, ts, hp, batch, k_target, discount)
    critic, critic_opt = adam_step(s, ts.critic, ts.critic_opt, g, hp.lr_critic)
    n_upd = ts.n_upd + 1
    noise = nz.update(ts.noise, cfg=c.noise, time_attenuating=c.time_attenuating, hp=hp, rewards=rewards,
                      n_tr=ts.n_tr, n_upd=n_upd, episode_length=s.env.episode_length)  # fmt: skip
    return ts.replace(critic=critic, critic_opt=critic_opt, noise=noise, n_upd=n_upd), batch, loss, q_mean


def delay_due(c: TrainConfig, ts: TrainState, j: jax.Array) -> jax.Array:
    """Whether update ``j`` of its vector step (just done) is a ``policy_delay``-th one.  When
    G is a multiple of d, ``j`` alone decides, so a ``lax.cond`` on it stays a branch under a
    seed ``vmap`` (``j`` is not batched)."""
    if c.updates_per_step % c.policy_delay == 0:
        return (j + 1) % c.policy_delay == 0
    return ts.n_upd % c.policy_delay == 0


def actor_update(s: Setup, ts: TrainState, hp: Hyper, batch: rb.Transition):
    """One actor step along ∂Q₁/∂a and the target update; returns ``(ts, loss)``."""
    grad = jax.value_and_grad(advantage_actor_loss if s.config.advantage else actor_loss)
    loss, g = grad(ts.actor, nets=s.nets, critic=ts.critic, stats=obs_stats(s, ts), obs=batch.obs)
    actor, actor_opt = adam_step(s, ts.actor, ts.actor_opt, g, hp.lr_actor)
    return polyak(ts.replace(actor=actor, actor_opt=actor_opt), hp), loss


def update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array, j: jax.Array):
    """One critic step, the σ update and, every d-th update, the actor + target step."""
    ts, batch, c_loss, q_mean = critic_update(s, ts, hp, key)
    nan = jnp.full((), jnp.nan)
    due = delay_due(s.config, ts, j)
    ts, a_loss = jax.lax.cond(due, lambda ts: actor_update(s, ts, hp, batch), lambda ts: (ts, nan), ts)
    return ts, (c_loss, a_loss, q_mean)


def vector_step(s: Setup, ts: TrainState, hp: Hyper):
    """One env step of all envs under the noisy policy, then G updates; returns the state
    and ``(StepMetrics, Finished)``."""
    c = s.config
    hp = step_hyper(s, hp) if c.advantage else hp
    key, k_noise, k_reset, k_upd = jax.random.split(ts.key, 4)
    a = nn.policy(s.nets, ts.actor, obs_stats(s, ts), ts.env_state.obs)
    a = a + exploration_std(s, ts) * jax.random.normal(k_noise, (c.num_envs, s.env.action_size))
    ts, finished = collect(s, ts.replace(key=key), hp, jnp.clip(a, -1.0, 1.0), k_reset)
    keys = (jax.random.split(k_upd, c.updates_per_step), jnp.arange(c.updates_per_step))
    ts, (c_loss, a_loss, q) = jax.lax.scan(lambda t, x: update(s, t, hp, *x), ts, keys)
    return ts, (StepMetrics(jnp.mean(c_loss), jnp.nanmean(a_loss), jnp.mean(q)), finished)
