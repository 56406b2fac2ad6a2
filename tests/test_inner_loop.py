"""The firmware rate model (sim.inner_loop): the rate PID, mixer and motors against closed-form
responses, the Crazyflie's published loop, and the checks of its parameters."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.sim import inner_loop as il
from ttd3_jax.sim.dynamics import FirmwareState, QuadParams, QuadState, model_state, rk4_step
from ttd3_jax.sim.vehicles import CF2


def _fly(params: QuadParams, u, steps: int, dt: float) -> np.ndarray:
    """Body rates (steps, 3) after each of ``steps`` physics steps of ``dt`` under command ``u``."""
    x0 = model_state(params, QuadState.hover())

    def body(x, _):
        x = rk4_step(params, x, jnp.asarray(u, jnp.float32), dt)
        return x, x.w

    return np.asarray(jax.jit(lambda x: jax.lax.scan(body, x, None, steps)[1])(x0))


def _p_only(**loop) -> QuadParams:
    """CF2 with a P-only rate loop (no I, no D, no output clamp) and ``loop`` changes."""
    base = CF2.loop.replace(ki=(0.0,) * 3, kd=(0.0,) * 3, torque_limit=(1.0,) * 3)
    return CF2.replace(loop=base.replace(**loop))


def test_p_loop_with_instant_linear_rotors_is_a_first_order_lag():
    """With rotors far faster than the loop and thrust linear in speed, the P loop is
    J ω̇ = kp (ω_c − ω): ω(t) = ω_c (1 − exp(−t kp / J)) on every axis."""
    params = _p_only(tau_up=2e-5, tau_down=2e-5, curve=0.0)
    dt, steps, wc = 1e-5, 3000, 1.0
    for axis in range(3):
        u = [CF2.mass * CF2.gravity, 0.0, 0.0, 0.0]
        u[1 + axis] = wc
        w = _fly(params, u, steps, dt)[:, axis]
        t = dt * np.arange(1, steps + 1)
        k = params.loop.kp[axis] / params.inertia[axis]
        want = wc * (1.0 - np.exp(-k * t))
        assert np.max(np.abs(w - want)) < 0.01 * wc, axis


def test_p_loop_through_a_rotor_lag_is_the_closed_form_second_order_response():
    """P loop through first-order linear rotors (time constant τ): ω/ω_c = K / (τ s² + s + K),
    K = kp / J, whose step response and overshoot are closed form."""
    tau = 0.05
    params = _p_only(tau_up=tau, tau_down=tau, curve=0.0)
    dt, steps, wc = 1e-4, 4000, 1.0
    w = _fly(params, [CF2.mass * CF2.gravity, wc, 0.0, 0.0], steps, dt)[:, 0]
    t = dt * np.arange(1, steps + 1)
    k = params.loop.kp[0] / params.inertia[0]
    wn, zeta = math.sqrt(k / tau), 1.0 / (2.0 * math.sqrt(k * tau))
    wd = wn * math.sqrt(1.0 - zeta**2)
    want = wc * (
        1.0 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
    )
    assert np.max(np.abs(w - want)) < 0.02 * wc
    overshoot = math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta**2))
    assert abs((w.max() - wc) / wc - overshoot) < 0.02


def test_cf2_roll_step_matches_the_crazyflie_loop_through_crazyflow():
    """The cf2 vehicle's whole loop (firmware gains, rotors, quadratic thrust curve): a 2 rad/s
    roll-rate step reaches 90 % in 40-60 ms with 40-57 % overshoot, the figures the same loop
    gives through crazyflow's identified cf2x_L250 (issue 50's measurement)."""
    w = _fly(CF2, [CF2.mass * CF2.gravity, 2.0, 0.0, 0.0], 300, 1e-3)[:, 0]
    t90_ms = 1 + int(np.argmax(w >= 1.8))
    assert 40 <= t90_ms <= 60
    assert 0.40 <= w.max() / 2.0 - 1.0 <= 0.57


def test_cf2_hovers_at_the_hover_command_and_starts_with_rotors_holding_its_weight():
    x = model_state(CF2, QuadState.hover((1.0, 2.0, 3.0)))
    assert isinstance(x, FirmwareState)
    thrust, tau = il.wrench(CF2.loop, il.rotor_thrust(CF2.loop, x.motor))
    np.testing.assert_allclose(float(thrust), CF2.mass * CF2.gravity, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(tau), 0.0, atol=1e-9)
    step = jax.jit(lambda x: rk4_step(CF2, x, jnp.array([CF2.mass * CF2.gravity, 0.0, 0.0, 0.0]), 1e-3))
    for _ in range(1000):
        x = step(x)
    np.testing.assert_allclose(np.asarray(x.p), [1.0, 2.0, 3.0], atol=1e-5)
    np.testing.assert_allclose(np.asarray(x.w), 0.0, atol=1e-6)


def test_mixer_inverts_the_wrench_and_keeps_attitude_first_when_a_rotor_saturates():
    loop = CF2.loop
    thrust, tau = jnp.float32(0.3), jnp.array([2e-4, -1e-4, 5e-5], jnp.float32)
    t2, tau2 = il.wrench(loop, il.mix(loop, thrust, tau))
    np.testing.assert_allclose(float(t2), 0.3, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(tau2), np.asarray(tau), rtol=1e-4, atol=1e-9)
    # near full thrust a roll torque still comes out whole: the excess is taken off all four
    hot = il.mix(loop, jnp.float32(0.47), jnp.array([1e-3, 0.0, 0.0], jnp.float32))
    assert float(jnp.max(hot)) == pytest.approx(loop.motor_max)
    np.testing.assert_allclose(float(il.wrench(loop, hot)[1][0]), 1e-3, rtol=1e-4)
    # speed and thrust invert each other along the whole quadratic curve
    f = jnp.linspace(loop.motor_min, loop.motor_max, 9)
    np.testing.assert_allclose(
        np.asarray(il.rotor_thrust(loop, il.rotor_speed(loop, f))), np.asarray(f), rtol=1e-5
    )


def test_pid_differentiates_the_measurement_and_clamps_its_integral():
    loop = CF2.loop
    zero = jnp.zeros(3)
    cmd = jnp.array([1.0, 0.0, 0.0])
    # a setpoint step: no derivative kick (D acts on the measured rate only)
    tau, integ = il.rate_pid(loop, cmd, zero, zero, zero, 1e-3)
    np.testing.assert_allclose(float(tau[0]), loop.kp[0] * 1.0 + loop.ki[0] * 1e-3, rtol=1e-5)
    # a measured rate change: the D term opposes it
    tau, _ = il.rate_pid(loop, zero, jnp.array([0.1, 0.0, 0.0]), zero, zero, 1e-3)
    np.testing.assert_allclose(
        float(tau[0]), -loop.kp[0] * 0.1 - loop.ki[0] * 1e-4 - loop.kd[0] * 100.0, rtol=1e-5
    )
    # a persistent error winds the integral up to i_limit, no further
    for _ in range(2000):
        _, integ = il.rate_pid(loop, jnp.array([1.0, 1.0, 1.0]), zero, zero, integ, 1e-3)
    np.testing.assert_allclose(np.asarray(integ), [0.5812, 0.5812, 2.0], rtol=1e-4)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (dict(tau_up=0.0), "QuadParams.loop.tau_up must be > 0"),
        (dict(tau_down=-0.1), "QuadParams.loop.tau_down must be > 0"),
        (dict(motor_max=0.07), "QuadParams.loop.motor_max=0.07 N cannot hover"),
        (dict(motor_min=0.1), "QuadParams.loop.motor_min=0.1 N cannot hover"),
        (dict(kp=(-1e-3, 1e-3, 1e-3)), "QuadParams.loop.kp entries must be >= 0"),
        (dict(ki=(1e-3, 1e-3)), "QuadParams.loop.ki must have 3 entries"),
        (dict(curve=2.5), "QuadParams.loop.curve must be in [0, 2]"),
        (dict(arm=float("nan")), "QuadParams.loop.arm must be finite"),
    ],
)
def test_bad_inner_loop_parameters_are_refused_naming_the_field(change, field):
    with pytest.raises(ValueError) as e:
        QuadParams.create(**{**_fields(CF2), "loop": CF2.loop.replace(**change)})
    assert field in str(e.value)
    assert "\n" not in str(e.value)


def test_the_firmware_model_needs_a_loop_and_no_other_model_takes_one():
    with pytest.raises(ValueError, match="QuadParams.loop must be an InnerLoop with rate_model 'firmware'"):
        QuadParams.create(rate_model="firmware")
    with pytest.raises(ValueError, match="QuadParams.loop must be None with rate_model 'instant'"):
        QuadParams.create(loop=CF2.loop)


def _fields(q: QuadParams) -> dict:
    return {name: getattr(q, name) for name in q.__dataclass_fields__}
