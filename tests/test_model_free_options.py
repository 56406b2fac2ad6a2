"""The model-free directions' options (experiments/model_free.py): the observation's memory
and privileged tail, the log error cost, the actor's input slice and the residual critic."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.tiny import tiny
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.env import TrackingEnv, error_cost
from ttd3_jax.td3.config import TrainConfig
from ttd3_jax.td3.networks import MLP, ResidualMLP, make_networks
from ttd3_jax.td3.trainer import seed_keys

A1, A2 = jnp.array([0.3, -0.2, 0.1, 0.5]), jnp.array([-0.4, 0.6, 0.0, -0.1])


def _two_steps(cfg: EnvConfig):
    env = TrackingEnv(cfg)
    s0 = env.reset(jax.random.PRNGKey(3))
    s1 = env.step(s0, A1)
    return env, s0, s1, env.step(s1, A2)


def test_memory_observes_last_action_and_leaky_error_integral():
    cfg = make_config("practical", obs_memory=True, memory_tau=0.5)
    env, s0, s1, s2 = _two_steps(cfg)
    assert env.observation_size == env.actor_observation_size == 24
    lay = env.layout
    np.testing.assert_array_equal(s0.obs[lay.actor_size - 7 :], np.zeros(7))
    np.testing.assert_allclose(s2.obs[lay.slice("last_action")], A2, atol=1e-7)
    dt, leak = cfg.control_dt, math.exp(-cfg.control_dt / 0.5)
    e = lambda s: tr.position(s.pipeline_state.track, s.pipeline_state.k, cfg.dt) - s.pipeline_state.quad.p  # noqa: E731
    want = leak * dt * e(s1) + dt * e(s2)
    np.testing.assert_allclose(s2.obs[lay.slice("error_integral")], want, rtol=1e-5, atol=1e-8)
    plain = _two_steps(make_config("practical", memory_tau=0.5))[3]
    np.testing.assert_array_equal(s2.obs[: plain.obs.shape[0]], plain.obs)  # the paper's parts first


def test_privileged_tail_is_wind_and_the_reference_ahead():
    cfg = make_config("practical", obs_privileged=True)
    env, _, _, s2 = _two_steps(cfg)
    assert (env.observation_size, env.actor_observation_size) == (26, 17)
    ps = s2.pipeline_state
    assert env.layout.critic_only == ("wind", "p_ahead_0.5s", "p_ahead_1s")
    np.testing.assert_allclose(s2.obs[env.layout.slice("wind")], ps.wind, rtol=1e-6)
    ahead = ps.k + cfg.observation.lookahead_k
    for t in (0.5, 1.0):
        want = tr.position(ps.track, ahead + round(t / cfg.dt), cfg.dt) - tr.position(ps.track, ahead, cfg.dt)
        np.testing.assert_allclose(s2.obs[env.layout.slice(f"p_ahead_{t:g}s")], want, rtol=1e-5, atol=1e-6)
    # the track table covers the extra second of look-ahead
    assert cfg.horizon_steps == make_config("practical").horizon_steps + 1000


def test_log_error_cost_and_its_crash_cost():
    cfg = make_config("practical", err_cost="log", err_scale=0.05)
    e = jnp.array([0.0, 0.01, 0.5, 3.0])
    np.testing.assert_allclose(error_cost(cfg, e), np.log1p(np.asarray(e) / 0.05), rtol=1e-6)
    assert cfg.crash_cost == pytest.approx(math.log1p(1.0 / 0.05) * 10 / 0.01)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(err_scale=0.0), "err_scale"),
        (dict(memory_tau=-1.0), "memory_tau"),
        (dict(obs_memory=True, action_delay=1), "obs_memory needs disturbances.action_delay 0"),
        (dict(obs_privileged=1), "obs_privileged"),
    ],
)
def test_option_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EnvConfig().replace(**kwargs)
    with pytest.raises(ValueError, match="critic_arch must be one of"):
        TrainConfig(critic_arch="transformer")


def test_actor_reads_only_its_slice_and_residual_critic_shapes():
    nets = make_networks(4, (16, 16), "residual", actor_obs_size=5)
    assert isinstance(nets.critic, ResidualMLP) and isinstance(nets.actor, MLP)
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 9))
    p = nets.actor.init(jax.random.PRNGKey(1), x)
    assert p["params"]["Dense_0"]["kernel"].shape == (5, 16)
    np.testing.assert_array_equal(nets.actor.apply(p, x), nets.actor.apply(p, x.at[:, 5:].set(7.0)))
    q = nets.critic.init(jax.random.PRNGKey(2), x)
    assert nets.critic.apply(q, x).shape == (3, 1)
    assert q["params"]["Dense_0"]["kernel"].shape == (9, 16)  # width hidden[0]


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_one_epoch_with_every_option_trains_and_stays_finite():
    s = tiny(critic_arch="residual", n_step=3)
    s = sp.replace(s, task=s.task.replace(obs_memory=True, obs_privileged=True, err_cost="log"))
    t = sp.trainer_for(s)
    assert (t.env.obs_size, t.env.actor_obs_size) == (33, 24)
    ts = jax.jit(t.init)(seed_keys(0, 1)[0], s.hp)
    ts, m = jax.jit(t.epoch)(ts, s.hp)
    assert ts.actor["params"]["Dense_0"]["kernel"].shape == (24, 32)
    assert all(np.isfinite(float(m[k])) for k in ("critic_loss", "actor_loss", "q_mean"))


def test_every_direction_builds_and_fast_model_free_is_the_memory_privileged_direction():
    from experiment_scripts import experiment

    mf = experiment("model_free")
    for name in mf.DIRECTIONS:
        assert mf.spec_for(name).num_seeds == 3
    assert mf.spec_for("memory_privileged") == sp.preset("fast_model_free", num_seeds=3)
    assert mf.beats(25.0, 398.0) and not mf.beats(25.0, 400.0) and not mf.beats(None, 1.0)
