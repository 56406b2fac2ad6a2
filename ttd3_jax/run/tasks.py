"""The envs the trainer drives, each as a :class:`~ttd3_jax.td3.env_spec.EnvSpec` with its
own evaluation: the quadrotor tracking env and the Brax/MJX tasks.
"""

from __future__ import annotations

import contextlib
import io

import jax
import jax.numpy as jnp

from ttd3_jax.control.closed_loop import policy_controller, test_and_validation_metrics
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.td3.env_spec import EnvSpec

BRAX_ENVS = (
    "ant", "halfcheetah", "hopper", "humanoid", "humanoidstandup", "inverted_pendulum",
    "inverted_double_pendulum", "pusher", "reacher", "swimmer", "walker2d",
)  # fmt: skip
BACKENDS = ("mjx", "generalized", "positional", "spring")
EVAL_KEY = 12345  # Brax evaluation episodes start from fixed keys


def quadrotor(cfg: EnvConfig, track_rows: int | None = None) -> EnvSpec:
    """The tracking env of ``cfg``, evaluated on the test and validation tracks
    (:func:`~ttd3_jax.control.closed_loop.test_and_validation_metrics`); ``track_rows``: a
    reader's, which does not read users' training tracks (:class:`TrackingEnv`)."""
    env = TrackingEnv(cfg, track_rows=track_rows)

    def evaluate(policy):
        return test_and_validation_metrics(cfg, policy_controller(policy))

    return EnvSpec(env, env.observation_size, env.action_size, env.episode_length, evaluate, True,
                   env.actor_observation_size)  # fmt: skip


def load_brax_envs():
    """``brax.envs``, imported when a Brax task (or Brax's trainers) first needs it, not with the
    package: it imports all of Brax and MuJoCo MJX (about 0.5 s).  mujoco.mjx prints "Failed to
    import warp" when the optional GPU package is absent; that stays out of our output."""
    with contextlib.redirect_stdout(io.StringIO()):
        from brax import envs
    return envs


class _WithTerminated:
    """A Brax env whose ``info["terminated"]`` is 1.0 at a true terminal state (a fall), and
    0.0 at the time limit (``info["truncation"]``), as :class:`~ttd3_jax.sim.env.TrackingEnv`
    reports it."""

    def __init__(self, env):
        self.env = env
        self.observation_size, self.action_size = env.observation_size, env.action_size

    def reset(self, rng: jax.Array):
        s = self.env.reset(rng)
        return s.replace(info={**s.info, "terminated": jnp.zeros_like(s.done)})

    def step(self, state, action: jax.Array):
        s = self.env.step(state, action)
        return s.replace(info={**s.info, "terminated": s.done * (1.0 - s.info["truncation"])})


def brax(name: str, backend: str = "mjx", episode_length: int = 1000, eval_episodes: int = 10) -> EnvSpec:
    """Brax env ``name`` with a time limit of ``episode_length`` steps; evaluated by the mean
    undiscounted return of ``eval_episodes`` deterministic episodes (``eval_return``)."""
    brax_envs = load_brax_envs()  # here, not at the top: a quadrotor run never loads Brax
    env = brax_envs.get_environment(name, backend=backend)
    env = brax_envs.training.EpisodeWrapper(env, episode_length, action_repeat=1)
    env = _WithTerminated(env)

    def evaluate(policy):
        s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(EVAL_KEY), eval_episodes))

        def body(carry):
            t, s, ret, alive = carry
            s = jax.vmap(env.step)(s, jax.vmap(policy)(s.obs))
            # where, not alive * reward: a finished episode keeps stepping and its physics may
            # blow up (MJX inverted_double_pendulum does), and 0 * nan is nan
            ret = ret + jnp.where(alive > 0, s.reward, 0.0)
            return t + 1, s, ret, alive * (1.0 - s.done)

        def running(carry):  # stop early once every episode has ended (falls end them early)
            t, _, _, alive = carry
            return (t < episode_length) & jnp.any(alive > 0)

        ones = jnp.ones(eval_episodes)
        init = (jnp.zeros((), jnp.int32), s, 0.0 * ones, ones)
        return {"eval_return": jnp.mean(jax.lax.while_loop(running, body, init)[2])}

    return EnvSpec(env, env.observation_size, env.action_size, episode_length, evaluate, False,
                   env.observation_size)  # fmt: skip
