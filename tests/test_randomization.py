"""Domain randomisation drawn per episode (sim.randomization): the plant's draws, the env's
physics under each, their validation, the nominal evaluation, and a tiny training run."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny import tiny

from ttd3_jax.run import spec as sp
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim.config import PLANT_NEUTRAL, make_config
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.sim.env import TrackingEnv, hover_action
from ttd3_jax.sim.env_state import RandomizedTrackingState, TrackingState
from ttd3_jax.td3 import trainer as T

G = 9.81


def flight(**kw):
    """The paper's env on Spiral-RT from rest at p_d(0) = 0, no wind, no termination, with ``kw``."""
    base = dict(wind_sigma=0.0, randomize_init=False, track="spiral_rt", terminate=False, episode_steps=600)
    return TrackingEnv(make_config("paper", **{**base, **kw}))


def run(env, actions, key=0):
    """Positions and velocities after each control step of ``actions`` (n, 4), and the last state."""
    s0 = env.reset(jax.random.PRNGKey(key))

    def body(s, a):
        s = env.step(s, a)
        return s, (s.pipeline_state.quad.p, s.pipeline_state.quad.v)

    s, (p, v) = jax.jit(lambda s0, a: jax.lax.scan(body, s0, a))(s0, actions)
    return np.asarray(p, np.float64), np.asarray(v, np.float64), s


def test_the_neutral_config_keeps_the_unrandomised_env():
    env = flight()
    assert (
        not rz.active(env.config) and type(env.reset(jax.random.PRNGKey(0)).pipeline_state) is TrackingState
    )
    assert rz.active(env.config.replace(mass=(1.0, 1.1)))
    assert (
        type(flight(mass=(1.1, 1.1)).reset(jax.random.PRNGKey(0)).pipeline_state) is RandomizedTrackingState
    )


@pytest.mark.parametrize(
    "field, factor, accel", [("mass", 1.2, G * (1 / 1.2 - 1)), ("thrust_gain", 0.9, -0.1 * G)]
)
def test_a_fixed_mass_or_thrust_gain_is_unknown_to_the_action_map(field, factor, accel):
    """The hover action of the nominal map, on a heavier vehicle or one short of thrust,
    falls at the closed-form rate (RK4 is exact for a constant acceleration)."""
    env = flight(**{field: (factor, factor)})
    n = 50
    p, v, _ = run(env, jnp.tile(hover_action(env.config), (n, 1)))
    t = np.arange(1, n + 1) * 1e-3
    np.testing.assert_allclose(v[:, 2], accel * t, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(p[:, 2], 0.5 * accel * t**2, rtol=1e-3, atol=1e-8)
    np.testing.assert_allclose(p[:, :2], 0.0, atol=1e-9)


def _actions(cfg, n, seed=1):
    hover = hover_action(cfg)
    return hover + 0.05 * jax.random.uniform(jax.random.PRNGKey(seed), (n, 4), minval=-1.0, maxval=1.0)


def test_a_latency_of_d_physics_steps_applies_each_command_d_steps_later():
    """R = 1, d = 2 ms: the same flight as an undelayed env fed the commands 2 steps later;
    a thrust step shows in the velocity 2 physics steps after it was commanded."""
    env, plain = flight(latency=(0.002, 0.002)), flight()
    hover = hover_action(env.config)
    a = _actions(env.config, 40)
    p, v, s = run(env, a)
    assert int(s.pipeline_state.plant.latency) == 2
    shifted = jnp.concatenate([jnp.tile(hover, (2, 1)), a[:-2]])
    p0, v0, _ = run(plain, shifted)
    np.testing.assert_allclose(p, p0, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(v, v0, rtol=1e-5, atol=1e-6)
    step = jnp.tile(hover, (6, 1)).at[:, 0].set(1.0)  # full thrust from step 0
    _, v, _ = run(env, step)
    assert np.all(v[:2, 2] == 0.0) and np.all(v[2:, 2] > 0.0)


def test_a_latency_longer_than_a_control_step_splits_the_control_step():
    """action_repeat 10, d = 13 ms: physics step i applies the command of control step
    floor((i - 13) / 10), as an undelayed 1 ms env fed that sequence flies."""
    env = flight(action_repeat=10, latency=(0.013, 0.013))
    plain = flight()
    n = 8
    a = _actions(env.config, n)
    p, _, s = run(env, a)
    assert int(s.pipeline_state.plant.latency) == 13 and s.pipeline_state.pending.shape == (2, 4)
    i = np.arange(10 * n)
    idx = np.floor((i - 13) / 10).astype(int)
    per_step = jnp.where((idx >= 0)[:, None], a[np.maximum(idx, 0)], hover_action(env.config))
    p0, _, _ = run(plain, per_step)
    np.testing.assert_allclose(p, p0[9::10], rtol=1e-5, atol=1e-7)


def test_the_position_bias_is_observed_and_not_flown():
    env, plain = flight(pos_bias=0.05), flight()
    s, s0 = env.reset(jax.random.PRNGKey(3)), plain.reset(jax.random.PRNGKey(3))
    bias = np.asarray(s.pipeline_state.plant.pos_bias)
    assert np.all(np.abs(bias) <= 0.05) and np.all(bias != 0.0)
    lay = env.layout.slice("p")
    np.testing.assert_allclose(np.asarray(s.obs[lay]) - np.asarray(s0.obs[lay]), bias, atol=1e-7)
    np.testing.assert_array_equal(s.pipeline_state.quad.p, s0.pipeline_state.quad.p)
    a = hover_action(env.config)
    s, s0 = env.step(s, a), plain.step(s0, a)
    np.testing.assert_allclose(s.pipeline_state.quad.p, s0.pipeline_state.quad.p, atol=1e-7)
    np.testing.assert_allclose(np.asarray(s.obs[lay]) - np.asarray(s0.obs[lay]), bias, atol=1e-6)


def test_each_episode_draws_its_plant_within_the_ranges():
    ranges = dict(mass=(0.8, 1.2), inertia=(0.5, 1.5), thrust_max=(0.9, 1.1), thrust_gain=(0.95, 1.05),
                  tau_rate=(0.5, 2.0), rate_limit=(0.7, 1.0), latency=(0.0, 0.02), obs_noise=(0.0, 2.0),
                  pos_bias=0.02, wind_mean=0.3)  # fmt: skip
    cfg = make_config("practical", **ranges)
    q = cfg.vehicle.quad
    plants = jax.vmap(lambda k: rz.draw(cfg, k, dtype=jnp.float32))(
        jax.random.split(jax.random.PRNGKey(0), 256)
    )
    assert plants.quad.rate_model == "first_order"  # tau_rate randomised on an instant vehicle
    mass = np.asarray(plants.quad.mass) / q.mass
    assert len(np.unique(mass)) == 256 and mass.min() >= 0.8 - 1e-6 and mass.max() <= 1.2 + 1e-6
    inertia = np.stack(plants.quad.inertia, -1) / np.asarray(q.inertia)
    assert (
        inertia.min() >= 0.5 - 1e-6
        and inertia.max() <= 1.5 + 1e-6
        and np.std(inertia[:, 0] - inertia[:, 1]) > 0
    )
    tau = np.asarray(plants.quad.tau_rate) / q.tau_rate
    assert tau.min() >= 0.5 - 1e-6 and tau.max() <= 2.0 + 1e-6
    rate = np.asarray(plants.quad.rate_max) / q.rate_max
    np.testing.assert_allclose(np.asarray(plants.quad.rate_min) / q.rate_min, rate, rtol=1e-6)
    lat = np.asarray(plants.latency)
    assert set(np.unique(lat)) == set(range(21)) and rz.pending_size(cfg) == 2
    assert (
        np.abs(np.asarray(plants.pos_bias)).max() <= 0.02
        and np.abs(np.asarray(plants.wind_mean)).max() <= 0.3
    )
    # two resets with different keys fly different vehicles; the track and start are those of an
    # unrandomised env (drawing the plant changes no other draw)
    env, plain = TrackingEnv(cfg), TrackingEnv(make_config("practical"))
    s1, s2 = env.reset(jax.random.PRNGKey(1)), env.reset(jax.random.PRNGKey(2))
    assert float(s1.pipeline_state.plant.quad.mass) != float(s2.pipeline_state.plant.quad.mass)
    n1 = plain.reset(jax.random.PRNGKey(1))
    np.testing.assert_array_equal(s1.pipeline_state.quad.p, n1.pipeline_state.quad.p)
    np.testing.assert_array_equal(s1.pipeline_state.wind, n1.pipeline_state.wind)


def test_a_given_vehicle_is_randomised_around():
    cfg = make_config("paper", mass=(1.2, 1.2))
    heavy = QuadParams(mass=3.0, thrust_max=40.0)
    plant = rz.draw(cfg, jax.random.PRNGKey(0), heavy)
    assert math.isclose(float(plant.quad.mass), 3.6, rel_tol=1e-6) and float(plant.quad.thrust_max) == 40.0


@pytest.mark.parametrize(
    "kw, match",
    [
        (
            dict(mass=(-0.1, 1.0)),
            r"EnvConfig.randomization.mass must be a range \(lo, hi\) of 2 finite numbers > 0",
        ),
        (dict(mass=(1.2, 0.8)), r"EnvConfig.randomization.mass must be a range \(lo, hi\) with lo <= hi"),
        (dict(thrust_gain=(1.0,)), "EnvConfig.randomization.thrust_gain must be a range"),
        (dict(inertia=(0.5, math.inf)), "EnvConfig.randomization.inertia must be a range"),
        (dict(latency=(0.0, 0.1)), r"EnvConfig.randomization.latency must be .* in \[0, 0.05\] s"),
        (dict(latency=(-0.001, 0.0)), "EnvConfig.randomization.latency must be"),
        (dict(obs_noise=(-1.0, 1.0)), "EnvConfig.randomization.obs_noise must be"),
        (dict(pos_bias=-0.1), "EnvConfig.randomization.pos_bias must be a finite number >= 0"),
        (dict(wind_mean=math.nan), "EnvConfig.randomization.wind_mean must be"),
        (
            dict(mass=(1.0, 1.4)),
            "EnvConfig.randomization.mass, thrust_max, thrust_gain must let every drawn ",
        ),
        (dict(thrust_gain=(0.7, 1.0)), "must let every drawn vehicle hover"),
        (dict(quad=QuadParams(rate_model="torque"), tau_rate=(0.5, 1.0)), "EnvConfig.randomization.tau_rate"),
    ],
)
def test_bad_ranges_are_refused_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        make_config("paper", **kw)


def test_evaluation_flies_the_nominal_plant():
    ranges = dict(mass=(0.8, 1.2), latency=(0.0, 0.02), pos_bias=0.02, wind_mean=0.3, obs_noise=(0.5, 2.0))
    cfg = make_config("practical", **ranges)
    nominal = make_config("practical")
    for track in ("spiral_rt", "validation"):
        assert cfg.for_eval(track) == nominal.for_eval(track) and not rz.active(cfg.for_eval(track))
    assert {f"randomization.{k}" for k in PLANT_NEUTRAL} <= {cfg.path(f) for f in cfg.for_eval.__globals__[
        "EVAL_PROTOCOL_FIELDS"]}  # fmt: skip


def test_gradients_flow_through_the_randomised_plant():
    """The model-based actor differentiates the return through the env: under latency, mass
    and thrust-gain errors and a 10 ms control step the gradient is finite and nonzero."""
    cfg = make_config("practical", hover_centered_thrust=True, mass=(0.9, 1.1), thrust_gain=(0.95, 1.05),
                      latency=(0.005, 0.015), wind_mean=0.2)  # fmt: skip
    env = TrackingEnv(cfg)
    s0 = env.reset(jax.random.PRNGKey(0))

    def ret(a0):
        a = hover_action(cfg).at[0].set(a0)
        return jax.lax.scan(lambda s, _: (env.step(s, a), s.reward), s0, None, 20)[1].sum()

    g = jax.jit(jax.grad(ret))(0.1)
    assert math.isfinite(float(g)) and float(g) != 0.0


@pytest.mark.slow  # tests/test_robust.py's tiny robust run covers it by default
def test_a_tiny_randomised_run_trains():
    task = sp.preset("fast_dpg").task.replace(mass=(0.9, 1.1), latency=(0.0, 0.02), thrust_gain=(0.95, 1.05),
                                              pos_bias=0.01, wind_mean=0.2)  # fmt: skip
    s = tiny(task=task, model_horizon=2, epochs=1)
    t = sp.trainer_for(s)
    ts = jax.jit(t.init)(T.seed_keys(0, 1)[0], s.hp)
    ts, m = jax.jit(t.epoch)(ts, s.hp)
    assert np.all(np.isfinite(np.asarray(m["critic_loss"])))
    assert np.isfinite(float(jax.jit(t.evaluate)(ts)["spiral_tracking_error"]))
