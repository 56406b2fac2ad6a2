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


def hover_flight(steps: int, **changes):
    """The observed disturbance estimate (observation.disturbance_tau 0.1 s) after each of ``steps``
    control steps of the hover action of the nominal vehicle, from rest and level without OU
    wind or noise, on ``make_config("practical")`` with ``changes``; and the episode's plant."""
    from ttd3_jax.sim.env import hover_action

    cfg = make_config("practical", hover_centered_thrust=True, obs_memory=True, disturbance_tau=0.1,
                      wind_sigma=0.0, randomize_init=False, track="spiral_rt", **changes)  # fmt: skip
    env = TrackingEnv(cfg)
    s, at = env.reset(jax.random.PRNGKey(2)), env.layout.slice("disturbance")
    step = jax.jit(env.step)
    seen = [np.asarray(s.obs[at])]
    for _ in range(steps):
        s = step(s, hover_action(cfg))
        seen.append(np.asarray(s.obs[at]))
    return np.array(seen), getattr(s.pipeline_state, "plant", None), cfg


def test_the_disturbance_estimate_finds_the_wind_and_the_weight_the_nominal_model_does_not_know():
    """observation.disturbance_tau: hovering on the nominal vehicle it stays 0; under a constant
    wind acceleration w (randomization.wind_mean, drawn per axis) it rises as 1 − e^(−t/τ) to w
    (the nominal model knows neither); on a vehicle 20 % heavier than the nominal one it finds
    the thrust deficit g (1/1.2 − 1) along z."""
    d, _, cfg = hover_flight(50)
    assert np.max(np.abs(d)) < 1e-5, np.max(np.abs(d))
    d, plant, cfg = hover_flight(60, wind_mean=0.5)
    w, keep = np.asarray(plant.wind_mean), cfg.disturbance_keep
    assert np.all(np.abs(w) > 0.05) and keep == pytest.approx(np.exp(-0.1))  # (dt 10 ms, tau 0.1 s)
    np.testing.assert_array_equal(d[0], 0.0)  # zeros at reset; the first step's a_meas is its own
    np.testing.assert_allclose(d[10], (1 - keep**10) * w, rtol=0.02, atol=1e-3)  # one tau: 63 %
    np.testing.assert_allclose(d[60], w, rtol=0.01, atol=1e-3)  # six: 99.75 %
    d, plant, cfg = hover_flight(60, mass=(1.2, 1.2))
    g = cfg.vehicle.quad.gravity
    assert float(plant.quad.mass) == pytest.approx(1.2 * cfg.vehicle.quad.mass)
    np.testing.assert_allclose(d[60], [0.0, 0.0, g / 1.2 - g], rtol=0.01, atol=1e-3)


@pytest.mark.parametrize(
    "extra",
    [
        dict(hover_centered_thrust=True, mass=(0.8, 1.2), action_history_s=(0.05,), obs_noise_vel=0.05,
             obs_noise_quat=0.01, quad=QuadParams.create(rate_model="first_order")),
        dict(ref_integral_gain=3.0, thrust_map_mass=1.3, obs_noise_vel=0.02),
        dict(hover_centered_thrust=True,
             quad=QuadParams.create(thrust_units="mass_normalized", thrust_max=20.0)),
    ],
    ids=["randomised-history-noise", "nominal-linear-map", "mass-normalised"],
)  # fmt: skip
def test_the_disturbance_estimate_is_the_update_policy_json_and_fly_exported_give(extra):
    """After each control step of a flight with random actions, the observed disturbance equals
    fly_exported.py's Memory (float32, from policy.json's observation_spec.memory) and the
    update policy.json's text gives, in float64 from its numbers, from the measured v and q (the
    observation's, noise included): d = keep d + (1 − keep) ((v − v_prev) / dt − a_nom),
    a_nom = T(a) / m R(q_prev) e3 − g e3 with the nominal action map's T."""
    from experiment_scripts import experiment

    from ttd3_jax.interop.policy import memory_spec, observation_spec

    fx = experiment("fly_exported")
    cfg = make_config("practical", obs_memory=True, disturbance_tau=0.05, **extra)
    env, lay, mem = TrackingEnv(cfg), observation.layout(cfg), memory_spec(cfg)
    model, keep, dt = mem["disturbance_model"], mem["disturbance_keep"], mem["dt_s"]
    assert (
        keep == pytest.approx(np.exp(-0.01 / 0.05)) and dt == 0.01 and "a_meas - a_nom" in mem["disturbance"]
    )
    meta = dict(observation_spec=observation_spec(cfg, env.observation_size), obs_size=env.observation_size)
    memory, want = fx.Memory(meta), np.zeros(3)
    s, step = env.reset(jax.random.PRNGKey(4)), jax.jit(env.step)
    read = lambda s, name: np.asarray(s.obs[lay.slice(name)])  # noqa: E731
    v_prev, q_prev = read(s, "v").astype(np.float64), read(s, "q").astype(np.float64)
    memory.see(np.concatenate([read(s, "p"), read(s, "v"), read(s, "q"), np.zeros(3, np.float32)]))
    actions = np.random.default_rng(0).uniform(-0.6, 0.6, (25, 4)).astype(np.float32)
    for a in actions:
        s = step(s, jnp.asarray(a))
        v, q = read(s, "v").astype(np.float64), read(s, "q").astype(np.float64)
        hover, lo, hi, a0 = model["thrust_hover_N"], model["thrust_min_N"], model["thrust_max_N"], float(a[0])
        if model["hover_centered"]:
            thrust = hover + a0 * ((hi - hover) if a0 >= 0 else (hover - lo))
        else:
            thrust = lo + 0.5 * (a0 + 1.0) * (hi - lo)
        w, x, y, z = q_prev
        body_z = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        a_nom = thrust / model["mass_kg"] * body_z - np.array([0.0, 0.0, model["gravity_m_s2"]])
        want = keep * want + (1 - keep) * ((v - v_prev) / dt - a_nom)
        memory.update(a, read(s, "p"), np.zeros(3), v.astype(np.float32))
        memory.see(np.concatenate([read(s, "p"), read(s, "v"), read(s, "q"), np.zeros(3, np.float32)]))
        got = read(s, "disturbance")
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=2e-4)  # float32 against float64
        np.testing.assert_allclose(memory.disturbance, got, rtol=1e-5, atol=1e-5)
        v_prev, q_prev = v, q
    assert np.max(np.abs(want)) > 0.1  # (wind, a mass the nominal model does not know, noise)
    newton = 1.3 if "thrust_map_mass" in extra else 1.5  # the mass the map assumes, else the vehicle's
    mass = {"newton": newton, "mass_normalized": 1.0}[cfg.vehicle.quad.thrust_units]
    assert model["mass_kg"] == pytest.approx(mass)  # (1: the thrust is an acceleration)


@pytest.mark.parametrize("bad", [-0.1, 0.005, 11.0, float("nan"), float("inf")])
def test_a_bad_disturbance_tau_is_refused_naming_the_field(bad):
    with pytest.raises(
        ValueError, match=r"^EnvConfig\.observation\.disturbance_tau must be 0 \(off\) or a finite number in "
        r"\[0\.01, 10\] s, got"
    ):  # fmt: skip
        make_config("practical", obs_memory=True, disturbance_tau=bad)
    with pytest.raises(ValueError, match=r"observation\.disturbance_tau must be 0 without obs_memory"):
        make_config("practical", disturbance_tau=0.1)
