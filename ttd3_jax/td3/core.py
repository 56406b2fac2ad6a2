"""TD3's core, shared by both actor updates: the train state, collection (env step → replay
buffer), the twin-critic update and its loss, the optimiser step and the target update.

Read one transition top to bottom: :func:`env_step` steps the vmapped envs and keeps the
true next observation and ``terminated`` apart from truncation, :func:`store` writes the
batch to the buffer, :func:`critic_update` samples a minibatch and takes one optax Adam step
on :func:`critic_loss`, and :func:`polyak` moves the targets.  The actor updates live in
:mod:`~ttd3_jax.td3.dpg` (the paper's ∂Q₁/∂a) and :mod:`~ttd3_jax.td3.model_based`
(through the simulator); each calls T-TD3's σ schedule (:mod:`~ttd3_jax.td3.noise`) itself.
Pure functions of the static :class:`Setup` first, then the :class:`TrainState`, the
:class:`~ttd3_jax.td3.config.Hyper` pytree and keys: ``vmap`` over those for sweeps.
"""

from __future__ import annotations

import functools
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


# -- collection: env step -> replay buffer ------------------------------------------------


def reset_envs(s: Setup, key: jax.Array) -> object:
    """Fresh episodes (a new track and start) for all envs."""
    return jax.vmap(s.env.env.reset)(jax.random.split(key, s.config.num_envs))


def _where(mask, a, b):
    """Per-env select between two batched pytrees (mask (n,))."""
    return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def env_step(s: Setup, env_state, ep_return, *, hp: Hyper, actions: jax.Array, key: jax.Array):
    """Step all envs with ``actions`` and auto-reset finished ones (:func:`reset_envs`).

    Returns the new env state, the :class:`~ttd3_jax.td3.buffer.Transition` (true next
    observation, ``terminated`` apart from truncation, the reward scaled by
    ``hp.reward_scale``: the one place it is), the running episode returns (unscaled: the
    env's units) and the :class:`Finished` episodes."""
    nxt = jax.vmap(s.env.env.step)(env_state, actions)
    tr = rb.Transition(obs=env_state.obs, action=actions, reward=hp.reward_scale * nxt.reward,
                       next_obs=nxt.obs, terminated=nxt.info["terminated"], done=nxt.done)  # fmt: skip
    done = nxt.done > 0
    ep_return = ep_return + nxt.reward
    finished = Finished(jnp.sum(jnp.where(done, ep_return, 0.0)), jnp.sum(done))
    new_state = jax.lax.cond(jnp.any(done), functools.partial(_reset_done, s, key, done, nxt), lambda: nxt)
    return new_state, tr, jnp.where(done, 0.0, ep_return), finished


def _reset_done(s: Setup, key: jax.Array, done: jax.Array, nxt):
    """``nxt`` with the envs that are ``done`` on fresh episodes (as :func:`reset_envs`)."""
    return _where(done, jax.vmap(s.env.env.reset)(jax.random.split(key, s.config.num_envs)), nxt)


def store(s: Setup, ts: TrainState, tr: rb.Transition) -> TrainState:
    """Insert one env batch of transitions (when critics train: nothing else reads the
    buffer); update the observation statistics and the transition count."""
    c = s.config
    stats = nn.update_obs_stats(ts.obs_stats, tr.next_obs) if c.normalize_obs else ts.obs_stats
    buffer = rb.insert(ts.buffer, tr) if c.trains_critics else ts.buffer
    return ts.replace(obs_stats=stats, buffer=buffer, n_tr=ts.n_tr + c.num_envs)


def collect(s: Setup, ts: TrainState, hp: Hyper, actions: jax.Array, key: jax.Array):
    """Step all envs with ``actions``, store the transitions, auto-reset finished envs;
    returns the state and the :class:`Finished` episodes."""
    env_state, tr, ep_return, finished = env_step(s, ts.env_state, ts.ep_return, hp=hp, actions=actions,
                                                  key=key)  # fmt: skip
    return store(s, ts.replace(env_state=env_state, ep_return=ep_return), tr), finished


# -- the twin critics ---------------------------------------------------------------------


def critic_loss(critic, *, nets: nn.Networks, target_actor, target_critic, stats: nn.ObsStats | None,
                batch: rb.Transition, key: jax.Array, hp: Hyper, target_std,
                discount: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """TD3's twin-critic loss Σ_i mean (y − Q_i(s, a))² and mean Q_1 over the batch (spec §2.4):
    y = r + γ (1 − terminated) min_i Q'_i(s', clip(π'(s') + clip(σ̃ ξ, −c, c), −1, 1)), σ̃ =
    ``target_std``, its noise clipped to ±``hp.target_clip``; ``discount`` (B,) replaces γ for
    n-step returns (γ^m of each row's m steps).  Observations arrive raw (the networks
    normalise them)."""
    disc = (hp.gamma if discount is None else discount) * (1.0 - batch.terminated)
    pi_next = nn.policy(nets, target_actor, stats, batch.next_obs)
    eps = jnp.clip(target_std * jax.random.normal(key, pi_next.shape), -hp.target_clip, hp.target_clip)
    a_next = jnp.clip(pi_next + eps, -1.0, 1.0)
    q_next = jnp.min(nn.twin_q(nets, target_critic, stats, batch.next_obs, a_next), axis=0)
    y = jax.lax.stop_gradient(batch.reward + disc * q_next)
    q = nn.twin_q(nets, critic, stats, batch.obs, batch.action)
    return jnp.sum(jnp.mean((q - y) ** 2, axis=-1)), jnp.mean(q[0])


def critic_update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array):
    """One twin-critic step on a fresh minibatch (n-step returns with ``n_step`` > 1); returns
    ``(ts, batch, the rows' one-step rewards, loss, mean Q_1)``."""
    c = s.config
    k_batch, k_target = jax.random.split(key)
    if c.n_step > 1:
        batch, discount, rewards = rb.sample_n_step(ts.buffer, k_batch, c.batch_size, n=c.n_step,
                                                    num_envs=c.num_envs, gamma=hp.gamma)  # fmt: skip
    else:
        batch = rb.sample(ts.buffer, k_batch, c.batch_size)
        discount, rewards = None, batch.reward
    target_std = exploration_std(s, ts) if c.target_noise == "shared_sigma" else hp.target_sigma  # A4
    grad = jax.value_and_grad(critic_loss, has_aux=True)
    targets = dict(target_actor=ts.target_actor, target_critic=ts.target_critic, target_std=target_std)
    (loss, q_mean), g = grad(ts.critic, nets=s.nets, stats=obs_stats(s, ts), batch=batch, key=k_target, hp=hp,
                             discount=discount, **targets)  # fmt: skip
    critic, critic_opt = adam_step(s, ts.critic, ts.critic_opt, g, hp.lr_critic)
    ts = ts.replace(critic=critic, critic_opt=critic_opt, n_upd=ts.n_upd + 1)
    return ts, batch, rewards, loss, q_mean


def update_sigma(s: Setup, ts: TrainState, hp: Hyper, rewards: jax.Array) -> TrainState:
    """T-TD3's σ after a critic update on a minibatch with one-step ``rewards`` (TD3: constant)."""
    c = s.config
    noise = nz.update(ts.noise, cfg=c.noise, time_attenuating=c.time_attenuating, hp=hp, rewards=rewards,
                      n_tr=ts.n_tr, n_upd=ts.n_upd, episode_length=s.env.episode_length)  # fmt: skip
    return ts.replace(noise=noise)


# -- the optimiser step and the targets ---------------------------------------------------


def with_lr(opt_state, lr):
    """The optimiser state with its injected learning rate set to ``lr`` (in the dtype of
    the state's, so that the state's type does not depend on where ``lr`` came from)."""
    lr = jnp.asarray(lr, opt_state.hyperparams["learning_rate"].dtype)
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def adam_step(s: Setup, params, opt_state, grads, lr):
    """One Adam step at learning rate ``lr``; returns ``(params, opt_state)``."""
    updates, opt_state = s.adam.update(grads, with_lr(opt_state, lr), params)
    return optax.apply_updates(params, updates), opt_state


def actor_lr(s: Setup, ts: TrainState, hp: Hyper) -> jax.Array:
    """The actor's learning rate now: ``hp.lr_actor``, falling linearly by the fraction
    ``hp.lr_decay`` as the run's transitions are collected."""
    done = ts.n_tr.astype(jnp.float32) / s.config.transitions_run
    return hp.lr_actor * (1.0 - hp.lr_decay * done)


def delay_due(c: TrainConfig, ts: TrainState, j: jax.Array) -> jax.Array:
    """Whether update ``j`` of its vector step (just done) is a ``policy_delay``-th one.  When
    G is a multiple of d, ``j`` alone decides, so a ``lax.cond`` on it stays a branch under a
    seed ``vmap`` (``j`` is not batched)."""
    if c.updates_per_step % c.policy_delay == 0:
        return (j + 1) % c.policy_delay == 0
    return ts.n_upd % c.policy_delay == 0


def polyak(ts: TrainState, hp: Hyper) -> TrainState:
    """Move both target networks a step ``hp.tau`` towards the current ones."""
    return ts.replace(
        target_actor=optax.incremental_update(ts.actor, ts.target_actor, hp.tau),
        target_critic=optax.incremental_update(ts.critic, ts.target_critic, hp.tau),
    )
