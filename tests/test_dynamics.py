"""Physics tests for :mod:`ttd3_jax.sim.dynamics` (spec §2.1, rows D1-D7).

Conventions under test: world z up with gravity subtracted, Hamilton quaternions
stored scalar first and mapping body -> world, body rates in the body frame
(``q̇ = ½ q ⊗ [0, ω]``), thrust in N (``"newton"``) or m/s^2
(``"mass_normalized"``), RK4 with zero-order-hold control and optional
renormalisation of ``q``.

Everything runs on the CPU (an autouse fixture sets the default device).
Multi-step integrations go through the jitted helpers :func:`simulate`
(``lax.fori_loop``; the step count is traced, so one compile serves every
horizon) and :func:`trajectory` (``lax.scan``, static length, keeps every
state).  Gradients go through the un-jitted ``_scan`` inside ``jax.grad`` /
``jax.jacfwd``.  Float64 cases build their arrays inside
``jax.enable_x64(True)``.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import Primitive

from ttd3_jax.sim import dynamics as dyn
from ttd3_jax.sim.dynamics import QuadParams, QuadState

G = 9.81
EZ = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- helpers


@pytest.fixture(autouse=True)
def _on_cpu():
    """Run every test of this module on the CPU, without touching the global platform setting."""
    with jax.default_device(jax.devices("cpu")[0]):
        yield


@partial(jax.jit, static_argnames=("renormalize",))
def simulate(params, x0, u, dt, n, accel_ext=None, renormalize=True):
    """State after ``n`` RK4 steps of ``dt`` under constant control ``u``."""

    def body(_, x):
        return dyn.rk4_step(params, x, u, dt, accel_ext, renormalize=renormalize)

    return jax.lax.fori_loop(0, n, body, x0)


def _scan(params, x0, u, dt, n, accel_ext=None, renormalize=True):
    def body(x, _):
        x = dyn.rk4_step(params, x, u, dt, accel_ext, renormalize=renormalize)
        return x, x

    return jax.lax.scan(body, x0, None, length=n)


@partial(jax.jit, static_argnames=("n", "renormalize"))
def trajectory(params, x0, u, dt, n, accel_ext=None, renormalize=True):
    """``(final state, states after steps 1..n stacked on axis 0)`` via ``lax.scan``."""
    return _scan(params, x0, u, dt, n, accel_ext, renormalize)


def make_state(p=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0), dtype=None):
    """A :class:`QuadState` from array-likes, in the default float dtype unless told."""
    dtype = dtype or jnp.zeros(()).dtype
    return QuadState(
        p=jnp.asarray(p, dtype), v=jnp.asarray(v, dtype), q=jnp.asarray(q, dtype), w=jnp.asarray(w, dtype)
    )


def axis_angle(axis, angle):
    """Unit quaternion (numpy float64) for ``angle`` rad about ``axis`` (any length)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def random_unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def lambda_matrix(w):
    """Λ(ω) exactly as written in spec §2.1."""
    wx, wy, wz = w
    return np.array([[0, -wx, -wy, -wz], [wx, 0, wz, -wy], [wy, -wz, 0, wx], [wz, wy, -wx, 0]])


def max_state_diff(a: QuadState, b: QuadState) -> float:
    return max(
        float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


TILT = axis_angle([0.6, 0.0, 0.8], 0.7)  # a generic tilted attitude


# --------------------------------------------------------------------------- 1. hover


@pytest.mark.parametrize("thrust_units", ["newton", "mass_normalized"])
def test_hover_at_trim_stays_put(thrust_units):
    params = QuadParams.create(thrust_units=thrust_units, thrust_max=20.0)
    expected_hover = G * 1.5 if thrust_units == "newton" else G
    assert params.hover_thrust == pytest.approx(expected_hover)

    p0 = np.array([1.0, -2.0, 3.0])
    x0 = QuadState.hover(p=p0)
    u = jnp.array([params.hover_thrust, 0.0, 0.0, 0.0])
    x = simulate(params, x0, u, 1e-3, 3000)

    assert x.p.dtype == jnp.float32 and x.q.dtype == jnp.float32  # float32 is the default
    np.testing.assert_allclose(x.p, p0, rtol=0, atol=1e-5)
    np.testing.assert_allclose(x.v, 0.0, rtol=0, atol=1e-5)
    np.testing.assert_allclose(x.q, [1.0, 0.0, 0.0, 0.0], rtol=0, atol=1e-7)


def test_thrust_units_scale_acceleration():
    """The same thrust number is divided by the mass only under ``"newton"``."""
    x0 = QuadState.hover()
    u = jnp.array([12.0, 0.0, 0.0, 0.0])
    for units, accel in (("newton", 12.0 / 1.5 - G), ("mass_normalized", 12.0 - G)):
        params = QuadParams.create(thrust_units=units)
        x = simulate(params, x0, u, 1e-3, 1000)
        np.testing.assert_allclose(x.v, [0.0, 0.0, accel], atol=1e-4)
        np.testing.assert_allclose(x.p, [0.0, 0.0, 0.5 * accel], atol=1e-4)


# --------------------------------------------------------------------------- 2. free fall


def _free_fall_case(dtype):
    p0, v0 = np.array([0.5, -1.0, 2.0]), np.array([1.0, -2.0, 3.0])
    x0 = make_state(p=p0, v=v0, q=TILT, w=(0.4, 0.1, -0.2), dtype=dtype)
    u = jnp.array([0.0, 0.3, -0.5, 0.8], dtype)  # zero thrust; the vehicle may spin freely
    return p0, v0, x0, u


@pytest.mark.parametrize("rate_model", ["instant", "torque"])
def test_free_fall_matches_closed_form_float32(rate_model):
    params = QuadParams.create(rate_model=rate_model)
    p0, v0, x0, u = _free_fall_case(jnp.float32)
    t = 1.0
    x = simulate(params, x0, u, 1e-3, 1000)
    assert x.p.dtype == jnp.float32
    np.testing.assert_allclose(x.p, p0 + v0 * t - 0.5 * G * t**2 * EZ, rtol=0, atol=1e-4)
    np.testing.assert_allclose(x.v, v0 - G * t * EZ, rtol=0, atol=1e-4)


@pytest.mark.parametrize("accel_ext", [None, (0.3, -0.2, 0.1)], ids=["no_ext", "ext"])
def test_free_fall_matches_closed_form_float64(accel_ext):
    """RK4 is exact on the quadratic ballistic path: only round-off remains.

    A constant external acceleration simply adds to gravity.
    """
    params = QuadParams.create()
    a = -G * EZ + (0.0 if accel_ext is None else np.asarray(accel_ext))
    with jax.enable_x64(True):
        p0, v0, x0, u = _free_fall_case(jnp.float64)
        t = 1.0
        ext = None if accel_ext is None else jnp.asarray(accel_ext)
        x = simulate(params, x0, u, 1e-3, 1000, ext)
        assert x.p.dtype == jnp.float64
        np.testing.assert_allclose(x.p, p0 + v0 * t + 0.5 * a * t**2, rtol=0, atol=1e-10)
        np.testing.assert_allclose(x.v, v0 + a * t, rtol=0, atol=1e-10)


# --------------------------------------------------------------------------- 3. constant body rates


@pytest.mark.parametrize(
    "q0", [np.array([1.0, 0.0, 0.0, 0.0]), axis_angle([0.0, 1.0, 0.3], 0.9)], ids=["level", "tilted"]
)
def test_constant_body_rates_give_quaternion_exponential(q0):
    """``q(T) = q0 ⊗ exp(ωT/2)``: right multiplication, i.e. ω in the body frame.

    The tilted start distinguishes body rates from world rates (``exp ⊗ q0``).
    """
    params = QuadParams.create()  # instant rate model
    w = np.array([0.3, -0.5, 0.8])
    T, n = 3.0, 3000
    x0 = make_state(q=q0)
    x = simulate(params, x0, jnp.array([5.0, *w]), T / n, n)

    nw = np.linalg.norm(w)
    q_exp = np.concatenate([[math.cos(nw * T / 2)], math.sin(nw * T / 2) * w / nw])
    expected = dyn.quat_mul(jnp.asarray(q0), jnp.asarray(q_exp))
    np.testing.assert_allclose(x.q, expected, rtol=0, atol=1e-5)
    np.testing.assert_allclose(x.w, w, rtol=1e-7)
    if q0[0] != 1.0:  # world-frame rates would land somewhere else
        wrong = dyn.quat_mul(jnp.asarray(q_exp), jnp.asarray(q0))
        assert float(jnp.max(jnp.abs(x.q - wrong))) > 1e-2


def test_quat_rate_equals_half_q_times_omega():
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        for q, w in zip(random_unit_quats(rng, 16), rng.normal(scale=3.0, size=(16, 3)), strict=True):
            qd = np.asarray(dyn.quat_rate(jnp.asarray(q), jnp.asarray(w)))
            via_product = 0.5 * np.asarray(dyn.quat_mul(jnp.asarray(q), jnp.asarray([0.0, *w])))
            np.testing.assert_allclose(qd, via_product, rtol=0, atol=1e-14)
            np.testing.assert_allclose(qd, 0.5 * lambda_matrix(w) @ q, rtol=0, atol=1e-14)  # spec §2.1
            assert abs(qd @ q) < 1e-14  # tangent to the unit sphere: the norm is conserved


# --------------------------------------------------------------------------- 4. RK4 order


@pytest.mark.parametrize("renormalize", [True, False], ids=["renormalize", "raw"])
@pytest.mark.parametrize("rate_model", ["first_order", "torque"])
def test_rk4_global_error_is_fourth_order(rate_model, renormalize):
    """err(dt) / err(dt/2) ≈ 2^4 = 16 on a smooth, fully coupled case.

    Renormalising keeps order 4 because the exact flow stays on the unit sphere,
    so the projection moves ``q`` by no more than the O(dt^5) local error; the
    ``renormalize`` case checks this.  The torque command is small enough that
    the |η| clip never binds (a clip would make the right-hand side non-smooth).
    """
    params = QuadParams.create(rate_model=rate_model)
    T = 1.0
    with jax.enable_x64(True):
        x0 = make_state(p=(0.5, -1.0, 2.0), v=(1.0, -2.0, 3.0), q=TILT, w=(0.2, 0.1, -0.3))
        u = jnp.array([12.0, 0.8, -0.6, 0.5])  # thrust != hover (14.715 N)
        accel = jnp.array([0.3, -0.2, 0.1])
        # η never reaches the clip along the way, so the model is smooth:
        if rate_model == "torque":
            _, traj = trajectory(params, x0, u, 1e-3, 1000, accel)
            J = np.asarray(params.inertia)
            w = np.asarray(traj.w)
            eta = J * np.asarray(params.k_rate) * (np.asarray(u[1:]) - w) + np.cross(w, J * w)
            assert np.all(np.abs(eta) < 0.9 * np.asarray(params.torque_max))

        def run(dt):
            n = round(T / dt)
            return simulate(params, x0, u, T / n, n, accel, renormalize=renormalize)

        ref = run(0.01 / 64)
        for dt in (0.01, 0.005):
            err_coarse = max_state_diff(run(dt), ref)
            err_fine = max_state_diff(run(dt / 2), ref)
            assert err_fine > 1e-13, "errors too close to round-off to measure the order"
            assert 12.0 <= err_coarse / err_fine <= 20.0, (dt, err_coarse, err_fine)


# --------------------------------------------------------------------------- 5. quaternion norm


def test_quaternion_norm_under_tumbling():
    params = QuadParams.create(rate_max=10.0)
    x0 = make_state(q=TILT)
    u = jnp.array([5.0, 5.0, -4.0, 3.0])

    x = simulate(params, x0, u, 1e-3, 3000, renormalize=True)
    assert x.q.dtype == jnp.float32
    assert abs(float(jnp.linalg.norm(x.q)) - 1.0) < 1e-6

    # Without the projection the norm drifts, but only by float32 round-off.
    x_raw = simulate(params, x0, u, 1e-3, 3000, renormalize=False)
    drift = abs(float(jnp.linalg.norm(x_raw.q)) - 1.0)
    assert np.isfinite(drift) and drift < 1e-4
    # Both runs follow the same rotation.
    np.testing.assert_allclose(x_raw.q, x.q, atol=1e-4)
    assert float(jnp.max(jnp.abs(x.q - x0.q))) > 0.1  # it really tumbled


def test_renormalize_projects_quaternion_onto_unit_sphere():
    """One step from a non-unit ``q``: projected with ``renormalize=True``, left alone otherwise."""
    params = QuadParams.create()
    x0 = make_state(q=1.1 * TILT)
    u = jnp.array([10.0, 0.5, -0.4, 0.3])
    projected = dyn.rk4_step(params, x0, u, 1e-3)
    raw = dyn.rk4_step(params, x0, u, 1e-3, renormalize=False)
    assert float(jnp.linalg.norm(projected.q)) == pytest.approx(1.0, abs=1e-6)
    assert float(jnp.linalg.norm(raw.q)) == pytest.approx(1.1, abs=1e-5)
    np.testing.assert_allclose(projected.q, raw.q / jnp.linalg.norm(raw.q), atol=1e-7)


# --------------------------------------------------------------------------- 6. gradients


def _final_position(params, z, n=100, dt=0.01):
    """Final position after ``n`` steps as a function of ``z = [thrust, v0 (3), ω_cmd (3)]``."""
    x0 = make_state(p=(0.1, 0.2, 0.3), v=z[1:4], q=TILT, w=(0.0, 0.0, 0.0), dtype=z.dtype)
    u = jnp.concatenate([z[:1], z[4:7]])
    x, _ = _scan(params, x0, u, dt, n)
    return x.p


def _central_difference(f, z, eps):
    cols = []
    for i in range(z.shape[0]):
        e = np.zeros(z.shape[0])
        e[i] = eps
        cols.append((np.asarray(f(z + e)) - np.asarray(f(z - e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def test_gradients_through_rk4_match_finite_differences():
    """Forward- and reverse-mode derivatives of the final position after 100 steps
    w.r.t. thrust, initial velocity, rate command and mass agree with central differences."""
    params = QuadParams.create(rate_model="first_order")
    with jax.enable_x64(True):
        z = jnp.array([12.0, 1.0, -0.5, 0.3, 0.4, -0.7, 0.2])
        f = jax.jit(lambda z, mass=1.5: _final_position(params.replace(mass=mass), z))

        jac = np.asarray(jax.jacfwd(f)(z))
        fd = _central_difference(f, np.asarray(z), 1e-6)
        assert np.all(np.isfinite(jac))
        np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)
        assert np.all(np.abs(jac[:, 4:]) > 1e-3)  # the rate command really moves the vehicle

        # Reverse mode, through the params pytree as well.
        grad_z, grad_params = jax.jit(jax.grad(lambda z, prm: _final_position(prm, z)[2], argnums=(0, 1)))(
            z, params
        )
        np.testing.assert_allclose(grad_z, jac[2], rtol=1e-10, atol=1e-12)
        h = 1e-6
        fd_mass = (f(z, 1.5 + h)[2] - f(z, 1.5 - h)[2]) / (2 * h)
        assert float(grad_params.mass) == pytest.approx(float(fd_mass), rel=1e-6)
        assert abs(float(grad_params.mass)) > 1e-2


def test_gradient_of_level_climb_is_analytic():
    """Level, ω = 0: p_z(T) = ½ (f/m - g) T² exactly, so the gradients are known."""
    params = QuadParams.create()
    T, n = 1.0, 100
    with jax.enable_x64(True):

        def height(thrust, v0, prm):
            x, _ = _scan(prm, make_state(v=v0), jnp.stack([thrust, 0.0, 0.0, 0.0]), T / n, n)
            return x.p[2]

        thrust, v0 = jnp.float64(12.0), jnp.zeros(3)
        d_thrust, d_v0, d_params = jax.jit(jax.jacfwd(height, argnums=(0, 1, 2)))(thrust, v0, params)
        m = params.mass
        assert float(d_thrust) == pytest.approx(T**2 / (2 * m), rel=1e-10)
        np.testing.assert_allclose(d_v0, [0.0, 0.0, T], rtol=1e-10, atol=1e-12)
        assert float(d_params.mass) == pytest.approx(-12.0 * T**2 / (2 * m**2), rel=1e-10)
        assert float(d_params.gravity) == pytest.approx(-(T**2) / 2, rel=1e-10)


def test_gradient_in_float32_is_finite():
    params = QuadParams.create()
    z = jnp.array([12.0, 1.0, -0.5, 0.3, 0.4, -0.7, 0.2], jnp.float32)
    g = jax.jit(jax.grad(lambda z: jnp.sum(_final_position(params, z) ** 2)))(z)
    assert g.dtype == jnp.float32
    assert np.all(np.isfinite(g)) and float(jnp.max(jnp.abs(g))) > 0


# --------------------------------------------------------------------------- 7. batching


def test_vmap_over_states_and_controls_matches_loop():
    params = QuadParams.create(rate_model="first_order")
    rng = np.random.default_rng(1)
    b = 5
    xs = make_state(
        p=rng.normal(size=(b, 3)),
        v=rng.normal(size=(b, 3)),
        q=random_unit_quats(rng, b),
        w=rng.normal(size=(b, 3)),
    )
    us = jnp.asarray(np.c_[rng.uniform(5.0, 18.0, b), rng.uniform(-3.0, 3.0, (b, 3))], jnp.float32)

    step = jax.jit(dyn.rk4_step)
    one_step = jax.vmap(step, in_axes=(None, 0, 0, None))(params, xs, us, 1e-2)
    many = jax.vmap(simulate, in_axes=(None, 0, 0, None, None))(params, xs, us, 1e-2, 50)
    for i in range(b):
        xi = jax.tree.map(lambda a, i=i: a[i], xs)
        ref_one = step(params, xi, us[i], 1e-2)
        ref_many = simulate(params, xi, us[i], 1e-2, 50)
        for got, ref in ((one_step, ref_one), (many, ref_many)):
            got_i = jax.tree.map(lambda a, i=i: a[i], got)
            assert max_state_diff(got_i, ref) < 1e-5
    assert float(jnp.max(jnp.abs(many.p[0] - many.p[1]))) > 1e-2  # the batch entries differ


def test_vmap_over_params_with_array_mass():
    params = QuadParams.create()
    masses = jnp.array([1.2, 1.5, 1.8])
    batched = params.replace(mass=masses)
    axes = jax.tree.map(lambda _: None, params).replace(mass=0)

    thrust, T, n = 10.0, 1.0, 1000
    x0 = QuadState.hover()
    u = jnp.array([thrust, 0.0, 0.0, 0.0])
    x = jax.vmap(simulate, in_axes=(axes, None, None, None, None))(batched, x0, u, T / n, n)

    assert x.p.shape == (3, 3)
    z = np.asarray(x.p[:, 2])
    np.testing.assert_allclose(z, 0.5 * (thrust / np.asarray(masses) - G) * T**2, atol=1e-4)
    assert z[0] > z[1] > z[2]  # heavier falls faster under equal thrust in newtons
    for i, m in enumerate([1.2, 1.5, 1.8]):
        single = simulate(QuadParams.create(mass=m), x0, u, T / n, n)
        assert max_state_diff(jax.tree.map(lambda a, i=i: a[i], x), single) < 1e-5


# --------------------------------------------------------------------------- 8. rate models


def test_instant_rate_model_sets_rate_in_one_step():
    params = QuadParams.create(rate_model="instant")
    w_cmd = np.array([1.0, -2.0, 0.5])
    x = dyn.rk4_step(params, QuadState.hover(), jnp.array([10.0, *w_cmd]), 1e-3)
    np.testing.assert_array_equal(x.w, w_cmd.astype(np.float32))
    # ... and that rate already turned the attitude during the step.
    np.testing.assert_allclose(x.q[1:], 0.5 * w_cmd * 1e-3, rtol=1e-4)

    lagged = dyn.rk4_step(
        QuadParams.create(rate_model="first_order"), QuadState.hover(), jnp.array([10.0, *w_cmd]), 1e-3
    )
    assert float(jnp.max(jnp.abs(lagged.w - w_cmd))) > 0.5  # the other models lag


def test_first_order_rate_model_time_constant():
    tau = 0.03
    params = QuadParams.create(rate_model="first_order", tau_rate=tau)
    w_cmd = np.array([1.0, -2.0, 0.5])
    dt, n = 1e-3, 150  # 5 tau
    _, traj = trajectory(params, QuadState.hover(), jnp.array([10.0, *w_cmd]), dt, n)
    t = dt * np.arange(1, n + 1)[:, None]

    np.testing.assert_allclose(traj.w, w_cmd * (1 - np.exp(-t / tau)), rtol=0, atol=1e-5)
    err_tau = np.abs(np.asarray(traj.w[29]) - w_cmd) / np.abs(w_cmd)  # t = tau
    np.testing.assert_allclose(err_tau, math.exp(-1.0), atol=1e-4)
    err_final = np.abs(np.asarray(traj.w[-1]) - w_cmd) / np.abs(w_cmd)  # t = 5 tau
    assert np.all(err_final < 0.01)


def test_torque_rate_model_converges_with_bounded_torque():
    params = QuadParams.create(rate_model="torque")
    J = np.asarray(params.inertia)
    eta_max = np.asarray(params.torque_max)
    w_cmd = np.array([6.0, -6.0, 6.0])  # large step: J K Δω exceeds |η|max on every axis
    assert np.all(J * np.asarray(params.k_rate) * np.abs(w_cmd) > eta_max)

    dt, n = 1e-3, 2000
    _, traj = trajectory(params, QuadState.hover(), jnp.array([10.0, *w_cmd]), dt, n)
    w = np.concatenate([np.zeros((1, 3)), np.asarray(traj.w, np.float64)])

    # Torque actually applied, recovered from the integrated rates: J ω̇ + ω × Jω.
    w_dot = np.diff(w, axis=0) / dt
    w_mid = 0.5 * (w[1:] + w[:-1])
    eta = J * w_dot + np.cross(w_mid, J * w_mid)
    assert np.all(np.abs(eta) <= eta_max + 1e-2)
    assert np.all(np.abs(eta).max(axis=0) >= 0.99 * eta_max)  # the clip was active
    np.testing.assert_allclose(w_dot[0], np.sign(w_cmd) * eta_max / J, rtol=1e-3)  # gyro = 0 at rest

    np.testing.assert_allclose(w[-1], w_cmd, atol=1e-3)


# --------------------------------------------------------------------------- 9. validation


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"mass": 0.0}, r"QuadParams\.mass must be > 0"),
        ({"mass": -1.0}, r"QuadParams\.mass must be > 0"),
        ({"mass": float("nan")}, r"QuadParams\.mass must be finite"),
        ({"gravity": 0.0}, r"QuadParams\.gravity must be > 0"),
        ({"gravity": -9.81}, r"QuadParams\.gravity must be > 0"),
        ({"tau_rate": 0.0}, r"QuadParams\.tau_rate must be > 0"),
        ({"thrust_min": 5.0, "thrust_max": 4.0}, r"QuadParams\.thrust_min must be < thrust_max"),
        ({"thrust_min": -1.0}, r"QuadParams\.thrust_min must be >= 0"),
        ({"rate_min": 2.0, "rate_max": 1.0}, r"QuadParams\.rate_min must be < rate_max"),
        ({"rate_min": 0.5, "rate_max": 6.0}, r"body-rate range must contain 0"),
        (
            {"rate_model": "pid"},
            r"QuadParams\.rate_model must be one of \('instant', 'first_order', 'torque', 'firmware'\)",
        ),
        ({"thrust_units": "kgf"}, r"QuadParams\.thrust_units must be one of \('newton', 'mass_normalized'\)"),
        ({"thrust_max": 14.0}, r"QuadParams\.thrust_max=14\.0 cannot lift.*thrust_max > hover thrust"),
        (
            {"thrust_units": "mass_normalized", "thrust_max": 9.0},
            r"QuadParams\.thrust_max=9\.0 cannot lift.*9\.810 \(mass_normalized\).*thrust_max > hover thrust",
        ),
        ({"inertia": (0.03, 0.03)}, r"QuadParams\.inertia must have 3 entries"),
        ({"inertia": (0.03, 0.03, 0.05, 0.01)}, r"QuadParams\.inertia must have 3 entries"),
        ({"inertia": (0.03, -0.03, 0.05)}, r"QuadParams\.inertia entries must be > 0"),
        ({"torque_max": (2.2, 1.3)}, r"QuadParams\.torque_max must have 3 entries"),
    ],
)
def test_create_rejects_bad_values(overrides, match):
    with pytest.raises(ValueError, match=match):
        QuadParams.create(**overrides)


def test_create_rejects_scalar_inertia():
    with pytest.raises(ValueError, match=r"QuadParams\.inertia must have 3 entries"):
        QuadParams.create(inertia=0.03)


def test_validation_runs_without_any_jax_computation(monkeypatch):
    """``create`` validates in plain Python: no primitive is bound, so nothing is traced or compiled."""

    def forbidden(self, *args, **kwargs):
        raise AssertionError(f"JAX primitive {self.name!r} bound during validation")

    monkeypatch.setattr(Primitive, "bind", forbidden)
    with pytest.raises(AssertionError, match="bound during validation"):  # the guard works
        jnp.zeros(3) + 1.0

    with pytest.raises(ValueError, match="mass"):
        QuadParams.create(mass=-1.0)
    with pytest.raises(ValueError, match="thrust_max"):
        QuadParams.create(thrust_max=10.0)
    QuadParams.create(rate_model="torque", thrust_units="mass_normalized")  # valid values pass too


def test_create_accepts_valid_mass_normalized_limits():
    """14 m/s^2 lifts any vehicle under ``mass_normalized`` although 14 N cannot lift 1.5 kg."""
    params = QuadParams.create(thrust_units="mass_normalized", thrust_max=14.0)
    assert params.hover_thrust == pytest.approx(G)


# --------------------------------------------------------------------------- 10. rotations


def test_rotation_matrix_body_z_and_quat_rotate_agree():
    rng = np.random.default_rng(2)

    @jax.jit
    def compute(q, x):
        a, b = q[:32], q[32:]
        return {
            "R": dyn.quat_to_rotmat(q),
            "R_neg": dyn.quat_to_rotmat(-q),
            "rotated": dyn.quat_rotate(q, x),
            "body_z": dyn.body_z(q),
            "rotated_ez": dyn.quat_rotate(q, jnp.broadcast_to(jnp.asarray(EZ, q.dtype), x.shape)),
            "R_ab": dyn.quat_to_rotmat(dyn.quat_mul(a, b)),
            "q_qconj": dyn.quat_mul(q, dyn.quat_conj(q)),
        }

    with jax.enable_x64(True):
        x = rng.normal(size=(64, 3))
        out = jax.tree.map(np.asarray, compute(jnp.asarray(random_unit_quats(rng, 64)), jnp.asarray(x)))
    R = out["R"]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(out["rotated"], np.einsum("nij,nj->ni", R, x), atol=1e-12)
    np.testing.assert_allclose(out["body_z"], R[:, :, 2], atol=1e-12)
    np.testing.assert_allclose(out["body_z"], out["rotated_ez"], atol=1e-12)
    np.testing.assert_allclose(out["R_neg"], R, atol=1e-12)  # q and -q: the same rotation
    # Composition: R(a ⊗ b) = R(a) R(b); the conjugate is the inverse.
    np.testing.assert_allclose(out["R_ab"], R[:32] @ R[32:], atol=1e-12)
    np.testing.assert_allclose(out["q_qconj"], np.tile([1.0, 0.0, 0.0, 0.0], (64, 1)), atol=1e-12)


def test_rotation_conventions_on_known_cases():
    """Active right-handed rotations, z up: +90° yaw maps x to y; +θ roll tilts thrust towards -y."""
    with jax.enable_x64(True):
        yaw = dyn.quat_from_axis_angle(jnp.array([0.0, 0.0, 1.0]), jnp.float64(math.pi / 2))
        np.testing.assert_allclose(dyn.quat_rotate(yaw, jnp.array([1.0, 0.0, 0.0])), [0, 1, 0], atol=1e-15)
        th = 0.4
        roll = dyn.quat_from_axis_angle(jnp.array([1.0, 0.0, 0.0]), jnp.float64(th))
        np.testing.assert_allclose(dyn.body_z(roll), [0.0, -math.sin(th), math.cos(th)], atol=1e-15)
        np.testing.assert_allclose(roll, axis_angle([1, 0, 0], th), atol=1e-15)


def test_derivative_matches_spec_equations():
    """Spec D1/D2/D6: ṗ = v, v̇ = R(q)[0,0,c] - [0,0,g] + a_ext, q̇ = ½ Λ(ω_cmd) q."""
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        for units in ("newton", "mass_normalized"):
            params = QuadParams.create(thrust_units=units)
            for q in random_unit_quats(rng, 8):
                x = make_state(p=rng.normal(size=3), v=rng.normal(size=3), q=q, w=rng.normal(size=3))
                u = np.r_[rng.uniform(0.0, 20.0), rng.normal(size=3)]
                a_ext = rng.normal(size=3)
                dx = dyn.derivative(params, x, jnp.asarray(u), jnp.asarray(a_ext))
                c = u[0] / params.mass if units == "newton" else u[0]
                R = np.asarray(dyn.quat_to_rotmat(jnp.asarray(q)))
                np.testing.assert_allclose(dx.p, x.v, atol=1e-14)
                np.testing.assert_allclose(dx.v, R @ [0.0, 0.0, c] - [0.0, 0.0, G] + a_ext, atol=1e-12)
                np.testing.assert_allclose(dx.q, 0.5 * lambda_matrix(u[1:]) @ q, atol=1e-14)
                np.testing.assert_array_equal(dx.w, 0.0)  # instant model: stored rate does not move


def test_clip_control_box():
    params = QuadParams.create()
    u = jnp.array([25.0, -9.0, 3.0, 7.0])
    np.testing.assert_allclose(dyn.clip_control(params, u), [20.0, -6.0, 3.0, 6.0])
    np.testing.assert_allclose(dyn.clip_control(params, jnp.array([-1.0, 0, 0, 0])), [0.0, 0, 0, 0])
