"""Quadrotor rigid-body model with thrust + body-rate inputs, integrated with RK4.

Conventions (spec §2.1, rows D1-D7): world frame z up, gravity subtracted, Hamilton
quaternions stored scalar first ``(qw, qx, qy, qz)``, body rates in the body frame.  Pure
functions of one vehicle's arrays (``...``: any batch dims): ``jit``, ``vmap`` and
differentiate them (the NMPC differentiates through :func:`rk4_step`).  Control ``u`` (4,)
is physical: collective thrust (N under ``thrust_units="newton"``, m/s^2 under
``"mass_normalized"``), then the commanded body rates (rad/s).
"""

from __future__ import annotations

import math
from typing import Annotated

import jax
import jax.numpy as jnp
from flax import struct
from tyro.conf import Suppress  # (a field the command line does not show)

from ttd3_jax.sim import inner_loop as il
from ttd3_jax.sim.inner_loop import InnerLoop

RATE_MODELS = ("instant", "first_order", "torque", "firmware")
THRUST_UNITS = ("newton", "mass_normalized")


@struct.dataclass
class QuadParams:
    """Physical parameters (a pytree: numeric fields are leaves, so they can be vmapped).

    Build it with :meth:`QuadParams.create`, which validates every value.  The
    two string fields are static (part of the tree structure).
    """

    mass: float = 1.5  # kg
    gravity: Annotated[float, Suppress] = 9.81  # m/s^2, subtracted along world z
    thrust_min: Annotated[float, Suppress] = 0.0  # N ("newton") or m/s^2 ("mass_normalized")
    thrust_max: float = 20.0  # same unit as thrust_min
    rate_min: Annotated[float, Suppress] = -6.0  # rad/s, every body axis
    rate_max: Annotated[float, Suppress] = 6.0  # rad/s, every body axis
    # Only used by the "first_order" / "torque" rate models (spec D4).
    tau_rate: Annotated[float, Suppress] = 0.03  # s, first-order body-rate time constant
    inertia: Annotated[tuple[float, float, float], Suppress] = (
        0.029125,
        0.029125,
        0.055225,
    )  # kg m^2, diagonal of J
    k_rate: Annotated[tuple[float, float, float], Suppress] = (20.0, 20.0, 10.0)  # 1/s, rate-loop gain K_w
    torque_max: Annotated[tuple[float, float, float], Suppress] = (2.2, 1.3, 0.6)  # N m, |eta| bound per axis
    # The "firmware" rate model's rate PID, mixer, motors and drag (sim.inner_loop); None otherwise
    loop: Annotated[InnerLoop | None, Suppress] = None
    rate_model: str = struct.field(pytree_node=False, default="instant")
    thrust_units: Annotated[str, Suppress] = struct.field(pytree_node=False, default="newton")

    @classmethod
    def create(cls, **overrides) -> QuadParams:
        """Validated constructor. Raises ``ValueError`` naming the bad field."""
        params = cls(**overrides)
        validate_params(params)
        return params

    @property
    def hover_thrust(self) -> float:
        """Thrust that balances gravity, in this model's thrust unit."""
        return self.gravity * (self.mass if self.thrust_units == "newton" else 1.0)


def _as_float(name: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"QuadParams.{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"QuadParams.{name} must be finite, got {value!r}")
    return out


def validate_params(p: QuadParams) -> None:
    """Check every field of ``p`` at the Python level (never call under ``jit``)."""
    if p.rate_model not in RATE_MODELS:
        raise ValueError(f"QuadParams.rate_model must be one of {RATE_MODELS}, got {p.rate_model!r}")
    if p.thrust_units not in THRUST_UNITS:
        raise ValueError(f"QuadParams.thrust_units must be one of {THRUST_UNITS}, got {p.thrust_units!r}")
    for name in ("mass", "gravity", "tau_rate"):
        if _as_float(name, getattr(p, name)) <= 0:
            raise ValueError(f"QuadParams.{name} must be > 0, got {getattr(p, name)!r}")
    for lo, hi in (("thrust_min", "thrust_max"), ("rate_min", "rate_max")):
        vlo, vhi = _as_float(lo, getattr(p, lo)), _as_float(hi, getattr(p, hi))
        if vlo >= vhi:
            raise ValueError(f"QuadParams.{lo} must be < {hi}, got {lo}={vlo}, {hi}={vhi}")
    if _as_float("thrust_min", p.thrust_min) < 0:
        raise ValueError(f"QuadParams.thrust_min must be >= 0 (rotors only push), got {p.thrust_min}")
    if not p.rate_min < 0 < p.rate_max:
        raise ValueError(f"QuadParams body-rate range must contain 0, got [{p.rate_min}, {p.rate_max}] rad/s")
    if p.hover_thrust >= p.thrust_max:
        raise ValueError(
            f"QuadParams.thrust_max={p.thrust_max} cannot lift the vehicle: hover needs "
            f"{p.hover_thrust:.3f} ({p.thrust_units}); allowed range is thrust_max > hover thrust"
        )
    for name in ("inertia", "k_rate", "torque_max"):
        _check_triple(name, getattr(p, name), strict=True)
    if p.rate_model == "firmware":
        validate_loop(p)
    elif p.loop is not None:
        raise ValueError(
            f"QuadParams.loop must be None with rate_model {p.rate_model!r} (only 'firmware' flies "
            "an inner loop), got an InnerLoop"
        )


def _check_triple(name: str, vals, strict: bool) -> None:
    if not isinstance(vals, (tuple, list)) or len(vals) != 3:
        raise ValueError(f"QuadParams.{name} must have 3 entries (x, y, z), got {vals!r}")
    for v in vals:
        x = _as_float(name, v)
        if x < 0 or (strict and x == 0):
            raise ValueError(f"QuadParams.{name} entries must be {'> 0' if strict else '>= 0'}, got {vals!r}")


def validate_loop(p: QuadParams) -> None:
    """Check ``p.loop`` (the ``firmware`` rate model's inner loop), naming the bad field."""
    loop = p.loop
    if not isinstance(loop, InnerLoop):
        raise ValueError(
            f"QuadParams.loop must be an InnerLoop with rate_model 'firmware' (the cf2 vehicle has one: "
            f"--vehicle cf2), got {loop!r}"
        )
    if p.thrust_units != "newton":
        raise ValueError(
            f"QuadParams.thrust_units must be 'newton' with rate_model 'firmware', got {p.thrust_units!r}"
        )
    for name in ("kp", "ki", "kd"):
        _check_triple(f"loop.{name}", getattr(loop, name), strict=False)
    for name in ("i_limit", "torque_limit"):
        _check_triple(f"loop.{name}", getattr(loop, name), strict=True)
    for name in ("arm", "yaw_coeff", "motor_max", "tau_up", "tau_down"):
        if _as_float(f"loop.{name}", getattr(loop, name)) <= 0:
            raise ValueError(f"QuadParams.loop.{name} must be > 0, got {getattr(loop, name)!r}")
    for name in ("motor_min", "drag", "curve"):
        if _as_float(f"loop.{name}", getattr(loop, name)) < 0:
            raise ValueError(f"QuadParams.loop.{name} must be >= 0, got {getattr(loop, name)!r}")
    if loop.curve > 2:
        raise ValueError(
            f"QuadParams.loop.curve must be in [0, 2] (the thrust curve's share of s²), got {loop.curve!r}"
        )
    if loop.motor_min >= loop.motor_max:
        raise ValueError(
            f"QuadParams.loop.motor_min must be < motor_max, got {loop.motor_min} >= {loop.motor_max}"
        )
    weight = p.mass * p.gravity
    if 4 * loop.motor_max <= weight:
        raise ValueError(
            f"QuadParams.loop.motor_max={loop.motor_max} N cannot hover: four rotors make "
            f"{4 * loop.motor_max:.4g} N, the weight is {weight:.4g} N; allowed: motor_max > {weight / 4:.4g}"
        )
    if 4 * loop.motor_min >= weight:
        raise ValueError(
            f"QuadParams.loop.motor_min={loop.motor_min} N cannot hover: four idle rotors make "
            f"{4 * loop.motor_min:.4g} N, the weight is {weight:.4g} N; allowed: motor_min < {weight / 4:.4g}"
        )


@struct.dataclass
class QuadState:
    """Vehicle state. ``p`` (3,) m and ``v`` (3,) m/s in the world frame,
    ``q`` (4,) unit quaternion body->world (scalar first), ``w`` (3,) rad/s body rates."""

    p: jax.Array
    v: jax.Array
    q: jax.Array
    w: jax.Array

    @classmethod
    def hover(cls, p=(0.0, 0.0, 0.0), dtype=None) -> QuadState:
        """At rest, level, at position ``p``."""
        dtype = dtype or jnp.zeros(()).dtype
        zero = jnp.zeros(3, dtype)
        return cls(p=jnp.asarray(p, dtype), v=zero, q=jnp.array([1.0, 0.0, 0.0, 0.0], dtype), w=zero)


@struct.dataclass
class FirmwareState(QuadState):
    """:class:`QuadState` of the ``firmware`` rate model: also the rotors' speeds ``motor`` (4,)
    (1 = full thrust), the rate PID's integral ``integ`` (3,) rad and the body rates it measured
    last, ``gyro`` (3,) rad/s (its D term differentiates the measurement)."""

    motor: jax.Array
    integ: jax.Array
    gyro: jax.Array


def model_state(params: QuadParams, x: QuadState) -> QuadState:
    """``x`` as ``params``' rate model carries it: under ``firmware``, a :class:`FirmwareState`
    whose rotors hold the weight (the vehicle as it hovers), the PID at rest; else ``x``."""
    if params.rate_model != "firmware":
        return x
    s = il.hover_speed(params.loop, params.mass * params.gravity).astype(x.p.dtype)
    return FirmwareState(p=x.p, v=x.v, q=x.q, w=x.w, motor=jnp.broadcast_to(s, (4,)),
                         integ=jnp.zeros(3, x.p.dtype), gyro=x.w)  # fmt: skip


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product ``a ⊗ b`` of scalar-first quaternions, shapes (..., 4)."""
    aw, ax, ay, az = jnp.moveaxis(a, -1, 0)
    bw, bx, by, bz = jnp.moveaxis(b, -1, 0)
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: jax.Array) -> jax.Array:
    """Conjugate (= inverse for unit quaternions), shape (..., 4)."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


def quat_rotate(q: jax.Array, x: jax.Array) -> jax.Array:
    """Rotate body-frame vector ``x`` (..., 3) into the world frame by unit ``q`` (..., 4)."""
    zero = jnp.zeros_like(x[..., :1])
    return quat_mul(quat_mul(q, jnp.concatenate([zero, x], -1)), quat_conj(q))[..., 1:]


def quat_to_rotmat(q: jax.Array) -> jax.Array:
    """Rotation matrix (..., 3, 3) of unit quaternion ``q`` (..., 4); columns are body axes in world."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def quat_from_axis_angle(axis: jax.Array, angle: jax.Array) -> jax.Array:
    """Unit quaternion for a rotation of ``angle`` rad about unit ``axis`` (3,)."""
    half = 0.5 * angle
    return jnp.concatenate([jnp.cos(half)[..., None], jnp.sin(half)[..., None] * axis], -1)


def body_z(q: jax.Array) -> jax.Array:
    """World-frame direction of the body z axis (thrust direction), shape (..., 3)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)


def yaw_of(q: jax.Array) -> jax.Array:
    """Yaw ψ (rad) of the scalar-first unit quaternion ``q`` (z-y-x Euler angles)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quat_rate(q: jax.Array, w: jax.Array) -> jax.Array:
    """``q̇ = ½ Λ(ω) q`` (spec D2) with body rates ``w`` (3,): equals ``½ q ⊗ [0, ω]``."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    wx, wy, wz = w[0], w[1], w[2]
    return 0.5 * jnp.stack(
        [
            -wx * qx - wy * qy - wz * qz,
            wx * qw + wz * qy - wy * qz,
            wy * qw - wz * qx + wx * qz,
            wz * qw + wy * qx - wx * qy,
        ]
    )


def collective_accel(params: QuadParams, thrust: jax.Array) -> jax.Array:
    """Mass-normalised collective thrust c (m/s^2) from the thrust input in the model's unit."""
    return thrust / params.mass if params.thrust_units == "newton" else thrust


def rate_derivative(params: QuadParams, w: jax.Array, w_cmd: jax.Array) -> jax.Array:
    """``ω̇`` (rad/s^2) for the ``first_order`` and ``torque`` rate models (spec D4)."""
    if params.rate_model == "first_order":
        return (w_cmd - w) / params.tau_rate
    inertia = jnp.asarray(params.inertia, w.dtype)
    gyro = jnp.cross(w, inertia * w)
    eta = inertia * jnp.asarray(params.k_rate, w.dtype) * (w_cmd - w) + gyro
    eta_max = jnp.asarray(params.torque_max, w.dtype)
    eta = jnp.clip(eta, -eta_max, eta_max)
    return (eta - gyro) / inertia


def derivative(params: QuadParams, x: QuadState, u: jax.Array,
               accel_ext: jax.Array | None = None) -> QuadState:  # fmt: skip
    """Continuous-time ``ẋ = f(x, u)`` for control ``u`` (4,) ``[thrust, ω_cmd]`` and an
    optional extra world-frame acceleration ``accel_ext`` (3,) m/s^2 (wind).  Under
    ``rate_model="instant"`` ω_cmd drives the attitude and the stored ``w`` does not move."""
    if params.rate_model == "firmware":
        return _firmware_derivative(params, x, u, accel_ext)
    c = collective_accel(params, u[0])
    w_cmd = u[1:4]
    g = jnp.asarray([0.0, 0.0, params.gravity], x.v.dtype)
    v_dot = c * body_z(x.q) - g
    if accel_ext is not None:
        v_dot = v_dot + accel_ext
    if params.rate_model == "instant":
        w_att, w_dot = w_cmd, jnp.zeros_like(x.w)
    else:
        w_att, w_dot = x.w, rate_derivative(params, x.w, w_cmd)
    return QuadState(p=x.v, v=v_dot, q=quat_rate(x.q, w_att), w=w_dot)


def _firmware_derivative(params: QuadParams, x: FirmwareState, s_cmd: jax.Array,
                         accel_ext: jax.Array | None) -> FirmwareState:  # fmt: skip
    """``ẋ`` of the ``firmware`` model under rotor-speed commands ``s_cmd`` (4,) (held over the
    step; the PID's state changes only between steps)."""
    loop, dtype = params.loop, x.v.dtype
    thrust, tau = il.wrench(loop, il.rotor_thrust(loop, x.motor))
    g = jnp.asarray([0.0, 0.0, params.gravity], dtype)
    v_dot = (thrust * body_z(x.q) - loop.drag * x.v) / params.mass - g
    if accel_ext is not None:
        v_dot = v_dot + accel_ext
    inertia = jnp.asarray(params.inertia, dtype)
    w_dot = (tau - jnp.cross(x.w, inertia * x.w)) / inertia
    zero = jnp.zeros_like(x.integ)
    return FirmwareState(p=x.v, v=v_dot, q=quat_rate(x.q, x.w), w=w_dot,
                         motor=il.rotor_rate(loop, x.motor, s_cmd), integ=zero, gyro=zero)  # fmt: skip


def _axpy(a, dx: QuadState, x: QuadState) -> QuadState:
    return jax.tree.map(lambda xi, di: xi + a * di, x, dx)


def rk4_step(params: QuadParams, x: QuadState, u: jax.Array, dt: float,
             accel_ext: jax.Array | None = None, *, substeps: int = 1,
             renormalize: bool = True) -> QuadState:  # fmt: skip
    """Advance ``x`` by ``dt`` seconds under zero-order-hold ``u`` (spec D7): ``substeps`` RK4
    steps, then ``q`` back to unit norm if ``renormalize`` (``instant`` model: ``w = ω_cmd``)."""
    firmware = params.rate_model == "firmware"
    if firmware:  # the firmware's step, once per physics step: u becomes rotor-speed commands
        gyro = x.w
        u, integ = il.command(params.loop, u[0], u[1:4], gyro, x.gyro, x.integ, dt)
    h = dt / substeps
    for _ in range(substeps):  # static, small: unrolled
        k1 = derivative(params, x, u, accel_ext)
        k2 = derivative(params, _axpy(0.5 * h, k1, x), u, accel_ext)
        k3 = derivative(params, _axpy(0.5 * h, k2, x), u, accel_ext)
        k4 = derivative(params, _axpy(h, k3, x), u, accel_ext)
        x = jax.tree.map(
            lambda xi, a, b, c, d: xi + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d), x, k1, k2, k3, k4
        )
    q = x.q / jnp.linalg.norm(x.q) if renormalize else x.q
    if firmware:  # the PID measured the rates at the start of this step
        return x.replace(q=q, integ=integ, gyro=gyro)
    w = u[1:4].astype(x.w.dtype) if params.rate_model == "instant" else x.w
    return x.replace(q=q, w=w)


def clip_control(params: QuadParams, u: jax.Array) -> jax.Array:
    """Clip a physical control (4,) to the thrust and body-rate box."""
    lo = jnp.stack([params.thrust_min, params.rate_min, params.rate_min, params.rate_min])
    hi = jnp.stack([params.thrust_max, params.rate_max, params.rate_max, params.rate_max])
    return jnp.clip(u, lo.astype(u.dtype), hi.astype(u.dtype))
