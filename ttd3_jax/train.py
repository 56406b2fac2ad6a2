"""T-TD3 / TD3 trainer: parallel envs, device replay buffer and updates in one ``lax.scan``.

Read one transition top to bottom: :func:`_collect` steps the vmapped envs and
builds a :class:`~ttd3_jax.buffer.Transition` (true next observation, ``terminated``
apart from time-limit truncation) before auto-resetting finished envs;
:func:`ttd3_jax.buffer.insert` writes it; :func:`_update` samples a minibatch and
takes the critic step (:func:`ttd3_jax.losses.critic_loss`), the σ update
(:mod:`ttd3_jax.noise`) and, every ``policy_delay`` updates, the actor step and
the Polyak target update.

With ``model_horizon`` H > 0 (the ``fast`` preset; not in the paper) the actor step is
:func:`_model_actor_step` instead: :func:`_model_rollout` steps the envs H times with the
current policy, the gradient of the rollout's return flows back through the simulator
into the actor, and the rollout's transitions are stored for the critic updates.

Static settings (shapes, loop lengths, algorithm switches) live in the frozen
:class:`TrainConfig`; numeric hyperparameters live in the :class:`Hyper` pytree, so a
sweep over seeds and hyperparameters is a ``vmap`` of :meth:`Trainer.train`.

CLI: ``python -m ttd3_jax.train --help``.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ttd3_jax import buffer as rb
from ttd3_jax import noise as nz
from ttd3_jax import normalize as nrm
from ttd3_jax.env import PRESETS as ENV_PRESETS
from ttd3_jax.env import TrackingEnv, make_config, parse_overrides
from ttd3_jax.evaluate import Controller, evaluate_on_tracks, test_tracks
from ttd3_jax.losses import actor_loss, critic_loss
from ttd3_jax.networks import CRITICS, Networks, init_params, make_networks, twin_q
from ttd3_jax.trajectories import validation_tracks

QUADROTOR = "quadrotor"
BRAX_ENVS = (
    "ant", "halfcheetah", "hopper", "humanoid", "humanoidstandup", "inverted_pendulum",
    "inverted_double_pendulum", "pusher", "reacher", "swimmer", "walker2d",
)  # fmt: skip
ALGOS = ("ttd3", "td3")
TARGET_NOISES = ("fixed", "shared_sigma")
BACKENDS = ("mjx", "generalized", "positional", "spring")
LR_SCHEDULES = ("constant", "linear", "cosine")


@struct.dataclass
class Hyper:
    """Numeric hyperparameters: pytree leaves, so ``vmap`` sweeps over them (spec §2.4)."""

    gamma: float = 0.99  # discount per env step
    tau: float = 5e-4  # Polyak factor (A6: 1 - 0.9995)
    lr_actor: float = 3e-4  # Adam
    lr_critic: float = 3e-4  # Adam
    sigma: float = 0.1  # TD3 exploration std (constant schedule; linear start)
    sigma_end: float = 0.0  # linear schedule end value
    beta: float = 0.08  # T-TD3 weight of the time term
    lam: float = 0.01  # T-TD3 decay rate per unit of t
    u_max: float = 1.0  # action bound used by the σ formula
    target_sigma: float = 0.2  # σ̃, target-policy smoothing std
    target_clip: float = 0.1  # c, target-policy smoothing clip
    reward_scale: float = 1.0  # rewards are stored times this (keeps Q values O(1..100))
    # CAPS weights (0 = TD3).  The CAPS terms are compiled in only when the TrainConfig's own
    # hp has one of them non-zero (``uses_caps``): a sweep over them starts from such a config.
    smooth_time: float = 0.0  # CAPS weight on ||π(s) − π(s')||² in the actor loss
    smooth_space: float = 0.0  # CAPS weight on ||π(s) − π(s + smooth_sigma ξ)||²
    smooth_sigma: float = 0.05  # std of the CAPS state perturbation, in network-input units
    # model-based actor gradient (``TrainConfig.model_horizon`` > 0; not in the paper)
    model_bootstrap: float = 1.0  # weight of min_i Q_i at the rollout's horizon (0 = pure rollout)
    model_grad_clip: float = 1.0  # global-norm clip of the back-propagated actor gradient


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration. Counts are env transitions unless stated."""

    env: str = QUADROTOR  # "quadrotor" or a Brax env name
    env_preset: str = "paper"  # quadrotor env preset ("paper" | "practical")
    hover_centered_thrust: bool = False  # quadrotor: action a0 = 0 means hover thrust (spec O2)
    # quadrotor: EnvConfig fields set on top of env_preset, each "name=value" with value in
    # JSON (else a plain string), e.g. obs_frame=heading e_max=1.5 'tracks={"train_scale": [0.05, 1]}'
    env_overrides: tuple[str, ...] = ()
    backend: str = "mjx"  # Brax physics backend
    algo: str = "ttd3"  # "ttd3" (time-attenuating σ) | "td3" (constant σ)
    num_envs: int = 20  # M, parallel training envs
    total_transitions: int = 3_000_000
    warmup_transitions: int = 25_000  # uniform-random actions before learning
    buffer_size: int = 1_000_000  # rounded up to a multiple of num_envs
    batch_size: int = 256
    updates_per_step: int = 20  # G, gradient updates per vector env step
    policy_delay: int = 2  # d
    # 0: the actor follows ∂Q₁/∂a (TD3, the paper).  H >= 1 (quadrotor only, not in the paper):
    # every vector step rolls the envs H steps with the current policy (plus exploration
    # noise), back-propagates Σ γ^k r_k + γ^H min_i Q_i(s_H, π(s_H)) through the simulator into
    # the actor, and stores the H·num_envs transitions for the usual TD3 critic updates.
    model_horizon: int = 0
    n_step: int = 1  # n-step returns in the critic target (1 = TD3 as published)
    lr_schedule: str = "constant"  # "linear" / "cosine": learning rates decay to 0 over the run
    hidden: tuple[int, ...] = (256, 256)
    critic: str = "mlp"  # "mlp" (the paper) | "advantage": Q = V(s) + A(s, a) − A(s, π(s))
    critic_layer_norm: bool = False  # LayerNorm in the critics' hidden layers (not in the paper)
    normalize_obs: bool = False  # running mean/std normalisation of observations (nets' input)
    epochs: int = 50  # progress / eval / checkpoint points
    eval_episodes: int = 10  # Brax envs: deterministic episodes per evaluation
    episode_length: int = 1000  # Brax envs: steps per episode
    noise: nz.NoiseConfig = nz.NoiseConfig()
    target_noise: str = "fixed"  # A4: σ̃ fixed, or "shared_sigma" (uses the current σ)
    hp: Hyper = Hyper()
    seed: int = 0
    num_seeds: int = 1  # seeds run side by side with vmap: seed, seed+1, ...

    def __post_init__(self):
        validate(self)

    # derived loop lengths ------------------------------------------------------------
    @property
    def env_steps_per_step(self) -> int:
        """Env steps per vector step after warm-up (``model_horizon``, or 1)."""
        return max(1, self.model_horizon)

    @property
    def warmup_steps(self) -> int:
        """Vector env steps of random warm-up."""
        return -(-self.warmup_transitions // self.num_envs)

    @property
    def steps_per_epoch(self) -> int:
        """Vector steps (each ``env_steps_per_step`` env steps, then G updates) per compiled epoch."""
        left = self.total_transitions // self.num_envs - self.warmup_steps
        return max(1, left // (self.env_steps_per_step * self.epochs))

    @property
    def buffer_capacity(self) -> int:
        return -(-self.buffer_size // self.num_envs) * self.num_envs


def validate(c: TrainConfig) -> None:
    """Raise ``ValueError`` naming the bad field; runs before anything is compiled."""

    def need(ok, msg):
        if not ok:
            raise ValueError(msg)

    need(
        c.env == QUADROTOR or c.env in BRAX_ENVS,
        f"env must be {QUADROTOR!r} or one of {BRAX_ENVS}, got {c.env!r}",
    )
    need(c.env_preset in ENV_PRESETS, f"env_preset must be one of {ENV_PRESETS}, got {c.env_preset!r}")
    if c.env_overrides:
        need(c.env == QUADROTOR, f"env_overrides set quadrotor env fields; env {c.env!r} has none")
        try:
            quad_env_config(c)  # parses and validates every override
        except (TypeError, ValueError) as e:
            raise ValueError(f"env_overrides {list(c.env_overrides)}: {e}") from None
    need(c.backend in BACKENDS, f"backend must be one of {BACKENDS}, got {c.backend!r}")
    need(c.algo in ALGOS, f"algo must be one of {ALGOS}, got {c.algo!r}")
    need(c.critic in CRITICS, f"critic must be one of {CRITICS}, got {c.critic!r}")
    need(c.lr_schedule in LR_SCHEDULES, f"lr_schedule must be one of {LR_SCHEDULES}, got {c.lr_schedule!r}")
    need(
        c.target_noise in TARGET_NOISES,
        f"target_noise must be one of {TARGET_NOISES}, got {c.target_noise!r}",
    )
    for name in ("num_envs", "total_transitions", "buffer_size", "batch_size", "updates_per_step",
                 "policy_delay", "n_step", "epochs", "eval_episodes", "episode_length",
                 "num_seeds"):  # fmt: skip
        v = getattr(c, name)
        need(
            isinstance(v, int) and not isinstance(v, bool) and v >= 1,
            f"{name} must be an integer >= 1, got {v!r}",
        )
    need(isinstance(c.model_horizon, int) and not isinstance(c.model_horizon, bool) and c.model_horizon >= 0,
         f"model_horizon must be an integer >= 0, got {c.model_horizon!r}")  # fmt: skip
    if c.model_horizon > 0:
        need(c.env == QUADROTOR,
             f"model_horizon > 0 back-propagates through the quadrotor simulator; env {c.env!r} "
             "needs model_horizon 0")  # fmt: skip
        need(not uses_caps(c), "the CAPS terms (hp.smooth_time, hp.smooth_space) need model_horizon 0")
    need(isinstance(c.warmup_transitions, int) and c.warmup_transitions >= 0,
         f"warmup_transitions must be an integer >= 0, got {c.warmup_transitions!r}")  # fmt: skip
    need(isinstance(c.seed, int) and c.seed >= 0, f"seed must be an integer >= 0, got {c.seed!r}")
    need(len(c.hidden) >= 1 and all(isinstance(h, int) and h >= 1 for h in c.hidden),
         f"hidden must be one or more layer widths >= 1, got {c.hidden!r}")  # fmt: skip
    need(
        c.batch_size <= c.buffer_size, f"batch_size ({c.batch_size}) must be <= buffer_size ({c.buffer_size})"
    )
    need(c.warmup_transitions > (c.n_step - 1) * c.num_envs,
         f"warmup_transitions ({c.warmup_transitions}) must exceed (n_step - 1) * num_envs "
         f"({(c.n_step - 1) * c.num_envs}) so that n-step windows exist when learning starts")  # fmt: skip
    need(c.warmup_transitions >= c.batch_size,
         f"warmup_transitions ({c.warmup_transitions}) must be >= batch_size ({c.batch_size}) so the "
         "first minibatch is drawn from a filled buffer")  # fmt: skip
    budget = (c.total_transitions // c.num_envs - c.warmup_steps) // c.env_steps_per_step
    need(budget >= c.epochs,
         f"total_transitions ({c.total_transitions}) leaves {max(budget, 0)} vector steps after warm-up, "
         f"fewer than epochs ({c.epochs}); raise total_transitions or lower epochs")  # fmt: skip
    h = c.hp
    for name in ("gamma", "tau"):
        v = getattr(h, name)
        need(0 < v <= 1 if name == "tau" else 0 <= v < 1,
             f"hp.{name} must be in {'(0, 1]' if name == 'tau' else '[0, 1)'}, got {v!r}")  # fmt: skip
    for name in ("lr_actor", "lr_critic", "u_max", "reward_scale", "model_grad_clip"):
        need(getattr(h, name) > 0, f"hp.{name} must be > 0, got {getattr(h, name)!r}")
    for name in ("sigma", "sigma_end", "lam", "target_sigma", "target_clip", "smooth_time", "smooth_space",
                 "smooth_sigma", "model_bootstrap"):  # fmt: skip
        need(getattr(h, name) >= 0, f"hp.{name} must be >= 0, got {getattr(h, name)!r}")
    need(0 <= h.beta <= 1, f"hp.beta must be in [0, 1], got {h.beta!r}")


def with_algo(c: TrainConfig, algo: str) -> TrainConfig:
    """T-TD3 and TD3 differ only in the exploration schedule."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    schedule = "time_attenuating" if algo == "ttd3" else "constant"
    return dataclasses.replace(c, algo=algo, noise=dataclasses.replace(c.noise, schedule=schedule))


# --------------------------------------------------------------------------- state


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


class EnvSpec(NamedTuple):
    env: object  # single-env object with Brax reset/step
    obs_size: int
    action_size: int
    episode_length: int  # transitions per nominal episode (L_nom)


def make_env(c: TrainConfig) -> EnvSpec:
    """The training env: the quadrotor tracking env, or a Brax env with a time limit."""
    if c.env == QUADROTOR:
        env = TrackingEnv(quad_env_config(c))
        return EnvSpec(env, env.observation_size, env.action_size, env.episode_length)
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from brax import envs as brax_envs
        from brax.envs.wrappers.training import EpisodeWrapper

        env = brax_envs.get_environment(c.env, backend=c.backend)
    env = EpisodeWrapper(env, c.episode_length, action_repeat=1)
    return EnvSpec(env, env.observation_size, env.action_size, c.episode_length)


def uses_caps(c: TrainConfig) -> bool:
    """Whether the actor loss carries the CAPS terms (static): when ``c.hp`` sets a non-zero
    ``smooth_time`` or ``smooth_space``.  An ``hp`` passed to the trainer's functions
    (a sweep) cannot turn them on: its values are traced."""
    return c.hp.smooth_time != 0 or c.hp.smooth_space != 0


# set by the run, not by an override: the training env draws the training mixture (evaluation
# picks its own tracks), and the thrust centring has its own TrainConfig field
_NOT_OVERRIDABLE = {"track": "training draws the training mixture", "los_seed": "training draws the "
                    "training mixture", "hover_centered_thrust": "use hover_centered_thrust"}  # fmt: skip


def env_override_items(c: TrainConfig) -> dict:
    """``c.env_overrides`` parsed: ``{field: value}`` in the types of ``EnvConfig``."""
    return parse_overrides(c.env_overrides, _NOT_OVERRIDABLE)


def env_override(name: str, value) -> str:
    """The ``env_overrides`` entry that sets ``EnvConfig.name`` to ``value`` (nested configs
    as objects of their fields)."""
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    return f"{name}={json.dumps(value)}"


def quad_env_config(c: TrainConfig):
    """The quadrotor training env's config for this run: ``env_preset``, the thrust centring
    and ``env_overrides``."""
    return make_config(c.env_preset, hover_centered_thrust=c.hover_centered_thrust, **env_override_items(c))


def _adam(lr):
    return optax.inject_hyperparams(optax.adam)(learning_rate=lr)


def with_actor(ts: TrainState, actor, hp: Hyper) -> TrainState:
    """``ts`` with ``actor`` as its policy (e.g. a behaviour-cloned one): the target actor set
    to it and a fresh Adam state for it."""
    return ts.replace(actor=actor, target_actor=actor, actor_opt=_adam(hp.lr_actor).init(actor))


def _with_lr(opt_state, lr):
    """The optimiser state with its (injected) learning rate set to ``lr``."""
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def lr_fraction(c: TrainConfig, n_upd: jax.Array) -> jax.Array:
    """Learning-rate multiplier after ``n_upd`` updates under ``c.lr_schedule``."""
    if c.lr_schedule == "constant":
        return jnp.ones(())
    x = jnp.clip(n_upd / max(1, c.steps_per_epoch * c.epochs * c.updates_per_step), 0.0, 1.0)
    return 1.0 - x if c.lr_schedule == "linear" else 0.5 * (1.0 + jnp.cos(jnp.pi * x))


def _where(mask, a, b):
    """Per-env select between two batched pytrees (mask (n,))."""
    return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


# --------------------------------------------------------------------------- trainer


class Trainer(NamedTuple):
    """Pure functions of one seed's state; ``vmap`` them over seeds / hyperparameters."""

    config: TrainConfig
    spec: EnvSpec
    nets: Networks
    init: Callable  # (key, hp) -> TrainState, buffer filled by the random warm-up
    epoch: Callable  # (ts, hp) -> (ts, metrics): steps_per_epoch vector steps + updates
    evaluate: Callable  # (ts) -> eval metrics (deterministic policy, separate envs)
    train: Callable  # (key, hp) -> (ts, per-epoch metrics, per-epoch eval): fully fused
    model_loss: Callable  # (actor, ts, hp, key) -> (loss, aux): the model-based actor objective


PROGRESS_TICKS = 50  # host progress callbacks per epoch (when ``on_progress`` is given)


def make_trainer(c: TrainConfig, on_progress: Callable[[int], None] | None = None) -> Trainer:
    """Build the pure training functions for config ``c`` (see module docstring).

    ``on_progress(vector_steps_done_in_epoch)``, if given, is called from the compiled
    epoch about ``PROGRESS_TICKS`` times per epoch (a host callback; values unchanged)."""
    spec = make_env(c)
    env, n = spec.env, c.num_envs
    noise_cfg = c.noise
    nets = make_networks(spec.action_size, c.hidden, c.critic, c.critic_layer_norm)
    v_reset, v_step = jax.vmap(env.reset), jax.vmap(env.step)

    def stats(ts: TrainState):
        return ts.obs_stats if c.normalize_obs else None

    def policy(ts: TrainState, obs):
        return nets.actor.apply(ts.actor, nrm.apply(stats(ts), obs))

    def _env_step(env_state, ep_return, hp: Hyper, actions: jax.Array, key: jax.Array):
        """Step all envs with ``actions`` and auto-reset finished ones (fresh track and start).

        Returns the new env state, the :class:`~ttd3_jax.buffer.Transition` (true next
        observation, ``terminated`` apart from truncation), the raw next state (before the
        reset), the running episode returns, and the sum and count of finished returns."""
        nxt = v_step(env_state, actions)
        trunc = nxt.info["truncation"]
        terminated = nxt.done * (1.0 - trunc)
        tr = rb.Transition(
            obs=env_state.obs,
            action=actions,
            reward=hp.reward_scale * nxt.reward,
            next_obs=nxt.obs,
            terminated=terminated,
            done=nxt.done,
        )
        done = nxt.done > 0
        ep_return = ep_return + nxt.reward
        finished = (jnp.sum(jnp.where(done, ep_return, 0.0)), jnp.sum(done))
        new_state = jax.lax.cond(
            jnp.any(done), lambda: _where(done, v_reset(jax.random.split(key, n)), nxt), lambda: nxt
        )
        return new_state, tr, nxt, jnp.where(done, 0.0, ep_return), finished

    def _store(ts: TrainState, tr: rb.Transition) -> TrainState:
        """Insert one env batch of transitions; update the observation statistics."""
        return ts.replace(
            obs_stats=nrm.update(ts.obs_stats, tr.next_obs) if c.normalize_obs else ts.obs_stats,
            buffer=rb.insert(ts.buffer, tr),
            n_tr=ts.n_tr + n,
        )

    def _collect(ts: TrainState, hp: Hyper, actions: jax.Array, key: jax.Array):
        """Step all envs with ``actions``; store transitions; auto-reset finished envs."""
        env_state, tr, _, ep_return, (finished_sum, finished_n) = _env_step(
            ts.env_state, ts.ep_return, hp, actions, key
        )
        ts = _store(ts.replace(env_state=env_state, ep_return=ep_return), tr)
        return ts, finished_sum, finished_n

    def _init(key, hp: Hyper) -> TrainState:
        k_net, k_env, k_warm, k_run = jax.random.split(key, 4)
        actor, critic = init_params(nets, k_net, spec.obs_size, spec.action_size)
        ts = TrainState(
            actor=actor,
            critic=critic,
            target_actor=actor,
            target_critic=critic,
            actor_opt=_adam(hp.lr_actor).init(actor),
            critic_opt=_adam(hp.lr_critic).init(critic),
            buffer=rb.init(c.buffer_capacity, spec.obs_size, spec.action_size),
            env_state=v_reset(jax.random.split(k_env, n)),
            ep_return=jnp.zeros(n),
            obs_stats=nrm.init(spec.obs_size),
            noise=nz.init(noise_cfg, hp),
            key=k_run,
            n_tr=jnp.zeros((), jnp.int32),
            n_upd=jnp.zeros((), jnp.int32),
        )

        def warm(ts, k):  # spec A8: uniform-random actions before learning
            k_a, k_r = jax.random.split(k)
            a = jax.random.uniform(k_a, (n, spec.action_size), minval=-1.0, maxval=1.0)
            return _collect(ts, hp, a, k_r)[0], None

        if c.normalize_obs:
            ts = ts.replace(obs_stats=nrm.update(ts.obs_stats, ts.env_state.obs))
        ts, _ = jax.lax.scan(warm, ts, jax.random.split(k_warm, c.warmup_steps))
        return ts

    caps = uses_caps(c)

    def _apply_actor_grad(ts: TrainState, hp: Hyper, g, frac) -> TrainState:
        """One Adam step of the actor along ``g`` at learning rate ``hp.lr_actor · frac``."""
        actor_opt = _with_lr(ts.actor_opt, hp.lr_actor * frac)
        upd, actor_opt = _adam(hp.lr_actor).update(g, actor_opt, ts.actor)
        return ts.replace(actor=optax.apply_updates(ts.actor, upd), actor_opt=actor_opt)

    def _polyak(ts: TrainState, hp: Hyper) -> TrainState:
        """Move both target networks a step ``hp.tau`` towards the current ones."""
        return ts.replace(
            target_actor=optax.incremental_update(ts.actor, ts.target_actor, hp.tau),
            target_critic=optax.incremental_update(ts.critic, ts.target_critic, hp.tau),
        )

    def _update(ts: TrainState, hp: Hyper, key: jax.Array, j: jax.Array):
        """One critic step, the σ update and, every d-th update, the actor + target step.

        ``j`` is this update's index within its vector step (from the scan, so it is not
        batched under a seed ``vmap``).  When G is a multiple of d every vector step starts
        at n_upd ≡ 0 (mod d), so "every d-th update" is decided by ``j`` alone and the
        ``lax.cond`` stays a branch under ``vmap`` instead of becoming a select."""
        k_batch, k_target, k_smooth = jax.random.split(key, 3)
        if c.n_step == 1:
            batch, nstep = rb.sample(ts.buffer, k_batch, c.batch_size), None
        else:
            batch, nstep = rb.sample_nstep(ts.buffer, k_batch, c.batch_size, c.n_step, n, hp.gamma)
        if c.normalize_obs:
            batch = batch.replace(
                obs=nrm.apply(ts.obs_stats, batch.obs), next_obs=nrm.apply(ts.obs_stats, batch.next_obs)
            )
            if nstep is not None:
                nstep = nstep.replace(next_obs=nrm.apply(ts.obs_stats, nstep.next_obs))
        target_std = hp.target_sigma if c.target_noise == "fixed" else nz.std(noise_cfg, ts.noise.sigma)
        targets = (ts.target_actor, ts.target_critic)
        (c_loss, aux), grads = jax.value_and_grad(critic_loss, has_aux=True)(
            ts.critic, nets, *targets, batch, k_target, hp, target_std, ts.actor, nstep
        )
        frac = lr_fraction(c, ts.n_upd)
        critic_opt = _with_lr(ts.critic_opt, hp.lr_critic * frac)
        updates, critic_opt = _adam(hp.lr_critic).update(grads, critic_opt, ts.critic)
        critic = optax.apply_updates(ts.critic, updates)
        n_upd = ts.n_upd + 1
        noise = nz.update(
            noise_cfg, hp, ts.noise, batch.reward, ts.n_tr, n_upd, c.total_transitions, spec.episode_length
        )
        ts = ts.replace(critic=critic, critic_opt=critic_opt, noise=noise, n_upd=n_upd)

        def actor_step(ts):
            if c.model_horizon > 0:  # the rollout already updated the actor: targets only
                return _polyak(ts, hp), jnp.full((), jnp.nan)
            a_loss, g = jax.value_and_grad(actor_loss)(ts.actor, nets, ts.critic, batch, k_smooth, hp, caps)
            return _polyak(_apply_actor_grad(ts, hp, g, frac), hp), a_loss

        if c.updates_per_step % c.policy_delay == 0:
            due = (j + 1) % c.policy_delay == 0
        else:
            due = n_upd % c.policy_delay == 0
        ts, a_loss = jax.lax.cond(due, actor_step, lambda ts: (ts, jnp.full((), jnp.nan)), ts)
        return ts, (c_loss, a_loss, aux["q_mean"])

    def _model_rollout(actor, ts: TrainState, hp: Hyper, key: jax.Array):
        """``model_horizon`` steps of all envs under the noisy current policy, differentiable in
        ``actor``: returns −mean_envs [Σ_{k<H} γ^k r_k + γ^H min_i Q_i(s_H, π(s_H))] (scaled
        rewards; an episode's return stops where it ends, bootstrapping with γ min_i Q_i at the
        true final observation if it was truncated), and the rollout's transitions (H, n, ...)
        with the env state and running returns after it.  The critics are held fixed."""
        x_stats, critic = stats(ts), jax.lax.stop_gradient(ts.critic)
        std = nz.std(noise_cfg, ts.noise.sigma)

        def q_min(obs):  # min_i Q_i(s, π(s)), (n,)
            x = nrm.apply(x_stats, obs)
            a = nets.actor.apply(actor, x)
            return jnp.min(twin_q(nets, critic, x, a, a), axis=0)

        def body(carry, k):
            s, ep_ret, alive, disc, ret, fin = carry
            k_noise, k_reset = jax.random.split(k)
            pi = nets.actor.apply(actor, nrm.apply(x_stats, s.obs))
            a = jnp.clip(pi + std * jax.random.normal(k_noise, pi.shape), -1.0, 1.0)
            s, tr, nxt, ep_ret, f = _env_step(s, ep_ret, hp, a, k_reset)
            boot = hp.gamma * nxt.info["truncation"] * q_min(nxt.obs)
            ret = ret + disc * alive * (tr.reward + hp.model_bootstrap * boot)
            fin = (fin[0] + f[0], fin[1] + f[1])
            carry = (s, ep_ret, alive * (1.0 - tr.done), disc * hp.gamma, ret, fin)
            return carry, jax.lax.stop_gradient(tr)

        zero = jnp.zeros(())
        carry = (ts.env_state, ts.ep_return, jnp.ones(n), jnp.ones(()), jnp.zeros(n), (zero, zero))
        carry, trs = jax.lax.scan(body, carry, jax.random.split(key, c.model_horizon))
        s, ep_ret, alive, disc, ret, fin = carry
        ret = ret + disc * alive * hp.model_bootstrap * q_min(s.obs)
        return -jnp.mean(ret), (jax.lax.stop_gradient((s, ep_ret)), trs, fin)

    def _model_actor_step(ts: TrainState, hp: Hyper, key: jax.Array):
        """One actor update from a differentiable rollout (``model_horizon`` > 0); its
        transitions go to the buffer and the envs continue from where it ended."""
        grad = jax.value_and_grad(_model_rollout, has_aux=True)
        (a_loss, ((env_state, ep_return), trs, fin)), g = grad(ts.actor, ts, hp, key)
        norm = jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree.leaves(g)))
        scale = jnp.minimum(1.0, hp.model_grad_clip / (norm + 1e-12))
        g = jax.tree.map(lambda x: x * scale, g)
        ts = _apply_actor_grad(ts, hp, g, lr_fraction(c, ts.n_upd))
        ts = ts.replace(env_state=env_state, ep_return=ep_return)
        ts = jax.lax.scan(lambda t, tr: (_store(t, tr), None), ts, trs)[0]
        return ts, a_loss, fin

    def _vector_step(ts: TrainState, hp: Hyper):
        key, k_noise, k_reset, k_upd = jax.random.split(ts.key, 4)
        ts = ts.replace(key=key)
        if c.model_horizon > 0:
            ts, m_loss, (ret_sum, ret_n) = _model_actor_step(ts, hp, k_noise)
        else:
            obs = ts.env_state.obs
            std = nz.std(noise_cfg, ts.noise.sigma)
            a = policy(ts, obs) + std * jax.random.normal(k_noise, (n, spec.action_size))
            ts, ret_sum, ret_n = _collect(ts, hp, jnp.clip(a, -1.0, 1.0), k_reset)
        ts, (c_loss, a_loss, q) = jax.lax.scan(
            lambda t, x: _update(t, hp, *x),
            ts,
            (jax.random.split(k_upd, c.updates_per_step), jnp.arange(c.updates_per_step)),
        )
        a_loss = m_loss if c.model_horizon > 0 else jnp.nanmean(a_loss)
        out = dict(critic_loss=jnp.mean(c_loss), actor_loss=a_loss, q_mean=jnp.mean(q))
        return ts, (out, ret_sum, ret_n)

    every = max(1, c.steps_per_epoch // PROGRESS_TICKS)

    def _tick(i):
        if on_progress is not None:
            jax.lax.cond((i + 1) % every == 0, lambda: jax.debug.callback(on_progress, i + 1), lambda: None)

    def _epoch(ts: TrainState, hp: Hyper):
        def body(t, i):
            _tick(i)
            return _vector_step(t, hp)

        ts, (out, ret_sum, ret_n) = jax.lax.scan(body, ts, jnp.arange(c.steps_per_epoch))
        m = {k: jnp.nanmean(v) for k, v in out.items()}
        n_ep = jnp.sum(ret_n)
        m.update(
            train_return=jnp.where(n_ep > 0, jnp.sum(ret_sum) / jnp.maximum(n_ep, 1), jnp.nan),
            episodes=n_ep.astype(jnp.float32),
            sigma=ts.noise.sigma,
            env_steps=ts.n_tr.astype(jnp.float32),
        )
        return ts, m

    def _evaluate(ts: TrainState):
        if c.env == QUADROTOR:
            return _eval_quad(c, nets, ts.actor, stats(ts))
        return _eval_brax(c, spec, nets, ts.actor, stats(ts))

    def _train(key, hp: Hyper):
        ts = _init(key, hp)

        def body(ts, _):
            ts, m = _epoch(ts, hp)
            return ts, (m, _evaluate(ts))

        ts, (m, ev) = jax.lax.scan(body, ts, None, c.epochs)
        return ts, m, ev

    return Trainer(c, spec, nets, _init, _epoch, _evaluate, _train, _model_rollout)


def policy_controller(nets: Networks, actor_params, obs_stats: nrm.ObsStats | None = None) -> Controller:
    """The deterministic policy as an :class:`~ttd3_jax.evaluate.Controller` (``obs_stats``:
    the run's observation normaliser, ``None`` when it did not normalise)."""

    def act(carry, s):
        return nets.actor.apply(actor_params, nrm.apply(obs_stats, s.obs)), carry

    return Controller(init=lambda s: (), act=act)


def _eval_quad(c: TrainConfig, nets: Networks, actor, obs_stats) -> dict:
    """Spiral-RT and LOS-RT (seed 0) with the paper's evaluation protocol (spec §2.5),
    both in one vmapped closed loop; plus ``val_tracking_error``, the mean Σ‖e‖ over the 10
    validation tracks (spec T8), the only figure used to select a policy."""
    base = quad_env_config(c)
    ctrl = policy_controller(nets, actor, obs_stats)
    env = TrackingEnv(base.for_eval("los_rt"))
    m = evaluate_on_tracks(env, ctrl, test_tracks(env))
    out = {}
    for i, name in enumerate(("spiral", "los")):
        out.update({f"{name}_{k}": v[i] for k, v in m.items()})
    venv = TrackingEnv(base.for_eval("validation"))
    val = validation_tracks(base.tracks, base.dt, base.horizon_steps, venv.num_segments)
    out["val_tracking_error"] = jnp.mean(evaluate_on_tracks(venv, ctrl, val)["tracking_error"])
    return out


def _eval_brax(c: TrainConfig, spec: EnvSpec, nets: Networks, actor, obs_stats) -> dict:
    """Mean undiscounted return of ``eval_episodes`` deterministic episodes (fixed keys)."""
    env = spec.env
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(12345), c.eval_episodes))

    def body(carry):
        t, s, ret, alive = carry
        s = jax.vmap(env.step)(s, nets.actor.apply(actor, nrm.apply(obs_stats, s.obs)))
        # where, not alive * reward: a finished episode keeps stepping and its physics may
        # blow up (MJX inverted_double_pendulum does), and 0 * nan is nan
        ret = ret + jnp.where(alive > 0, s.reward, 0.0)
        return t + 1, s, ret, alive * (1.0 - s.done)

    def running(carry):  # stop early once every episode has ended (falls end them early)
        t, _, _, alive = carry
        return (t < c.episode_length) & jnp.any(alive > 0)

    ones = jnp.ones(c.eval_episodes)
    _, _, ret, _ = jax.lax.while_loop(running, body, (jnp.zeros((), jnp.int32), s, 0.0 * ones, ones))
    return {"eval_return": jnp.mean(ret)}


def initial_actor(t: Trainer, key: jax.Array) -> dict:
    """The actor parameters ``t.init(key, hp)`` starts from, without the warm-up (which
    leaves them unchanged): the policy evaluated at step 0 of a run."""
    k_net = jax.random.split(key, 4)[0]  # as in make_trainer's _init
    return init_params(t.nets, k_net, t.spec.obs_size, t.spec.action_size)[0]


def evaluate_actor(t: Trainer, actor, obs_stats: nrm.ObsStats | None = None) -> dict:
    """``t.evaluate`` for bare actor parameters (``obs_stats``: the run's normaliser, if any)."""
    c = t.config
    if c.env == QUADROTOR:
        return _eval_quad(c, t.nets, actor, obs_stats)
    return _eval_brax(c, t.spec, t.nets, actor, obs_stats)


def seed_keys(c: TrainConfig) -> jax.Array:
    """Per-seed keys: seed i of a vmapped run equals ``--seed seed+i`` run alone."""
    return jax.vmap(lambda s: jax.random.fold_in(jax.random.PRNGKey(0), s))(
        jnp.arange(c.seed, c.seed + c.num_seeds)
    )


def buffer_bytes(c: TrainConfig, obs_size: int, action_size: int) -> int:
    """Replay memory of the whole run (all seeds), in bytes."""
    return c.num_seeds * c.buffer_capacity * rb.transition_bytes(obs_size, action_size)


def preset(name: str, **overrides) -> TrainConfig:
    """Named training configurations.

    ``paper``: the published quadrotor settings (spec §2.4), 3e6 transitions.
    ``fast``: quadrotor with the ``practical`` env (10 ms actions, 50 ms look-ahead,
    track-frame observation), hover-centred thrust, running observation normalisation,
    64-64 networks, 64 envs, rewards scaled by 0.01, and (not in the paper) a model-based
    actor update: 0.5 s rollouts (``model_horizon=50``) back-propagated through the
    simulator, actor lr 1e-3.  The twin critics are still trained by TD3 but the actor does
    not use them (``model_bootstrap=0``; with them at the horizon it learns worse,
    docs/results.md).  About 2 minutes on 2 CPU cores; beats the paper's T-TD3 errors.
    ``fast_dpg``: ``fast`` with the paper's actor update (∂Q₁/∂a through the critic),
    450k transitions, 16 updates per 64-env step; it plateaus (docs/results.md).
    ``mujoco``: the MuJoCo protocol (spec §2.7): 1 env, 1 update per step, τ = 0.005,
    c = 0.5, 1e6 steps, L_nom = 1000.
    """
    if name == "paper":
        base = TrainConfig()
    elif name in ("fast", "fast_dpg"):
        base = TrainConfig(
            env_preset="practical",
            hover_centered_thrust=True,
            num_envs=64,
            total_transitions=450_000,
            warmup_transitions=10_000,
            buffer_size=450_000,
            batch_size=256,
            updates_per_step=16,
            hidden=(64, 64),
            normalize_obs=True,
            epochs=15,
            hp=Hyper(tau=0.005, reward_scale=0.01),
        )
        if name == "fast":
            base = dataclasses.replace(
                base,
                model_horizon=50,
                total_transitions=3_200_000,
                epochs=10,
                hp=base.hp.replace(lr_actor=1e-3, model_bootstrap=0.0),
            )
    elif name == "mujoco":
        base = TrainConfig(
            env="hopper",
            num_envs=1,
            total_transitions=1_000_000,
            warmup_transitions=25_000,
            buffer_size=1_000_000,
            updates_per_step=1,
            epochs=200,
            hp=Hyper(tau=0.005, target_clip=0.5),
        )
    else:
        raise ValueError(f"unknown training preset {name!r}; allowed: {PRESETS}")
    return dataclasses.replace(base, **overrides) if overrides else base


PRESETS = ("paper", "fast", "fast_dpg", "mujoco")


def total_epochs_transitions(c: TrainConfig) -> int:
    """Transitions actually collected by a run (the budget rounded to whole epochs)."""
    return (c.warmup_steps + c.steps_per_epoch * c.epochs * c.env_steps_per_step) * c.num_envs


def _finite_tree(tree) -> bool:
    return all(
        bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)
    )


# --------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    """``python -m ttd3_jax.train [--preset fast|paper|mujoco] [--algo ttd3|td3] [...]``."""
    import argparse
    import sys

    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="fast", choices=PRESETS)
    pre.add_argument("--out", default="runs")
    pre.add_argument("--resume", default=None)
    pre.add_argument("--compile-cache", default=None)
    known, rest = pre.parse_known_args(argv)
    from ttd3_jax.runner import TrainingDiverged, run, use_compile_cache

    if known.resume is not None and rest:
        print(f"error: --resume continues the saved config; remove {' '.join(rest)}", file=sys.stderr)
        return 2
    try:
        description = (
            f"Train T-TD3 or TD3 (preset {known.preset!r}; defaults below are that preset's). Also: "
            f"--preset {{{','.join(PRESETS)}}}, --out DIR (default runs), --resume RUN_DIR, "
            "--compile-cache DIR|none (XLA compilation cache; default ~/.cache/ttd3_jax/xla)."
        )
        if known.resume is None:
            # tyro reports a ValueError from TrainConfig validation itself and exits with status 2
            cfg = tyro.cli(TrainConfig, default=preset(known.preset), args=rest, description=description)
            if not any(a.startswith("--noise.schedule") for a in rest):
                cfg = with_algo(cfg, cfg.algo)
        cache = use_compile_cache(known.compile_cache)
        note = " (--compile-cache none turns it off)" if cache else ""
        print(f"XLA compilation cache: {cache or 'off'}{note}")
        if known.resume is not None:
            run(resume=known.resume)
            return 0
        run(cfg, out=known.out)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
