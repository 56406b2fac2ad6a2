"""Tracking environment: observation layout, reward, termination, presets, Brax wrappers."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training

from ttd3_jax.control.closed_loop import closed_loop, hover_controller, metrics
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.dynamics import QuadParams, QuadState
from ttd3_jax.sim.env import TrackingEnv, _zero_non_finite, action_to_control, control_to_action, hover_action

DT = 1e-3


def spiral_np(k, dt=DT):
    """Paper eq. 6 with t = k dt seconds, float64."""
    t = np.asarray(k, np.float64) * dt
    return np.stack([0.1 * t * np.cos(np.pi * t / 20), 0.1 * t * np.sin(np.pi * t / 20), 0.1 * t], -1)


def spiral_env(**kw):
    return TrackingEnv(make_config("paper", **kw).for_eval("spiral_rt"))


def with_quad(env, state, k, p, v=(0, 0, 0), q=(1, 0, 0, 0)):
    """Put the vehicle at a known state at step k and rebuild the observation."""
    quad = QuadState(
        p=jnp.asarray(p, jnp.float32),
        v=jnp.asarray(v, jnp.float32),
        q=jnp.asarray(q, jnp.float32),
        w=jnp.zeros(3),
    )
    ps = state.pipeline_state.replace(quad=quad, k=jnp.asarray(k, jnp.int32))
    obs, ps = env.observe(ps)
    return state.replace(pipeline_state=ps, obs=obs)


def test_observation_layout_exact_at_known_state():
    env = spiral_env()
    s = env.reset(jax.random.PRNGKey(0))
    k = 1200
    p, v = np.array([0.3, -0.2, 0.5]), np.array([0.1, 0.2, -0.3])
    q = np.array([-0.9, 0.1, 0.3, -0.2])
    q = q / np.linalg.norm(q)
    s = with_quad(env, s, k, p, v, q)
    o = np.asarray(s.obs, np.float64)
    assert o.shape == (17,) and env.observation_size == 17
    ref_next, ref_now = spiral_np(k + 1), spiral_np(k)
    np.testing.assert_allclose(o[0:3], p, atol=1e-6)
    np.testing.assert_allclose(o[3:6], v, atol=1e-6)
    np.testing.assert_allclose(o[6:10], -q, atol=1e-6)  # canonical sign: qw >= 0
    np.testing.assert_allclose(o[10:13], ref_next, atol=1e-6)
    np.testing.assert_allclose(o[13:16], ref_next - p, atol=1e-6)
    np.testing.assert_allclose(o[16], np.linalg.norm(ref_now - p), atol=1e-6)


def test_observation_options_next_error_lookahead_and_rates():
    env = TrackingEnv(
        make_config(
            "paper",
            err_ref="next",
            lookahead_k=50,
            canonical_q_obs=False,
            quad=QuadParams.create(rate_model="first_order"),
        ).for_eval("spiral_rt")
    )
    assert env.observation_size == 20
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 100, (0.1, 0.0, 0.0), q=(-1, 0, 0, 0))
    o = np.asarray(s.obs, np.float64)
    assert o.shape == (20,)
    np.testing.assert_allclose(o[6:10], [-1, 0, 0, 0])
    np.testing.assert_allclose(o[10:13], spiral_np(150), atol=1e-6)
    np.testing.assert_allclose(o[16], np.linalg.norm(spiral_np(101) - [0.1, 0, 0]), atol=1e-6)


@pytest.mark.parametrize("offset", [0.5, 1.5])
def test_reward_matches_hand_computation_on_both_branches(offset):
    env = spiral_env()
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 500, spiral_np(500) + [offset, 0, 0])
    a = jnp.array([0.2, -0.3, 0.1, 0.4])
    s2 = jax.jit(env.step)(s, a)
    p1 = np.asarray(s2.pipeline_state.quad.p, np.float64)
    e = np.linalg.norm(spiral_np(501) - p1)
    r_e = e if e * e <= 1 else e * e
    expected = -1.0 * r_e - 0.01 * float(np.sum(np.asarray(a) ** 2))
    assert (e < 1) == (offset < 1)  # both branches are exercised
    np.testing.assert_allclose(float(s2.reward), expected, rtol=1e-5)
    assert float(s2.done) == 0
    np.testing.assert_allclose(float(s2.metrics["tracking_error"]), e, rtol=1e-5)


def test_squared_error_cost_option():
    env = spiral_env(err_cost="squared", rho2=0.0)
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 10, spiral_np(10) + [0.5, 0, 0])
    s2 = env.step(s, hover_action(env.config))
    e = np.linalg.norm(spiral_np(11) - np.asarray(s2.pipeline_state.quad.p))
    np.testing.assert_allclose(float(s2.reward), -(e**2), rtol=1e-5)


def test_action_rate_cost_compares_with_the_last_action_and_needs_the_memory():
    """rho_rate adds rho_rate ||a − a_prev||² per physics step, a_prev the last commanded action
    (obs_memory's last_action, which the policy sees); without the memory it is refused."""
    env = TrackingEnv(make_config("paper", obs_memory=True, rho_rate=0.5).for_eval("spiral_rt"))
    base = TrackingEnv(make_config("paper", obs_memory=True).for_eval("spiral_rt"))
    a1, a2 = jnp.array([0.2, -0.3, 0.1, 0.4]), jnp.array([0.1, 0.3, 0.1, -0.2])
    s, b = env.reset(jax.random.PRNGKey(0)), base.reset(jax.random.PRNGKey(0))
    s, b = env.step(s, a1), base.step(b, a1)  # from the reset's last action, zeros
    np.testing.assert_allclose(float(s.reward), float(b.reward) - 0.5 * float(jnp.sum(a1 * a1)), rtol=1e-5)
    s, b = env.step(s, a2), base.step(b, a2)
    np.testing.assert_allclose(
        float(s.reward), float(b.reward) - 0.5 * float(jnp.sum((a2 - a1) ** 2)), rtol=1e-5
    )
    with pytest.raises(
        ValueError, match=r"EnvConfig.reward.rho_rate must be 0 without observation.obs_memory"
    ):
        make_config("paper", rho_rate=0.5)


def test_heading_cost_is_rho_yaw_times_the_yaw_squared_after_each_physics_step():
    yaw = 0.3
    q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    env, base = spiral_env(rho_yaw=2.0), spiral_env()
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 100, spiral_np(100), q=q)
    b = with_quad(base, base.reset(jax.random.PRNGKey(0)), 100, spiral_np(100), q=q)
    a = hover_action(env.config)
    s, b = env.step(s, a), base.step(b, a)
    np.testing.assert_allclose(float(s.reward), float(b.reward) - 2.0 * yaw**2, rtol=1e-4)


def test_crash_terminates_with_penalty():
    env = TrackingEnv(make_config("paper", track="spiral_rt", randomize_init=False))
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 10, spiral_np(10) + [2.5, 0, 0])
    s2 = env.step(s, hover_action(env.config))
    assert float(s2.done) == 1 and float(s2.info["terminated"]) == 1
    assert float(s2.info["truncation"]) == 0
    assert float(s2.reward) < -400  # -r_e(2.5) - effort - 400
    np.testing.assert_allclose(float(s2.reward), -(2.5**2) - 400 - 0.01 * 0.4715**2, atol=0.05)


def test_nonfinite_state_terminates_and_obs_stays_finite():
    env = TrackingEnv(make_config("paper", track="spiral_rt", randomize_init=False))
    s = with_quad(env, env.reset(jax.random.PRNGKey(0)), 10, (jnp.nan, 0.0, 0.0))
    s2 = env.step(s, hover_action(env.config))
    assert float(s2.done) == 1 and float(s2.info["terminated"]) == 1
    assert bool(jnp.all(jnp.isfinite(s2.obs))) and bool(jnp.isfinite(s2.reward))


def test_obs_mask_matches_where_bit_for_bit_and_keeps_its_derivative():
    special = [1.0, -2.5, 0.0, -0.0, np.nan, -np.nan, np.inf, -np.inf, 3.4e38, -1e-45, 1e-38]
    x = jnp.asarray(np.r_[special, np.random.default_rng(0).normal(size=64)], jnp.float32)
    want = jnp.where(jnp.isfinite(x), x, 0.0)
    got = _zero_non_finite(x)
    np.testing.assert_array_equal(np.asarray(got).view(np.uint32), np.asarray(want).view(np.uint32))
    w = jnp.arange(x.size, dtype=jnp.float32)
    g_got = jax.grad(lambda x: jnp.sum(w * _zero_non_finite(x)))(x)
    g_want = jax.grad(lambda x: jnp.sum(w * jnp.where(jnp.isfinite(x), x, 0.0)))(x)
    np.testing.assert_array_equal(np.asarray(g_got), np.asarray(g_want))
    assert float(jnp.sum(g_got)) > 0  # the mask passes derivatives through (model-based actor)


def test_obs_is_differentiable_in_the_state():
    env = spiral_env()
    ps = env.reset(jax.random.PRNGKey(0)).pipeline_state
    p0 = ps.quad.p + jnp.array([0.1, -0.2, 0.05])  # off the track: ||p_d - p|| is smooth there
    g = jax.grad(lambda p: jnp.sum(env.observe(ps.replace(quad=ps.quad.replace(p=p)))[0]))(p0)
    # p enters slots 0-2 (+1 each), p_d - p (-1 each) and ||p_d - p|| (-(p_d - p)/||.||)
    e = tr.position(ps.track, ps.k, env.config.dt) - p0  # err_ref="current": p_d,k
    want = -e / jnp.linalg.norm(e)
    np.testing.assert_allclose(np.asarray(g), np.asarray(want), rtol=1e-5)


def test_time_limit_truncates_not_terminates():
    env = spiral_env()
    ctrl = geometric_controller(env.config)
    s = env.reset(jax.random.PRNGKey(0))

    def body(s, _):
        a, _ = ctrl.act((), s)
        s = env.step(s, a)
        return s, (s.done, s.info["truncation"], s.info["terminated"])

    s, (done, trunc, term) = jax.jit(lambda s: jax.lax.scan(body, s, None, length=3000))(s)
    assert int(jnp.argmax(done)) == 2999 and float(done.sum()) == 1  # first done at step 3000
    assert float(trunc[-1]) == 1 and float(term.sum()) == 0
    assert int(s.pipeline_state.k) == 3000


def test_vmapped_jit_step_runs_1024_envs():
    env = TrackingEnv()
    keys = jax.random.split(jax.random.PRNGKey(0), 1024)
    s = jax.jit(jax.vmap(env.reset))(keys)
    a = jax.random.uniform(jax.random.PRNGKey(1), (1024, 4), minval=-1, maxval=1)
    s2 = jax.jit(jax.vmap(env.step))(s, a)
    assert s2.obs.shape == (1024, 17) and s2.reward.shape == (1024,)
    assert bool(jnp.all(jnp.isfinite(s2.obs)))
    # resets draw different tracks and initial states
    assert len(np.unique(np.asarray(s.obs[:, 0]))) == 1024


def test_brax_episode_and_autoreset_wrappers():
    env = training.wrap(TrackingEnv(), episode_length=10)  # Vmap + Episode + AutoReset
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    s0 = jax.jit(env.reset)(keys)
    step = jax.jit(env.step)
    a = jnp.tile(hover_action(make_config()), (4, 1))
    s = s0
    for i in range(10):
        s = step(s, a)
        assert float(s.done.sum()) == (4 if i == 9 else 0)
    assert np.all(np.asarray(s.info["truncation"]) == 1)
    np.testing.assert_allclose(s.obs, s0.obs)  # auto-reset to the first state
    np.testing.assert_array_equal(s.info["steps"], 10)
    assert np.all(np.asarray(s.info["episode_metrics"]["tracking_error"]) > 0)
    s = step(s, a)  # continues after the reset
    assert float(s.done.sum()) == 0 and np.all(np.asarray(s.info["steps"]) == 1)


def test_episode_wrapper_on_single_env_and_eval_wrapper():
    env = training.EvalWrapper(training.wrap(TrackingEnv(), episode_length=5))
    s = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    step = jax.jit(env.step)
    for _ in range(5):
        s = step(s, jnp.zeros((2, 4)))
    em = s.info["eval_metrics"]
    assert np.all(np.asarray(em.episode_steps) == 5)
    assert np.all(np.asarray(em.active_episodes) == 0)


def test_action_map_hover_and_inverse():
    cfg = make_config()
    a_h = np.asarray(hover_action(cfg))
    np.testing.assert_allclose(a_h, [0.4715, 0, 0, 0], atol=1e-4)
    a = jax.random.uniform(jax.random.PRNGKey(0), (100, 4), minval=-1, maxval=1)
    u = action_to_control(cfg, a)
    assert float(u[:, 0].min()) >= 0 and float(u[:, 0].max()) <= 20
    assert float(jnp.abs(u[:, 1:]).max()) <= 6
    np.testing.assert_allclose(control_to_action(cfg, u), a, atol=1e-5)
    np.testing.assert_allclose(action_to_control(cfg, jnp.array([1.0, -1, 0, 1])), [20, -6, 0, 6])
    hc = make_config(hover_centered_thrust=True)
    np.testing.assert_allclose(action_to_control(hc, jnp.zeros(4))[0], 1.5 * 9.81, rtol=1e-6)
    np.testing.assert_allclose(action_to_control(hc, jnp.array([1.0, 0, 0, 0]))[0], 20.0)
    np.testing.assert_allclose(action_to_control(hc, jnp.array([-1.0, 0, 0, 0]))[0], 0.0, atol=1e-6)
    mn = make_config(quad=QuadParams.create(thrust_units="mass_normalized"))
    np.testing.assert_allclose(hover_action(mn)[0], -0.019, atol=1e-3)


def test_hover_action_holds_position_in_env():
    env = spiral_env()
    s = env.reset(jax.random.PRNGKey(0))
    a = hover_action(env.config)
    s = jax.jit(lambda s: jax.lax.scan(lambda s, _: (env.step(s, a), None), s, None, 3000)[0])(s)
    assert float(jnp.abs(s.pipeline_state.quad.p).max()) < 1e-4


def test_initial_state_ranges_and_track_variety():
    env = TrackingEnv()
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(7), 512))
    q = s.pipeline_state.quad
    assert float(jnp.abs(q.p).max()) <= 0.1 + 1e-6 and float(jnp.abs(q.v).max()) <= 0.2 + 1e-6
    tilt = jnp.degrees(jnp.arccos(jnp.clip(1 - 2 * (q.q[:, 1] ** 2 + q.q[:, 2] ** 2), -1, 1)))
    assert float(tilt.max()) <= 10.0 + 1e-3 and float(tilt.max()) > 5.0
    np.testing.assert_allclose(jnp.linalg.norm(q.q, axis=-1), 1.0, atol=1e-6)
    kinds = np.asarray(s.pipeline_state.track.kind)
    assert set(np.unique(kinds)) == {tr.SPIRAL, tr.PIECEWISE}
    later = jax.jit(jax.vmap(lambda t: tr.position(t, 2000, DT)))(s.pipeline_state.track)
    assert len(np.unique(np.round(np.asarray(later), 5), axis=0)) == 512


def test_eval_reset_is_on_track_at_rest_and_level():
    env = TrackingEnv(make_config().for_eval("los_rt", los_seed=3))
    s = env.reset(jax.random.PRNGKey(11))
    q = s.pipeline_state.quad
    np.testing.assert_array_equal(q.p, 0.0)
    np.testing.assert_array_equal(q.v, 0.0)
    np.testing.assert_array_equal(q.q, [1, 0, 0, 0])
    expected = tr.position(tr.los_test_track(3), 2000, DT)
    np.testing.assert_allclose(tr.position(s.pipeline_state.track, 2000, DT), expected, atol=1e-6)


def test_wind_and_observation_noise_are_seeded():
    cfg = make_config(track="spiral_rt", randomize_init=False, wind_sigma=0.5, obs_noise_pos=0.01)
    env = TrackingEnv(cfg)
    a = hover_action(cfg)

    def run(key):
        s = env.reset(key)
        return jax.lax.scan(lambda s, _: (env.step(s, a), None), s, None, 500)[0]

    run = jax.jit(run)
    s1, s2, s3 = run(jax.random.PRNGKey(0)), run(jax.random.PRNGKey(0)), run(jax.random.PRNGKey(1))
    np.testing.assert_array_equal(s1.obs, s2.obs)
    assert float(jnp.abs(s1.pipeline_state.quad.p - s3.pipeline_state.quad.p).max()) > 1e-4
    # the wind moved the vehicle, and the observed position is noisy
    assert float(jnp.linalg.norm(s1.pipeline_state.quad.p)) > 1e-3
    assert 0 < float(jnp.linalg.norm(s1.obs[:3] - s1.pipeline_state.quad.p)) < 0.1


def test_practical_preset_repeats_actions():
    cfg = make_config("practical")
    assert (
        cfg.action_repeat == 10 and cfg.observation.lookahead_k == 50 and cfg.observation.obs_frame == "track"
    )
    assert cfg.reward.e_max == 1.0 and cfg.crash_cost == pytest.approx(1000)  # r_e(1)·10/(1-0.99)
    assert make_config("practical", e_max=2.0).crash_cost == pytest.approx(4000)
    env = TrackingEnv(cfg.for_eval("spiral_rt"))
    assert env.episode_length == 300 and env.dt == pytest.approx(0.01)
    s = env.step(env.reset(jax.random.PRNGKey(0)), hover_action(cfg))
    assert int(s.pipeline_state.k) == 10
    np.testing.assert_allclose(s.obs[10:13], spiral_np(60) - spiral_np(10), atol=1e-6)  # track frame
    assert float(s.metrics["energy"]) == pytest.approx(10 * 0.4715, rel=1e-4)


def test_geometric_controller_tracks_both_test_tracks():
    """End-to-end plausibility: a classical controller reaches the spec's §3 ranges."""
    results = {}
    for track in ("spiral_rt", "los_rt"):
        env = TrackingEnv(make_config().for_eval(track))
        for name, ctrl in (
            ("geo", geometric_controller(env.config)),
            ("hover", hover_controller(env.config)),
        ):
            m = jax.jit(lambda k, env=env, ctrl=ctrl: metrics(env, closed_loop(env, ctrl, env.reset(k))))(
                jax.random.PRNGKey(0)
            )
            results[track, name] = {k: float(v) for k, v in m.items()}
    assert results["spiral_rt", "geo"]["tracking_error"] < 15
    assert results["los_rt", "geo"]["tracking_error"] < 350
    assert results["spiral_rt", "hover"]["tracking_error"] > 500
    assert results["los_rt", "geo"]["crashed"] == 0
    # hover energy: Σ||a|| = 3000 * 0.4715
    assert results["spiral_rt", "hover"]["energy"] == pytest.approx(3000 * 0.4715, rel=1e-3)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(dt=0.0), "dt"),
        (dict(dt=-1e-3), "dt"),
        (dict(episode_steps=0), "episode_steps"),
        (dict(episode_steps=3000, action_repeat=7), "multiple of action_repeat"),
        (dict(track="circle"), "track"),
        (dict(err_ref="later"), "err_ref"),
        (dict(err_cost="cubic"), "err_cost"),
        (dict(e_max=0), "e_max"),
        (dict(wind_sigma=-0.1), "wind_sigma"),
        (dict(effort_weights=(1, 1, 1)), "effort_weights"),
        (dict(lookahead_k=1.5), "lookahead_k"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EnvConfig().replace(**kwargs)


def test_preset_and_quad_validation():
    with pytest.raises(ValueError, match="unknown env preset 'fast'.*paper"):
        make_config("fast")
    with pytest.raises(ValueError, match="mass"):
        EnvConfig().replace(quad=QuadParams(mass=-1.0))
    with pytest.raises(ValueError, match="rate_model"):
        TrackingEnv(make_config(), quad=QuadParams(rate_model="magic"))
    with pytest.raises(ValueError, match="thrust_min"):
        make_config(quad=QuadParams(thrust_min=5.0, thrust_max=2.0))


def test_float64_env_step():
    with jax.enable_x64(True):
        env = spiral_env()
        s = env.step(env.reset(jax.random.PRNGKey(0)), hover_action(env.config))
        assert s.obs.dtype == jnp.float64 and s.pipeline_state.quad.p.dtype == jnp.float64


def test_grad_of_return_through_env():
    env = spiral_env()
    s0 = env.reset(jax.random.PRNGKey(0))

    def ret(a0):
        a = hover_action(env.config).at[0].set(a0)
        return jax.lax.scan(lambda s, _: (env.step(s, a), s.reward), s0, None, 200)[1].sum()

    g = jax.grad(ret)(0.5)
    assert math.isfinite(float(g)) and float(g) != 0.0


def test_replace_keeps_validation():
    with pytest.raises(ValueError, match="rho1"):
        make_config().replace(rho1=0.0)


def test_los_rt_env_with_a_short_episode():
    env = TrackingEnv(make_config("paper", episode_steps=1000).for_eval("los_rt", los_seed=2))
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    s = jax.jit(env.step)(s, hover_action(env.config))
    assert np.isfinite(float(s.reward))


def test_track_frame_observation_is_translation_invariant():
    cfg = make_config("practical", obs_frame="track").for_eval("los_rt")
    env = TrackingEnv(cfg)
    ps = env.reset(jax.random.PRNGKey(0)).pipeline_state
    ps = ps.replace(k=jnp.asarray(500, jnp.int32))  # past the literal start p_d(0) = 0
    shift = jnp.array([3.0, -2.0, 1.5])
    track = ps.track.replace(seg=ps.track.seg.at[:, 0].add(shift))
    moved = ps.replace(quad=ps.quad.replace(p=ps.quad.p + shift), track=track)
    o1, _ = env.observe(ps)
    o2, _ = env.observe(moved)
    np.testing.assert_allclose(o1, o2, atol=1e-5)
    ow, _ = TrackingEnv(cfg.replace(obs_frame="world")).observe(ps)
    p_d = tr.position(ps.track, ps.k, cfg.dt)
    np.testing.assert_allclose(o1[0:3], ow[0:3] - p_d, atol=1e-6)  # p - p_d,k
    np.testing.assert_allclose(o1[10:13], ow[10:13] - p_d, atol=1e-6)  # p_d,k+L - p_d,k
    np.testing.assert_allclose(o1[3:10], ow[3:10], atol=1e-6)
    np.testing.assert_allclose(o1[13:], ow[13:], atol=1e-6)
    with pytest.raises(ValueError, match="obs_frame"):
        make_config("paper", obs_frame="body")
