"""The tracking env behind the Gymnasium and gymnax APIs (optional extras ``gym`` and ``gymnax``).

- :class:`GymnasiumTrackingEnv`: a single ``gymnasium.Env`` (Gymnasium >= 1.0) over the jitted
  ``TrackingEnv.reset`` / ``step``; it passes ``gymnasium.utils.env_checker.check_env``.
- :class:`GymnaxTrackingEnv`: a ``gymnax`` ``Environment`` (``reset_env`` / ``step_env`` with
  params; gymnax's ``step`` auto-resets), written against gymnax 0.0.9, the version the
  ``peers`` extra pins (gymnax 1.x changed ``step``'s outputs).

Why not Brax's ``brax.envs.wrappers.gym.GymWrapper``: it is written for the legacy ``gym``
package (``reset() -> obs``, ``step -> (obs, reward, done, info)``), not Gymnasium, so no
Gymnasium tool accepts it, and it reads the action bounds from ``env.sys.actuator.ctrl_range``,
a MuJoCo system that a quadrotor env has none of.  Giving the env a fake ``sys`` would fix the
second, not the first.

Both adapters keep ``terminated`` (a crash, ``info["terminated"]``) apart from ``truncated``
(the time limit, ``info["truncation"]``).  Observation: ``TrackingEnv.observation_size``
floats (17, or 20 with a rate model); action: 4 floats in [-1, 1] (collective thrust, body
rates; sim/env.py).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.env import TrackingEnv

_MISSING: dict[str, ImportError] = {}  # extra -> why it did not import
try:
    import gymnasium
except ImportError as e:  # the "gym" extra is not installed
    gymnasium, _MISSING["gym"] = None, e
try:  # gymnax 0.0.9 imports six without declaring it: pip install six
    from gymnax.environments import environment as gymnax_env
    from gymnax.environments import spaces as gymnax_spaces
except ImportError as e:  # the "gymnax" extra is not installed
    gymnax_env = gymnax_spaces = None
    _MISSING["gymnax"] = e

_METRICS = ("tracking_error", "energy", "crashed")  # per step, from State.metrics (m, -, 0/1)


def _require(cls: str, extra: str) -> None:
    if extra in _MISSING:
        raise ImportError(
            f"{cls} needs the {extra!r} extra (pip install 'ttd3_jax[{extra}]'): {_MISSING[extra]}"
        ) from _MISSING[extra]


class GymnasiumTrackingEnv(gymnasium.Env if gymnasium else object):
    """One tracking env as a ``gymnasium.Env``.  ``reset(seed=...)`` seeds ``np_random``,
    from which each reset draws the JAX key: the same seed gives the same episode.  ``info``
    holds this step's ``tracking_error`` (Σ‖e‖ over its physics steps, m), ``energy`` and
    ``crashed`` (floats)."""

    metadata = {"render_modes": []}

    def __init__(self, config: EnvConfig | None = None):
        _require("GymnasiumTrackingEnv", "gym")
        self.env = TrackingEnv(config)
        self.metadata = {"render_modes": [], "render_fps": 1.0 / self.env.dt}
        n = self.env.observation_size
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (n,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (self.env.action_size,), np.float32)
        self._reset, self._step = jax.jit(self.env.reset), jax.jit(self.env.step)
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options:
            raise ValueError(f"GymnasiumTrackingEnv.reset takes no options, got {sorted(options)}")
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        self._state = self._reset(key)
        return self._obs(), {}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("GymnasiumTrackingEnv.step called before reset()")
        a = np.asarray(action, np.float32)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        s = self._state = self._step(self._state, a)
        info = {k: float(s.metrics[k]) for k in _METRICS}
        terminated, truncated = bool(s.info["terminated"] > 0), bool(s.info["truncation"] > 0)
        return self._obs(), float(s.reward), terminated, truncated, info

    def _obs(self) -> np.ndarray:
        return np.asarray(self._state.obs, np.float32)


class GymnaxTrackingEnv(gymnax_env.Environment if gymnax_env else object):
    """The tracking env as a gymnax ``Environment``; its state is the Brax ``State``.  The
    env's configuration is static (an ``EnvConfig``, one compiled program each), so the
    params carry only ``max_steps_in_episode`` (control steps, ``TrackingEnv.episode_length``),
    which the env itself enforces.  ``info`` holds ``terminated``, ``truncation``,
    ``discount`` (0 after a crash) and the step's metrics."""

    def __init__(self, config: EnvConfig | None = None):
        _require("GymnaxTrackingEnv", "gymnax")
        self.env = TrackingEnv(config)

    @property
    def default_params(self):
        return gymnax_env.EnvParams(max_steps_in_episode=self.env.episode_length)

    def reset_env(self, key, params):
        s = self.env.reset(key)
        return s.obs, s

    def step_env(self, key, state, action, params):
        s = self.env.step(state, action)
        terminated = s.info["terminated"]
        info = {"terminated": terminated, "truncation": s.info["truncation"], "discount": 1.0 - terminated}
        info |= {k: s.metrics[k] for k in _METRICS}
        return s.obs, s, s.reward, s.done > 0, info

    def get_obs(self, state, params=None, key=None):
        return state.obs

    def is_terminal(self, state, params):
        return state.done > 0

    @property
    def name(self) -> str:
        return "TTD3Quadrotor-v0"

    @property
    def num_actions(self) -> int:
        return self.env.action_size

    def action_space(self, params=None):
        return gymnax_spaces.Box(-1.0, 1.0, (self.env.action_size,), jnp.float32)

    def observation_space(self, params=None):
        return gymnax_spaces.Box(-jnp.inf, jnp.inf, (self.env.observation_size,), jnp.float32)
