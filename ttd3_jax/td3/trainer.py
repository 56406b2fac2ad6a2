"""T-TD3 / TD3 trainer: parallel envs, device replay buffer and updates in one ``lax.scan``.

Pure module-level functions, each taking the static :class:`Setup` first, then the
:class:`TrainState`, the :class:`~ttd3_jax.td3.config.Hyper` pytree and a key (``vmap`` over
those for sweeps); :func:`make_trainer` only binds them.  One transition: :func:`env_step`
steps the vmapped envs (true next observation, the env's ``terminated`` apart from
truncation) and auto-resets finished ones; :func:`store` writes it to the buffer;
:func:`update` samples a minibatch for :func:`critic_update`, the σ update
(:mod:`~ttd3_jax.td3.noise`) and, every ``policy_delay`` updates, :func:`actor_update` and
the Polyak step.  :func:`vector_step` is one env step plus G updates, :func:`epoch` a scan
of them.  With ``model_horizon`` H > 0 (``fast``; not in the paper) the actor step is
:func:`model_actor_update`: the gradient of an H-step rollout's return (:func:`model_loss`)
flows back through the simulator into the actor, and its transitions train the critics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ttd3_jax.td3 import buffer as rb
from ttd3_jax.td3 import noise as nz
from ttd3_jax.td3 import normalize as nrm
from ttd3_jax.td3.config import Hyper, TrainConfig
from ttd3_jax.td3.envs import EnvSpec
from ttd3_jax.td3.losses import actor_loss, critic_loss
from ttd3_jax.td3.networks import Networks, init_params, make_networks


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
    ep_return: jax.Array  # (num_envs,) return of the running episodes
    obs_stats: nrm.ObsStats  # running observation statistics (used if normalize_obs)
    noise: nz.NoiseState
    key: jax.Array
    n_tr: jax.Array  # int32, transitions collected
    n_upd: jax.Array  # int32, gradient updates done


class Setup(NamedTuple):
    """The static half of a trainer: config, env, networks and one optimiser per network."""

    config: TrainConfig
    env: EnvSpec
    nets: Networks
    adam: optax.GradientTransformation  # Adam with an injected learning rate, set from ``hp``


class Finished(NamedTuple):
    """Episodes that ended in a batch of steps: the sum and the count of their returns."""

    return_sum: jax.Array
    count: jax.Array


def make_setup(c: TrainConfig, env: EnvSpec) -> Setup:
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=0.0)
    actor_in = env.actor_obs_size if env.actor_obs_size != env.obs_size else None
    return Setup(c, env, make_networks(env.action_size, c.hidden, c.critic_arch, actor_in), adam)


def obs_stats(s: Setup, ts: TrainState) -> nrm.ObsStats | None:
    """The normaliser the networks see (``None`` without ``normalize_obs``)."""
    return ts.obs_stats if s.config.normalize_obs else None


def act(s: Setup, actor, stats: nrm.ObsStats | None, obs: jax.Array) -> jax.Array:
    """The deterministic policy π(obs) for raw observations (..., n_obs)."""
    return s.nets.actor.apply(actor, nrm.apply(stats, obs))


def exploration_std(s: Setup, ts: TrainState) -> jax.Array:
    return nz.std(s.config.noise, ts.noise.sigma)


def _where(mask, a, b):
    """Per-env select between two batched pytrees (mask (n,))."""
    return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def env_step(s: Setup, env_state, ep_return, hp: Hyper, actions: jax.Array, key: jax.Array):
    """Step all envs with ``actions`` and auto-reset finished ones (fresh track and start).

    Returns the new env state, the :class:`~ttd3_jax.td3.buffer.Transition` (true next
    observation, ``terminated`` apart from truncation), the running episode returns and the
    :class:`Finished` episodes."""
    env, n = s.env.env, s.config.num_envs
    nxt = jax.vmap(env.step)(env_state, actions)
    reward = hp.reward_scale * nxt.reward
    tr = rb.Transition(obs=env_state.obs, action=actions, reward=reward, next_obs=nxt.obs,
                       terminated=nxt.info["terminated"], done=nxt.done)  # fmt: skip
    done = nxt.done > 0
    ep_return = ep_return + nxt.reward
    finished = Finished(jnp.sum(jnp.where(done, ep_return, 0.0)), jnp.sum(done))
    reset = lambda: _where(done, jax.vmap(env.reset)(jax.random.split(key, n)), nxt)  # noqa: E731
    new_state = jax.lax.cond(jnp.any(done), reset, lambda: nxt)
    return new_state, tr, jnp.where(done, 0.0, ep_return), finished


def store(s: Setup, ts: TrainState, tr: rb.Transition) -> TrainState:
    """Insert one env batch of transitions; update the observation statistics."""
    stats = nrm.update(ts.obs_stats, tr.next_obs) if s.config.normalize_obs else ts.obs_stats
    return ts.replace(obs_stats=stats, buffer=rb.insert(ts.buffer, tr), n_tr=ts.n_tr + s.config.num_envs)


def collect(s: Setup, ts: TrainState, hp: Hyper, actions: jax.Array, key: jax.Array):
    """Step all envs with ``actions``, store the transitions, auto-reset finished envs;
    returns the state and the :class:`Finished` episodes."""
    env_state, tr, ep_return, finished = env_step(s, ts.env_state, ts.ep_return, hp, actions, key)
    return store(s, ts.replace(env_state=env_state, ep_return=ep_return), tr), finished


def init(s: Setup, key: jax.Array, hp: Hyper) -> TrainState:
    """A fresh state: networks, optimisers, envs, then the random warm-up (spec A8)."""
    c, env, n = s.config, s.env, s.config.num_envs
    k_net, k_env, k_warm, k_run = jax.random.split(key, 4)
    actor, critic = init_params(s.nets, k_net, env.obs_size, env.action_size)
    zero = jnp.zeros((), jnp.int32)
    ts = TrainState(
        actor=actor, critic=critic, target_actor=actor, target_critic=critic,
        actor_opt=_with_lr(s.adam.init(actor), hp.lr_actor),
        critic_opt=_with_lr(s.adam.init(critic), hp.lr_critic),
        buffer=rb.init(c.buffer_capacity, env.obs_size, env.action_size),
        env_state=jax.vmap(env.env.reset)(jax.random.split(k_env, n)), ep_return=jnp.zeros(n),
        obs_stats=nrm.init(env.obs_size), noise=nz.init(hp, c.time_attenuating), key=k_run,
        n_tr=zero, n_upd=zero,
    )  # fmt: skip

    def warm(ts, k):  # uniform-random actions before learning
        k_a, k_r = jax.random.split(k)
        a = jax.random.uniform(k_a, (n, env.action_size), minval=-1.0, maxval=1.0)
        return collect(s, ts, hp, a, k_r)[0], None

    if c.normalize_obs:
        ts = ts.replace(obs_stats=nrm.update(ts.obs_stats, ts.env_state.obs))
    return jax.lax.scan(warm, ts, jax.random.split(k_warm, c.warmup_steps))[0]


def with_actor(s: Setup, ts: TrainState, actor, hp: Hyper) -> TrainState:
    """``ts`` with ``actor`` as its policy (e.g. a behaviour-cloned one): the target actor set
    to it and a fresh Adam state for it."""
    return ts.replace(actor=actor, target_actor=actor, actor_opt=_with_lr(s.adam.init(actor), hp.lr_actor))


def initial_actor(s: Setup, key: jax.Array) -> dict:
    """The actor parameters :func:`init` starts from (the warm-up leaves them unchanged)."""
    k_net = jax.random.split(key, 4)[0]  # as in init
    return init_params(s.nets, k_net, s.env.obs_size, s.env.action_size)[0]


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """Per-seed keys: seed i of a vmapped run equals seed ``seed + i`` run alone."""
    root = jax.random.PRNGKey(0)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(seed, seed + num_seeds))


def _with_lr(opt_state, lr):
    """The optimiser state with its injected learning rate set to ``lr`` (in the dtype of
    the state's, so that the state's type does not depend on where ``lr`` came from)."""
    lr = jnp.asarray(lr, opt_state.hyperparams["learning_rate"].dtype)
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def adam_step(s: Setup, params, opt_state, grads, lr):
    """One Adam step at learning rate ``lr``; returns ``(params, opt_state)``."""
    updates, opt_state = s.adam.update(grads, _with_lr(opt_state, lr), params)
    return optax.apply_updates(params, updates), opt_state


def polyak(ts: TrainState, hp: Hyper) -> TrainState:
    """Move both target networks a step ``hp.tau`` towards the current ones."""
    return ts.replace(
        target_actor=optax.incremental_update(ts.actor, ts.target_actor, hp.tau),
        target_critic=optax.incremental_update(ts.critic, ts.target_critic, hp.tau),
    )


def critic_update(s: Setup, ts: TrainState, hp: Hyper, batch: rb.Transition, key: jax.Array):
    """One twin-critic step on a (normalised) minibatch; returns ``(ts, loss, mean Q_1)``."""
    shared = s.config.target_noise == "shared_sigma"
    target_std = exploration_std(s, ts) if shared else hp.target_sigma
    grad = jax.value_and_grad(critic_loss, has_aux=True)
    (loss, q_mean), g = grad(ts.critic, s.nets, ts.target_actor, ts.target_critic, batch, key, hp, target_std)
    critic, critic_opt = adam_step(s, ts.critic, ts.critic_opt, g, hp.lr_critic)
    return ts.replace(critic=critic, critic_opt=critic_opt), loss, q_mean


def actor_update(s: Setup, ts: TrainState, hp: Hyper, batch: rb.Transition):
    """One actor step along ∂Q₁/∂a (TD3) and the target update; returns ``(ts, loss)``.
    With ``model_horizon`` > 0 the rollout already moved the actor: targets only."""
    if s.config.model_horizon > 0:
        return polyak(ts, hp), jnp.full((), jnp.nan)
    loss, g = jax.value_and_grad(actor_loss)(ts.actor, s.nets, ts.critic, batch.obs)
    actor, actor_opt = adam_step(s, ts.actor, ts.actor_opt, g, hp.lr_actor)
    return polyak(ts.replace(actor=actor, actor_opt=actor_opt), hp), loss


def update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array, j: jax.Array):
    """One critic step, the σ update and, every d-th update, the actor + target step.  ``j``
    is the update's index in its vector step (not batched under a seed ``vmap``): when G is a
    multiple of d, ``j`` alone decides, so the ``lax.cond`` stays a branch under ``vmap``."""
    c = s.config
    k_batch, k_target = jax.random.split(key)
    batch = rb.sample(ts.buffer, k_batch, c.batch_size)
    if c.normalize_obs:
        stats = ts.obs_stats
        batch = batch.replace(obs=nrm.apply(stats, batch.obs), next_obs=nrm.apply(stats, batch.next_obs))
    ts, c_loss, q_mean = critic_update(s, ts, hp, batch, k_target)
    n_upd = ts.n_upd + 1
    noise = nz.update(c.noise, c.time_attenuating, hp, ts.noise, batch.reward, ts.n_tr, n_upd,
                      s.env.episode_length)  # fmt: skip
    ts = ts.replace(noise=noise, n_upd=n_upd)
    aligned = c.updates_per_step % c.policy_delay == 0
    due = (j + 1) % c.policy_delay == 0 if aligned else n_upd % c.policy_delay == 0
    nan = jnp.full((), jnp.nan)
    ts, a_loss = jax.lax.cond(due, lambda ts: actor_update(s, ts, hp, batch), lambda ts: (ts, nan), ts)
    return ts, (c_loss, a_loss, q_mean)


def model_loss(s: Setup, actor, ts: TrainState, hp: Hyper, key: jax.Array):
    """``model_horizon`` steps of all envs under the noisy current policy, differentiable in
    ``actor``: returns −mean_envs Σ_{k<H} γ^k r_k (scaled rewards; an episode's return stops
    where it ends), and as aux the env state and running returns after the rollout, its
    transitions (H, n, ...) and the :class:`Finished` episodes."""
    stats, std, n = obs_stats(s, ts), exploration_std(s, ts), s.config.num_envs

    def body(carry, k):
        state, ep_ret, alive, disc, ret, fin = carry
        k_noise, k_reset = jax.random.split(k)
        pi = act(s, actor, stats, state.obs)
        a = jnp.clip(pi + std * jax.random.normal(k_noise, pi.shape), -1.0, 1.0)
        state, tr, ep_ret, f = env_step(s, state, ep_ret, hp, a, k_reset)
        ret = ret + disc * alive * tr.reward
        fin = Finished(fin.return_sum + f.return_sum, fin.count + f.count)
        carry = (state, ep_ret, alive * (1.0 - tr.done), disc * hp.gamma, ret, fin)
        return carry, jax.lax.stop_gradient(tr)

    zero = jnp.zeros(())
    carry = (ts.env_state, ts.ep_return, jnp.ones(n), jnp.ones(()), jnp.zeros(n), Finished(zero, zero))
    carry, trs = jax.lax.scan(body, carry, jax.random.split(key, s.config.model_horizon))
    state, ep_ret, _, _, ret, fin = carry
    return -jnp.mean(ret), (jax.lax.stop_gradient((state, ep_ret)), trs, fin)


def model_actor_update(s: Setup, ts: TrainState, hp: Hyper, key: jax.Array):
    """One actor update from a differentiable rollout (``model_horizon`` > 0); its
    transitions go to the buffer and the envs continue from where it ended.  Returns
    ``(ts, loss, finished)``."""
    grad = jax.value_and_grad(lambda a: model_loss(s, a, ts, hp, key), has_aux=True)
    (loss, ((env_state, ep_return), trs, fin)), g = grad(ts.actor)
    norm = jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree.leaves(g)))
    g = jax.tree.map(lambda x: x * jnp.minimum(1.0, hp.model_grad_clip / (norm + 1e-12)), g)
    actor, actor_opt = adam_step(s, ts.actor, ts.actor_opt, g, hp.lr_actor)
    ts = ts.replace(actor=actor, actor_opt=actor_opt, env_state=env_state, ep_return=ep_return)
    ts = jax.lax.scan(lambda t, tr: (store(s, t, tr), None), ts, trs)[0]
    return ts, loss, fin


class StepMetrics(NamedTuple):
    critic_loss: jax.Array
    actor_loss: jax.Array
    q_mean: jax.Array


def vector_step(s: Setup, ts: TrainState, hp: Hyper):
    """One env step of all envs (or an H-step model rollout), then G updates."""
    c = s.config
    key, k_noise, k_reset, k_upd = jax.random.split(ts.key, 4)
    ts = ts.replace(key=key)
    if c.model_horizon > 0:
        ts, m_loss, finished = model_actor_update(s, ts, hp, k_noise)
    else:
        a = act(s, ts.actor, obs_stats(s, ts), ts.env_state.obs)
        a = a + exploration_std(s, ts) * jax.random.normal(k_noise, (c.num_envs, s.env.action_size))
        ts, finished = collect(s, ts, hp, jnp.clip(a, -1.0, 1.0), k_reset)
    keys = (jax.random.split(k_upd, c.updates_per_step), jnp.arange(c.updates_per_step))
    ts, (c_loss, a_loss, q) = jax.lax.scan(lambda t, x: update(s, t, hp, *x), ts, keys)
    a_loss = m_loss if c.model_horizon > 0 else jnp.nanmean(a_loss)
    return ts, (StepMetrics(jnp.mean(c_loss), a_loss, jnp.mean(q)), finished)


def epoch(s: Setup, ts: TrainState, hp: Hyper):
    """``steps_per_epoch`` vector steps; returns the state and the epoch's mean metrics."""
    c = s.config
    ts, (out, fin) = jax.lax.scan(lambda t, _: vector_step(s, t, hp), ts, None, length=c.steps_per_epoch)
    m = {k: jnp.nanmean(v) for k, v in out._asdict().items()}
    n_ep = jnp.sum(fin.count)
    m.update(
        train_return=jnp.where(n_ep > 0, jnp.sum(fin.return_sum) / jnp.maximum(n_ep, 1), jnp.nan),
        episodes=n_ep.astype(jnp.float32),
        sigma=ts.noise.sigma,
        env_steps=ts.n_tr.astype(jnp.float32),
    )
    return ts, m


def evaluate(s: Setup, ts: TrainState) -> dict:
    """The env's evaluation of the deterministic policy (separate envs, fixed keys)."""
    stats = obs_stats(s, ts)
    return s.env.evaluate(lambda obs: act(s, ts.actor, stats, obs))


def train(s: Setup, key: jax.Array, hp: Hyper):
    """The whole run fused into one program: ``(state, per-epoch metrics, per-epoch eval)``."""

    def body(ts, _):
        ts, m = epoch(s, ts, hp)
        return ts, (m, evaluate(s, ts))

    ts, (m, ev) = jax.lax.scan(body, init(s, key, hp), None, s.config.epochs)
    return ts, m, ev


class Trainer(NamedTuple):
    """The trainer's functions bound to one :class:`Setup`; ``vmap`` them over seeds /
    hyperparameters."""

    setup: Setup
    init: Callable  # (key, hp) -> TrainState, buffer filled by the random warm-up
    epoch: Callable  # (ts, hp) -> (ts, metrics): steps_per_epoch vector steps + updates
    evaluate: Callable  # (ts) -> eval metrics (deterministic policy, separate envs)
    train: Callable  # (key, hp) -> (ts, per-epoch metrics, per-epoch eval): fully fused

    @property
    def config(self) -> TrainConfig:
        return self.setup.config

    @property
    def env(self) -> EnvSpec:
        return self.setup.env

    @property
    def nets(self) -> Networks:
        return self.setup.nets


def make_trainer(c: TrainConfig, env: EnvSpec) -> Trainer:
    """The pure training functions for config ``c`` on ``env``."""
    if c.model_horizon > 0 and not env.differentiable:
        raise ValueError("model_horizon > 0 back-propagates through the simulator; this env is not")
    s = make_setup(c, env)
    return Trainer(
        setup=s,
        init=lambda key, hp: init(s, key, hp),
        epoch=lambda ts, hp: epoch(s, ts, hp),
        evaluate=lambda ts: evaluate(s, ts),
        train=lambda key, hp: train(s, key, hp),
    )
