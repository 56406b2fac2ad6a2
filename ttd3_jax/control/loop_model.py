"""The NMPC's model of a ``firmware`` vehicle's inner loop: the rate PID, mixer and rotors of
:mod:`ttd3_jax.sim.inner_loop` reduced to a continuous-time system per body axis that a
50 ms node step can integrate with a few RK4 substeps.

The plant (``sim.inner_loop``) runs, per axis, every 1 ms: ``τ_c = clip(kp e + ki I − kd ω̇,
±τ_max)`` (``e = ω_c − ω``, ``I = clip(∫ e dt, ±i_limit)``, D on the measured rate), mixes the
torques and the collective thrust into four rotor thrusts, and the rotors follow their speed
commands with a first-order lag (``tau_up`` spinning up, ``tau_down`` down).  The reduced model
keeps that structure in continuous time and replaces the four rotors by two lags:

    τ_c = clip(kp e + ki I − kd ω̇, ±τ_max),  (T_m, τ_m) = wrench(mix(T_c, τ_c))   (the firmware)
    J ω̇ = τ − ω × Jω                                               (the rigid body)
    τ̇ = (τ_m − τ) / tau_torque                                     (the rotors, differentially)
    İ = e,  I clipped to ±i_limit after each substep
    Ṫ = (T_m − T) / (tau_up if T_m > T else tau_down)              (the rotors, collectively)
    m v̇ = T body_z − drag v − m g

``mix``/``wrench`` are the plant's own (``sim.inner_loop``: the firmware's cap, attitude first,
and each rotor clipped to its limits), so the model knows that torque at full thrust costs
thrust.  ``tau_torque`` = (tau_up + tau_down) / 2: a torque step speeds up the rotors on one
side and slows down those on the other, each with its own time constant.  The D term's ``ω̇`` is
the body's own (``(τ − ω × Jω) / J``), so ``τ_c`` is algebraic in the state.  Left out: the
PID's 1 ms discretisation and the quadratic thrust curve (thrust follows its command with the
rotor speed's lag).  ``tests/test_loop_model.py`` checks the model's rate and thrust steps
against the full simulated loop; docs/paper-notes.md ("The NMPC's model of ``cf2``") has the
figures.

The hidden states ``(τ, I, T)`` are not sensed: :func:`propagate_hidden` carries them from one
control step to the next through the model, from the sensed rigid-body state and the command the
controller applied (as a policy knows its last action).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ttd3_jax.sim import inner_loop as il
from ttd3_jax.sim.dynamics import QuadParams, QuadState, body_z, quat_rate

HIDDEN = 7  # torque (3), integral (3), thrust (1)


@struct.dataclass
class LoopModelState(QuadState):
    """:class:`QuadState` and the loop's hidden states: the rotors' body torque ``torque`` (3,)
    N m, the PID's integral ``integ`` (3,) rad and the collective thrust ``thrust`` () N.
    ``ravel_pytree`` keeps the field order, so p, v, q, w come first (as the NMPC reads them)."""

    torque: jax.Array
    integ: jax.Array
    thrust: jax.Array


def tau_torque(quad: QuadParams) -> float:
    """The time constant (s) of the body torque: the mean of the rotors' up and down lags."""
    return 0.5 * (quad.loop.tau_up + quad.loop.tau_down)


def hover_hidden(quad: QuadParams, dtype) -> jax.Array:
    """The hidden states (HIDDEN,) of the vehicle at rest: no torque, no integral, thrust = weight."""
    return jnp.zeros(HIDDEN, dtype).at[6].set(quad.mass * quad.gravity)


def with_hidden(x: QuadState, hidden: jax.Array) -> LoopModelState:
    """``x``'s rigid body with the hidden states ``hidden`` (HIDDEN,)."""
    return LoopModelState(p=x.p, v=x.v, q=x.q, w=x.w, torque=hidden[:3], integ=hidden[3:6], thrust=hidden[6])


def hidden_of(x: LoopModelState) -> jax.Array:
    """The hidden states (HIDDEN,) of ``x``."""
    return jnp.concatenate([x.torque, x.integ, x.thrust[None]])


def _axes(quad: QuadParams, dtype):
    loop = quad.loop
    return tuple(jnp.asarray(v, dtype) for v in (loop.kp, loop.ki, loop.kd, loop.torque_limit, quad.inertia))


def derivative(quad: QuadParams, x: LoopModelState, u: jax.Array) -> LoopModelState:
    """``ẋ`` under the command ``u`` (4,) = [thrust N, ω_c (3,) rad/s] (the module docstring)."""
    loop, dtype = quad.loop, x.v.dtype
    kp, ki, kd, tmax, inertia = _axes(quad, dtype)
    gyro = jnp.cross(x.w, inertia * x.w)
    w_dot = (x.torque - gyro) / inertia
    e = u[1:4] - x.w
    tau_c = jnp.clip(kp * e + ki * x.integ - kd * w_dot, -tmax, tmax)
    # what the rotors settle at: the firmware's mixer (its cap and per-rotor clip) of (T_c, τ_c)
    thrust_c, tau_c = il.wrench(loop, il.mix(loop, u[0], tau_c))
    lag = jnp.where(thrust_c > x.thrust, loop.tau_up, loop.tau_down)
    g = jnp.asarray([0.0, 0.0, quad.gravity], dtype)
    v_dot = (x.thrust * body_z(x.q) - loop.drag * x.v) / quad.mass - g
    torque_dot = (tau_c - x.torque) / tau_torque(quad)
    return LoopModelState(p=x.v, v=v_dot, q=quat_rate(x.q, x.w), w=w_dot, torque=torque_dot, integ=e,
                          thrust=(thrust_c - x.thrust) / lag)  # fmt: skip


def _axpy(a, dx, x):
    return jax.tree.map(lambda xi, di: xi + a * di, x, dx)


def step(quad: QuadParams, x: LoopModelState, u: jax.Array, dt: float, substeps: int = 1) -> LoopModelState:
    """Advance ``x`` by ``dt`` s under zero-order-hold ``u``: ``substeps`` RK4 steps, each followed
    by the firmware's clamp of the integral; ``q`` back to unit norm at the end."""
    h = dt / substeps
    lim = jnp.asarray(quad.loop.i_limit, x.v.dtype)

    def rk4(_, x):
        k1 = derivative(quad, x, u)
        k2 = derivative(quad, _axpy(0.5 * h, k1, x), u)
        k3 = derivative(quad, _axpy(0.5 * h, k2, x), u)
        k4 = derivative(quad, _axpy(h, k3, x), u)
        x = jax.tree.map(lambda xi, a, b, c, d: xi + (h / 6.0) * (a + 2 * b + 2 * c + d), x, k1, k2, k3, k4)
        return x.replace(integ=jnp.clip(x.integ, -lim, lim))

    x = rk4(0, x) if substeps == 1 else jax.lax.fori_loop(0, substeps, rk4, x)  # a loop: a small graph
    return x.replace(q=x.q / jnp.linalg.norm(x.q))


def propagate_hidden(quad: QuadParams, sensed: QuadState, hidden: jax.Array, u: jax.Array, dt: float,
                     substeps: int = 1) -> jax.Array:  # fmt: skip
    """The hidden states ``dt`` s after the sensed state ``sensed`` with hidden states ``hidden``,
    under the applied command ``u`` (4,): the estimate the next control step starts from."""
    return hidden_of(step(quad, with_hidden(sensed, hidden), u, dt, substeps))
