"""The Gymnasium and gymnax adapters of the tracking env (skipped without their extras)."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.interop import adapters
from ttd3_jax.sim.config import make_config

CFG = make_config("practical", episode_steps=50, track="spiral_rt")  # 5 control steps of 10 ms


def test_gymnasium_env_passes_the_checker_and_separates_termination():
    pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    env = adapters.GymnasiumTrackingEnv(CFG)
    assert env.observation_space.shape == (17,) and env.action_space.shape == (4,)
    assert env.action_space.low.min() == -1.0 and env.action_space.high.max() == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded observations and no render modes: by design
        check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=7)
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(obs, again)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)
    ends = []
    for _ in range(CFG.episode_length):
        obs, r, terminated, truncated, info = env.step(np.zeros(4, np.float32))
        ends.append((terminated, truncated))
        assert np.isfinite(r) and info["tracking_error"] > 0
    assert ends[-1] == (False, True) and not any(t or u for t, u in ends[:-1]), ends
    # full thrust flies off the track: a crash ends the episode as terminated, not truncated
    crash = adapters.GymnasiumTrackingEnv(make_config("practical", track="spiral_rt"))
    crash.reset(seed=0)
    for _ in range(crash.env.episode_length):
        _, _, terminated, truncated, info = crash.step(np.array([1, 0, 0, 0], np.float32))
        if terminated or truncated:
            break
    assert terminated and not truncated and info["crashed"] == 1.0
    with pytest.raises(ValueError, match=r"shape \(4,\)"):
        env.step(np.zeros(3))


def test_gymnasium_env_refuses_a_step_before_reset():
    pytest.importorskip("gymnasium")
    with pytest.raises(RuntimeError, match="before reset"):
        adapters.GymnasiumTrackingEnv(CFG).step(np.zeros(4))


def test_gymnax_env_steps_auto_resets_and_keeps_truncation():
    pytest.importorskip("gymnax")
    env = adapters.GymnaxTrackingEnv(CFG)
    params = env.default_params
    assert params.max_steps_in_episode == CFG.episode_length == 5
    assert env.observation_space(params).shape == (17,) and env.num_actions == 4
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    assert obs.shape == (17,)

    def body(carry, key):
        obs, s = carry
        k_act, k_step = jax.random.split(key)
        a = env.action_space(params).sample(k_act)
        obs, s, r, done, info = env.step(k_step, s, a, params)
        return (obs, s), (r, done, info["truncation"], info["discount"], s.pipeline_state.k)

    keys = jax.random.split(jax.random.PRNGKey(1), 12)
    _, (r, done, trunc, discount, k) = jax.jit(lambda c, ks: jax.lax.scan(body, c, ks))((obs, state), keys)
    assert bool(jnp.all(jnp.isfinite(r)))
    np.testing.assert_array_equal(np.flatnonzero(done), [4, 9])  # every 5th step ends the episode
    np.testing.assert_array_equal(np.asarray(trunc), np.asarray(done, np.float32))
    np.testing.assert_array_equal(np.asarray(discount), np.ones(12))  # time limits, no crash
    assert int(k[4]) == 0 and int(k[5]) == 10  # the state after a done is a fresh episode's
