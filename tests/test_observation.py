"""The named observation layout (ttd3_jax.sim.observation): it builds the env's observation,
covers it exactly once, and names the parts only the critics see."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.sim import observation
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.sim.env import TrackingEnv

CASES = [
    dict(obs_frame=frame, obs_memory=mem, obs_privileged=priv, quad=QuadParams.create(rate_model=model))
    for frame, mem, priv, model in itertools.product(
        ("world", "track"), (False, True), (False, True), ("instant", "first_order")
    )
]


@pytest.mark.parametrize("overrides", CASES, ids=lambda o: "-".join(str(v)[:8] for v in o.values()))
def test_the_parts_cover_the_observation_exactly_once(overrides):
    cfg = make_config("practical", **overrides)
    lay = observation.layout(cfg)
    covered = np.zeros(lay.size, int)
    for part in lay.parts:
        covered[lay.slice(part.name)] += 1
        assert lay.slice(part.name).stop - lay.slice(part.name).start == part.size == len(part.entries)
    assert (covered == 1).all() and len(lay.names) == lay.size == len(set(lay.names))
    env = TrackingEnv(cfg)
    assert env.observation_size == lay.size and env.actor_observation_size == lay.actor_size
    assert env.reset(jax.random.PRNGKey(0)).obs.shape == (lay.size,)
    only = [p.name for p in lay.parts if p.critic_only]
    assert lay.critic_only == tuple(only) and bool(only) == cfg.observation.obs_privileged
    assert all(lay.slice(name).start >= lay.actor_size for name in only)  # the actor reads a prefix
    assert lay.has("omega") == (cfg.vehicle.quad.rate_model != "instant")


def test_the_observation_is_the_layouts_parts_in_order():
    cfg = make_config("paper", quad=QuadParams.create(rate_model="first_order"))
    env = TrackingEnv(cfg)
    s = env.step(env.reset(jax.random.PRNGKey(1)), jnp.array([0.3, 0.2, -0.1, 0.4]))
    lay, ps = env.layout, s.pipeline_state
    np.testing.assert_array_equal(s.obs[lay.slice("p")], ps.quad.p)
    np.testing.assert_array_equal(s.obs[lay.slice("v")], ps.quad.v)
    np.testing.assert_array_equal(s.obs[lay.slice("omega")], ps.quad.w)
    assert lay.names[:3] == ["p.x", "p.y", "p.z"] and lay.names[-3:] == ["omega.x", "omega.y", "omega.z"]
    assert [d["start"] for d in lay.describe()] == [0, 3, 6, 10, 13, 16, 17]


def test_a_layout_refuses_parts_that_do_not_match_it():
    lay = observation.layout(make_config("paper"))
    with pytest.raises(ValueError, match="do not match the layout"):
        lay.build({"p": jnp.zeros(3)}, jnp.concatenate)
    with pytest.raises(KeyError, match="wind"):
        lay.slice("wind")
    late = observation.Part("wind", ("w",), "m/s^2", critic_only=True)
    with pytest.raises(ValueError, match="critics-only parts must come last"):
        observation.ObsLayout((late, *lay.parts))
    with pytest.raises(ValueError, match="unique"):
        observation.ObsLayout((*lay.parts, dataclasses.replace(lay.parts[0])))


def test_the_error_integral_integrates_the_observed_position_as_policy_json_says():
    """obs_memory's error integral follows policy.json's recurrence with the *measured* position
    (noise and bias included): a vehicle can keep it, and it does not leak the true state."""
    from ttd3_jax.interop.policy import memory_spec

    cfg = make_config("practical", obs_memory=True, obs_noise_pos=0.01, pos_bias=(0.02, 0.0, -0.01))
    env, lay, mem = TrackingEnv(cfg), observation.layout(cfg), memory_spec(cfg)
    s = env.reset(jax.random.PRNGKey(3))
    a = jnp.array([0.1, 0.05, -0.05, 0.0])
    for _ in range(5):
        before = np.asarray(s.obs[lay.slice("error_integral")])
        s = env.step(s, a)
        p_rel = np.asarray(s.obs[lay.slice("p")])  # measured p - p_d,k (obs_frame "track")
        want = mem["leak"] * before + mem["dt_s"] * -p_rel
        np.testing.assert_allclose(np.asarray(s.obs[lay.slice("error_integral")]), want, rtol=1e-5, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(s.obs[lay.slice("last_action")]), np.asarray(a))


@pytest.mark.parametrize(
    "extra", [{}, {"ref_integral_gain": 3.0}, {"mass": (0.9, 1.1)}], ids=["memory", "integral", "randomised"]
)
def test_the_action_history_is_the_leaky_average_policy_json_gives(extra):
    """observation.action_history_s: after each control step h_j = keep_j h_j + (1 - keep_j) a with
    policy.json's keep_j, from zeros at reset; with or without integral action or randomisation."""
    from ttd3_jax.interop.policy import memory_spec

    cfg = make_config("practical", obs_memory=True, action_history_s=(0.05, 0.2), **extra)
    env, lay = TrackingEnv(cfg), observation.layout(cfg)
    keep = np.asarray(memory_spec(cfg)["action_history_keep"], np.float32)[:, None]
    assert np.allclose(keep[:, 0], np.exp(-cfg.control_dt / np.array([0.05, 0.2])))
    s, want = env.reset(jax.random.PRNGKey(1)), np.zeros((2, 4), np.float32)
    np.testing.assert_array_equal(np.asarray(s.obs[lay.slice("action_history")]), want.ravel())
    for a in ([0.3, -0.2, 0.1, 0.0], [-0.1, 0.4, 0.0, 0.2], [0.0, 0.0, -0.3, 0.1]):
        s = env.step(s, jnp.asarray(a))
        want = keep * want + (1 - keep) * np.asarray(a, np.float32)
        np.testing.assert_allclose(np.asarray(s.obs[lay.slice("action_history")]), want.ravel(), atol=1e-7)


@pytest.mark.parametrize("bad", [(0.1, 0.05), (0.0,), (3.0,)])
def test_a_bad_action_history_is_refused_naming_the_field(bad):
    with pytest.raises(ValueError, match=r"observation\.action_history_s must be increasing time constants"):
        make_config("practical", obs_memory=True, action_history_s=bad)
    with pytest.raises(ValueError, match=r"action_history_s must be \(\) without obs_memory"):
        make_config("practical", action_history_s=(0.1,))


def test_the_preview_shows_the_actor_the_reference_ahead_exactly():
    """observation.preview_s: for each time t, p_d(k + L + t/dt) − p_d(k + L), read by the actor
    (before the critics-only parts), on a known circle and after some steps."""
    cfg = make_config("practical", preview_s=(0.1, 0.5), obs_privileged=True, track="spiral_rt")
    env = TrackingEnv(cfg)
    lay = env.layout
    assert [p.name for p in lay.parts if p.name.startswith("preview")] == ["preview_0.1s", "preview_0.5s"]
    assert lay.slice("preview_0.5s").stop == lay.actor_size == lay.slice("wind").start
    s = env.reset(jax.random.PRNGKey(0))
    for _ in range(7):
        s = env.step(s, jnp.zeros(4))
    ps, look = s.pipeline_state, cfg.observation.lookahead_k
    ahead = tr.position(ps.track, ps.k + look, cfg.dt)
    for t in (0.1, 0.5):
        want = tr.position(ps.track, ps.k + look + round(t / cfg.dt), cfg.dt) - ahead
        np.testing.assert_allclose(s.obs[lay.slice(f"preview_{t:g}s")], want, rtol=0, atol=1e-6)
        assert float(jnp.linalg.norm(want)) > 0.01  # the spiral moves: the preview is not a constant
    assert cfg.horizon_steps == cfg.episode_steps + look + 2 + round(1.0 / cfg.dt)  # privileged reaches 1 s


@pytest.mark.parametrize("bad", [(0.0,), (-0.1,), (0.5, 0.1), (0.2, 0.2), (2.5,), (float("nan"),)])
def test_a_bad_preview_is_refused_naming_the_field(bad):
    with pytest.raises(ValueError, match=r"observation\.preview_s must be increasing times in \(0, 2\] s"):
        make_config("practical", preview_s=bad)


def test_a_preview_lengthens_the_track_to_its_farthest_point():
    base = make_config("practical")
    assert make_config("practical", preview_s=(0.25, 1.5)).horizon_steps == base.horizon_steps + 1500


def test_the_reference_integral_shifts_the_observed_reference_as_policy_json_says():
    """observation.ref_integral_gain: ref_int += dt (p_d,k − p) per axis within ±band after each step, and
    the parts between the vehicle and the reference read p − s, s = clip(gain ref_int, ±limit);
    the rest of the observation is the one without the integral."""
    from ttd3_jax.interop.policy import memory_spec

    base = make_config("practical", obs_memory=True, track="spiral_rt", randomize_init=False)
    cfg = base.replace(ref_integral_gain=40.0, ref_integral_band=0.003, ref_integral_limit=0.001)
    env, plain, lay = TrackingEnv(cfg), TrackingEnv(base), observation.layout(cfg)
    ri = memory_spec(cfg)["reference_integral"]
    assert (ri["gain_per_s"], ri["band_m"], ri["limit_m"]) == (40.0, 0.003, 0.001)
    s = env.reset(jax.random.PRNGKey(0))
    s0 = plain.reset(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(s.obs, s0.obs)  # ref_int = 0 at reset
    a = jnp.array([0.3, 0.2, -0.1, 0.0])  # drifts off the spiral: errors leave the band
    ref_int, outside, limited = np.zeros(3), False, False
    for _ in range(12):
        s, s0 = env.step(s, a), plain.step(s0, a)  # the same flight: the shift changes no dynamics
        ps = s.pipeline_state
        e = np.asarray(tr.position(ps.track, ps.k, cfg.dt) - ps.quad.p)
        outside |= bool(np.any(np.abs(e) >= 0.003))
        ref_int = ref_int + memory_spec(cfg)["dt_s"] * np.where(np.abs(e) < 0.003, e, 0.0)
        np.testing.assert_allclose(np.asarray(ps.ref_int), ref_int, rtol=1e-5, atol=1e-9)
        shift = np.clip(40.0 * ref_int, -0.001, 0.001)
        limited |= bool(np.any(np.abs(40.0 * ref_int) > 0.001))
        o, o0 = np.asarray(s.obs), np.asarray(s0.obs)
        np.testing.assert_allclose(o[lay.slice("p")], o0[lay.slice("p")] - shift, atol=1e-6)
        np.testing.assert_allclose(
            o[lay.slice("p_ahead_error")], o0[lay.slice("p_ahead_error")] + shift, atol=1e-6
        )
        np.testing.assert_allclose(o[lay.slice("error")], np.linalg.norm(e + shift), atol=1e-6)
        for name in ("v", "q", "p_ahead", "last_action", "error_integral"):
            np.testing.assert_array_equal(o[lay.slice(name)], o0[lay.slice(name)])
    assert outside and limited  # the band and the limit were both exercised


def test_a_classical_controller_senses_the_true_position_under_the_reference_integral():
    """sensed_controller rebuilds p from the observation: the policy's shift is taken back out."""
    from ttd3_jax.control.closed_loop import Controller, sensed_controller

    cfg = make_config("practical", obs_memory=True, ref_integral_gain=50.0, randomize_init=False)
    env = TrackingEnv(cfg.for_eval("spiral_rt"))  # no noise: sensed = true
    probe = Controller(init=lambda s: (), act=lambda c, s: (jnp.zeros(4), s.pipeline_state.quad.p))
    sensed = sensed_controller(probe, env.config)
    s = env.reset(jax.random.PRNGKey(0))
    for _ in range(10):
        s = env.step(s, jnp.array([0.3, 0.2, 0.0, 0.0]))
    assert float(jnp.max(jnp.abs(s.pipeline_state.ref_int))) > 0  # a shift is in the observation
    np.testing.assert_allclose(sensed.act((), s)[1], s.pipeline_state.quad.p, rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    "field, bad, allowed",
    [
        ("ref_integral_gain", -1.0, r"a finite number in \[0, 100\] 1/s"),
        ("ref_integral_gain", float("nan"), r"a finite number in \[0, 100\] 1/s"),
        ("ref_integral_band", 0.0, r"a finite number in \(0, 1\] m"),
        ("ref_integral_limit", 2.0, r"a finite number in \(0, 1\] m"),
    ],
)
def test_a_bad_reference_integral_is_refused_naming_the_field(field, bad, allowed):
    with pytest.raises(ValueError, match=rf"EnvConfig\.observation\.{field} must be {allowed}"):
        make_config("practical", obs_memory=True, **{field: bad})


def test_the_reference_integral_needs_the_memory():
    with pytest.raises(ValueError, match=r"observation\.ref_integral_gain must be 0 without obs_memory"):
        make_config("practical", ref_integral_gain=2.0)
