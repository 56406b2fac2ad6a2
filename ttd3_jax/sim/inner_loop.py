"""What a real quadrotor puts between a body-rate command and its body rates: the flight
firmware's rate PID, the mixer, four motors, and air drag (the ``firmware`` rate model).

The policy commands collective thrust and body rates, as in the paper.  A Crazyflie's firmware
then runs, every physics step (1 kHz here; 500 Hz in the firmware), per body axis:

    e = ω_cmd − ω_meas;   I = clip(I + e dt, ±i_limit);   D = −(ω_meas − ω_meas,prev) / dt
    τ = clip(kp e + ki I + kd D, ±torque_limit)                                  (N m)

and mixes ``(T, τ)`` into four rotor thrusts (x configuration, attitude first: an excess over
the rotor limit is taken off all four, then each is clipped), which it turns into rotor-speed
commands through the thrust curve.  Each rotor's speed ``s`` (1 = the speed of full thrust)
follows its command as a first-order lag, slower spinning down than up, and makes thrust
``F(s) = motor_max (c s² + (1 − c) s)``.  The rigid body then feels ``ΣF`` along body z, the
torques of the rotor thrusts and drags, and a linear air drag ``−drag · v``.

Every number is the Crazyflie's (:class:`InnerLoop`'s defaults; sources in
docs/crazyflie-parameters.md and docs/paper-notes.md).  Pure functions of arrays; no import
of the rigid-body model (``sim.dynamics`` composes them).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct

# Rotor order and geometry (x configuration; body x forward, y left, z up), as crazyflow's
# cf2x_L250 and the firmware's legacy mixer: M1 front-right (+x, −y), M2 rear-right,
# M3 rear-left, M4 front-left; M1 and M3 spin one way, M2 and M4 the other.
ROLL_SIGNS = (-1.0, -1.0, 1.0, 1.0)  # τx = arm Σ ROLL_SIGNS_i F_i
PITCH_SIGNS = (-1.0, 1.0, 1.0, -1.0)  # τy = arm Σ PITCH_SIGNS_i F_i
YAW_SIGNS = (-1.0, 1.0, -1.0, 1.0)  # τz = yaw_coeff Σ YAW_SIGNS_i F_i


def _curve_share(k1: float, k2: float, f_max: float) -> float:
    """``c`` of ``F(s) = f_max (c s² + (1 − c) s)`` for a rotor curve ``F = k1 r + k2 r²`` (r
    the rotor speed), ``s = r / r_max`` with ``F(r_max) = f_max``."""
    r_max = (-k1 + math.sqrt(k1 * k1 + 4.0 * k2 * f_max)) / (2.0 * k2)
    return k2 * r_max * r_max / f_max


# crazyflow 0.4.0 cf2x_L250 (dynamics/first_principles/params.toml): rpm2thrust = [0, k1, k2]
CF2_CURVE = _curve_share(-5.382196214637237e-7, 2.4582929831265485e-10, 0.12)  # 1.104


@struct.dataclass
class InnerLoop:
    """The firmware rate loop, mixer, motors and drag of a vehicle (a pytree: every field is a
    leaf, so randomisation scales them and ``vmap`` flies several).  Defaults: a Crazyflie 2.x
    with legacy propellers (crazyflow's ``cf2x_L250``) and its firmware's default rate gains."""

    kp: tuple[float, float, float] = (1.706e-3, 1.706e-3, 3.702e-4)  # N m / (rad/s)
    ki: tuple[float, float, float] = (3.413e-3, 3.413e-3, 5.152e-5)  # N m / rad
    kd: tuple[float, float, float] = (1.706e-5, 1.706e-5, 0.0)  # N m / (rad/s²), on the measurement
    i_limit: tuple[float, float, float] = (0.5812, 0.5812, 2.909)  # rad, bound on ∫ e dt
    torque_limit: tuple[float, float, float] = (3.90e-3, 3.90e-3, 1.764e-3)  # N m (the int16 outputs)
    arm: float = 0.03253  # m, each rotor's distance from the body x and y axes
    yaw_coeff: float = 0.0073509  # m, yaw torque per newton of rotor thrust
    motor_min: float = 0.012817578393224994  # N per rotor, the firmware's THRUST_MIN
    motor_max: float = 0.12  # N per rotor at full speed (s = 1)
    curve: float = CF2_CURVE  # c of F(s) = motor_max (c s² + (1 − c) s); 1: F ∝ s²
    tau_up: float = 1.0 / 7.355623702172756  # s, rotor speed time constant spinning up (0.136)
    tau_down: float = 0.106  # s, spinning down (crazyflow's quadratic law, linearised at hover)
    drag: float = 0.014953790232821078  # N / (m/s), linear air drag, every axis


def _vec(x, like: jax.Array) -> jax.Array:
    return jnp.asarray(x, like.dtype)


def rotor_thrust(loop: InnerLoop, s: jax.Array) -> jax.Array:
    """Thrust (N) of each rotor at speed ``s`` (4,) (1 = full-thrust speed)."""
    c = loop.curve
    return loop.motor_max * (c * s * s + (1.0 - c) * s)


def rotor_speed(loop: InnerLoop, f: jax.Array) -> jax.Array:
    """The speed at which a rotor makes thrust ``f`` (4,) N > 0: the inverse of :func:`rotor_thrust`."""
    c, x = loop.curve, f / loop.motor_max
    b = 1.0 - c
    root = jnp.sqrt(b * b + 4.0 * c * x)
    # the root of c s² + b s = x in the form without cancellation: b >= 0 (curve <= 1, exact at
    # curve 0, a linear rotor) and b < 0 (curve > 1); the guards keep the unused branch finite
    return jnp.where(b >= 0, 2.0 * x / jnp.maximum(b + root, 1e-30), (root - b) / jnp.maximum(2.0 * c, 1e-30))


def wrench(loop: InnerLoop, f: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Collective thrust (N) and body torque (3,) N m of rotor thrusts ``f`` (4,)."""
    roll, pitch, yaw = (_vec(sg, f) for sg in (ROLL_SIGNS, PITCH_SIGNS, YAW_SIGNS))
    tau = jnp.stack(
        [loop.arm * jnp.dot(roll, f), loop.arm * jnp.dot(pitch, f), loop.yaw_coeff * jnp.dot(yaw, f)]
    )
    return jnp.sum(f), tau


def mix(loop: InnerLoop, thrust: jax.Array, tau: jax.Array) -> jax.Array:
    """Rotor thrusts (4,) N for collective ``thrust`` (N) and torque ``tau`` (3,): the inverse of
    :func:`wrench`, then the firmware's cap (an excess over ``motor_max`` is taken off every
    rotor, so that attitude comes first) and each rotor clipped to [motor_min, motor_max]."""
    roll, pitch, yaw = (_vec(sg, tau) for sg in (ROLL_SIGNS, PITCH_SIGNS, YAW_SIGNS))
    f = 0.25 * (thrust + roll * tau[0] / loop.arm + pitch * tau[1] / loop.arm + yaw * tau[2] / loop.yaw_coeff)
    f = f - jnp.maximum(jnp.max(f) - loop.motor_max, 0.0)
    return jnp.clip(f, loop.motor_min, loop.motor_max)


def rate_pid(loop: InnerLoop, w_cmd: jax.Array, w_meas: jax.Array, w_prev: jax.Array, integ: jax.Array,
             dt: float) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """One update of the firmware's rate PID: ``(torque (3,) N m, new integral (3,) rad)``."""
    kp, ki, kd, lim, tmax = (
        _vec(x, w_meas) for x in (loop.kp, loop.ki, loop.kd, loop.i_limit, loop.torque_limit)
    )
    e = w_cmd - w_meas
    integ = jnp.clip(integ + e * dt, -lim, lim)
    tau = kp * e + ki * integ - kd * (w_meas - w_prev) / dt
    return jnp.clip(tau, -tmax, tmax), integ


def command(loop: InnerLoop, thrust: jax.Array, w_cmd: jax.Array, w_meas: jax.Array, w_prev: jax.Array,
            integ: jax.Array, dt: float) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """The firmware's step: rotor-speed commands (4,) for collective ``thrust`` (N) and rate
    command ``w_cmd`` (3,), and the PID's new integral."""
    tau, integ = rate_pid(loop, w_cmd, w_meas, w_prev, integ, dt)
    return rotor_speed(loop, mix(loop, thrust, tau)), integ


def rotor_rate(loop: InnerLoop, s: jax.Array, s_cmd: jax.Array) -> jax.Array:
    """ds/dt (4,) of the rotors: a first-order lag, ``tau_up`` spinning up, ``tau_down`` down."""
    return jnp.where(s_cmd > s, (s_cmd - s) / loop.tau_up, (s_cmd - s) / loop.tau_down)


def hover_speed(loop: InnerLoop, weight: float) -> float:
    """Each rotor's speed when the four carry ``weight`` (N) together."""
    return rotor_speed(loop, jnp.full((4,), weight / 4.0))[0]
