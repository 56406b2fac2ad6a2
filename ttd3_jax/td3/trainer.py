"""T-TD3 / TD3 trainer: parallel envs, device replay buffer and updates in one ``lax.scan``.

:func:`make_trainer` picks the actor update once: :func:`~ttd3_jax.td3.dpg.vector_step`,
the paper's update through the critic (∂Q₁/∂a), or
:func:`~ttd3_jax.td3.model_based.vector_step`, the update through the simulator (``fast``,
a rollout horizon H > 0).  Around it, pure functions of the static
:class:`~ttd3_jax.td3.core.Setup`: :func:`init` (networks, optimisers, envs, random warm-up),
:func:`epoch` (a scan of vector steps), :func:`evaluate` and :func:`train` (the whole run
fused).  ``vmap`` them over seeds and hyperparameters for sweeps.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ttd3_jax import checks
from ttd3_jax.td3 import buffer as rb
from ttd3_jax.td3 import core, dpg, model_based
from ttd3_jax.td3 import networks as nn
from ttd3_jax.td3 import noise as nz
from ttd3_jax.td3.config import Hyper, TrainConfig
from ttd3_jax.td3.core import Setup, TrainState
from ttd3_jax.td3.env_spec import EnvSpec

StepFn = Callable[[Setup, Hyper, TrainState, None], tuple]  # (s, hp, ts, _) -> (ts, (StepMetrics, Finished))


def make_setup(c: TrainConfig, env: EnvSpec) -> Setup:
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=0.0)
    actor_in = env.actor_obs_size if env.actor_obs_size != env.obs_size else None
    return Setup(c, env, nn.make_networks(env.action_size, c.hidden, c.critic_arch, actor_in), adam)


def act(s: Setup, actor, stats: nn.ObsStats | None, obs: jax.Array) -> jax.Array:
    """The deterministic policy π(obs) for raw observations (..., n_obs)."""
    return nn.policy(s.nets, actor, stats, obs)


def init(s: Setup, key: jax.Array, hp: Hyper) -> TrainState:
    """A fresh state: networks, optimisers, envs, then the random warm-up (spec A8)."""
    c, env, n = s.config, s.env, s.config.num_envs
    k_net, k_env, k_warm, k_run = jax.random.split(key, 4)
    actor, critic = nn.init_params(s.nets, k_net, env.obs_size, env.action_size)
    zero = jnp.zeros((), jnp.int32)
    ts = TrainState(
        actor=actor, critic=critic, target_actor=actor, target_critic=critic,
        actor_opt=core.with_lr(s.adam.init(actor), hp.lr_actor),
        critic_opt=core.with_lr(s.adam.init(critic), hp.lr_critic),
        buffer=rb.init(c.buffer_capacity, env.obs_size, env.action_size),
        env_state=core.reset_envs(s, k_env), ep_return=jnp.zeros(n),
        obs_stats=nn.init_obs_stats(env.obs_size), noise=nz.init(hp, c.time_attenuating), key=k_run,
        n_tr=zero, n_upd=zero,
    )  # fmt: skip

    def warm(ts, k):  # uniform-random actions before learning
        k_a, k_r = jax.random.split(k)
        a = jax.random.uniform(k_a, (n, env.action_size), minval=-1.0, maxval=1.0)
        return core.collect(s, ts, hp, a, k_r)[0], None

    if c.normalize_obs:
        ts = ts.replace(obs_stats=nn.update_obs_stats(ts.obs_stats, ts.env_state.obs))
    if c.warmup_steps == 0:  # (no scan of length 0: its env step would still be compiled)
        return ts
    return jax.lax.scan(warm, ts, jax.random.split(k_warm, c.warmup_steps))[0]


def with_actor(s: Setup, ts: TrainState, actor, hp: Hyper) -> TrainState:
    """``ts`` with ``actor`` as its policy (e.g. a behaviour-cloned one): the target actor set
    to it and a fresh Adam state for it."""
    return ts.replace(
        actor=actor, target_actor=actor, actor_opt=core.with_lr(s.adam.init(actor), hp.lr_actor)
    )


def initial_actor(s: Setup, key: jax.Array) -> dict:
    """The actor parameters :func:`init` starts from (the warm-up leaves them unchanged)."""
    k_net = jax.random.split(key, 4)[0]  # as in init
    return nn.init_params(s.nets, k_net, s.env.obs_size, s.env.action_size)[0]


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """Per-seed keys: seed i of a vmapped run equals seed ``seed + i`` run alone."""
    return _fold_seeds(np.arange(seed, seed + num_seeds, dtype=np.int32))


@jax.jit
def _fold_seeds(seeds: jax.Array) -> jax.Array:  # one small program, not one per eager op
    root = jax.random.PRNGKey(0)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(seeds)


def epoch(s: Setup, step: StepFn, ts: TrainState, hp: Hyper):
    """``steps_per_epoch`` vector steps; returns the state and the epoch's mean metrics."""
    ts, (out, fin) = jax.lax.scan(functools.partial(step, s, hp), ts, None, length=s.config.steps_per_epoch)
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
    stats = core.obs_stats(s, ts)
    return s.env.evaluate(lambda obs: act(s, ts.actor, stats, obs))


def train(s: Setup, step: StepFn, key: jax.Array, hp: Hyper):
    """The whole run fused into one program: ``(state, per-epoch metrics, per-epoch eval)``."""

    def body(ts, _):
        ts, m = epoch(s, step, ts, hp)
        return ts, (m, evaluate(s, ts))

    ts, (m, ev) = jax.lax.scan(body, init(s, key, hp), None, s.config.epochs)
    return ts, m, ev


class Trainer(NamedTuple):
    """The trainer's functions bound to one :class:`~ttd3_jax.td3.core.Setup` and step;
    ``vmap`` them over seeds / hyperparameters."""

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
    def nets(self) -> nn.Networks:
        return self.setup.nets


def make_trainer(c: TrainConfig, env: EnvSpec) -> Trainer:
    """The pure training functions for config ``c`` on ``env``; the actor update is chosen
    here, once, and so is checked (the one place) that the model-based one has a
    differentiable env."""
    if c.model_horizon > 0 and not env.differentiable:
        why = "0 for this env: gradients do not flow through its step (> 0 back-propagates through it)"
        checks.fail("model_horizon", why, c.model_horizon)
    step = model_based.vector_step if c.model_horizon > 0 else dpg.vector_step
    s = make_setup(c, env)
    p = functools.partial
    return Trainer(setup=s, init=p(init, s), epoch=p(epoch, s, step), evaluate=p(evaluate, s),
                   train=p(train, s, step))  # fmt: skip
