"""Geometric tracking controller with thrust + body-rate output (Lee / Mellinger style).

Position loop: ``a_des = a_ref + Kp (p_ref - p) + Kv (v_ref - v) + g ẑ`` (m/s^2).
Collective thrust is ``a_des · z_B`` (projected on the current body z axis) and
the desired attitude has ``z_B,des ∥ a_des`` and zero yaw.  Attitude loop:
``ω_cmd = -K_R · vee(R_desᵀR - RᵀR_des)/2``, saturated to the rate box.  It sees the
true state and the analytic reference (position, velocity and acceleration feed-forward).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ttd3_jax.control.closed_loop import Controller
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.dynamics import QuadParams, QuadState, clip_control, quat_to_rotmat
from ttd3_jax.sim.env import control_to_action


@dataclasses.dataclass(frozen=True)
class GeometricGains:
    """Gains: ``kp`` 1/s^2, ``kv`` 1/s, ``k_att`` 1/s (per axis where a tuple)."""

    kp: tuple[float, float, float] = (16.0, 16.0, 16.0)
    kv: tuple[float, float, float] = (8.0, 8.0, 8.0)
    k_att: tuple[float, float, float] = (12.0, 12.0, 6.0)
    max_tilt_deg: float = 40.0

    def __post_init__(self):
        for name in ("kp", "kv", "k_att"):
            v = getattr(self, name)
            if len(v) != 3 or any(not x > 0 for x in v):
                raise ValueError(f"GeometricGains.{name} must be 3 values > 0, got {v!r}")
        if not 0 < self.max_tilt_deg < 90:
            raise ValueError(f"GeometricGains.max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")


def _vee(m: jax.Array) -> jax.Array:
    return jnp.stack([m[2, 1], m[0, 2], m[1, 0]])


def geometric_control(params: QuadParams, gains: GeometricGains, x: QuadState, *, p_ref: jax.Array,
                      v_ref: jax.Array, a_ref: jax.Array) -> jax.Array:  # fmt: skip
    """Physical control ``[thrust, ω_x, ω_y, ω_z]`` (thrust in the model's unit), clipped."""
    f = x.p.dtype
    g = jnp.asarray([0.0, 0.0, params.gravity], f)
    a_des = a_ref + jnp.asarray(gains.kp, f) * (p_ref - x.p) + jnp.asarray(gains.kv, f) * (v_ref - x.v) + g
    # keep enough vertical acceleration and limit the tilt
    a_des = a_des.at[2].set(jnp.maximum(a_des[2], 0.2 * params.gravity))
    h = jnp.linalg.norm(a_des[:2])
    h_max = a_des[2] * jnp.tan(jnp.deg2rad(gains.max_tilt_deg))
    a_des = a_des.at[:2].multiply(jnp.minimum(1.0, h_max / jnp.maximum(h, 1e-9)))
    R = quat_to_rotmat(x.q)
    c = jnp.dot(a_des, R[:, 2])  # m/s^2 along the current body z
    z_des = a_des / jnp.linalg.norm(a_des)
    x_c = jnp.asarray([1.0, 0.0, 0.0], f)
    y_des = jnp.cross(z_des, x_c)
    y_des = y_des / jnp.linalg.norm(y_des)
    x_des = jnp.cross(y_des, z_des)
    R_des = jnp.stack([x_des, y_des, z_des], axis=1)
    e_R = 0.5 * _vee(R_des.T @ R - R.T @ R_des)
    w_cmd = -jnp.asarray(gains.k_att, f) * e_R
    thrust = c * params.mass if params.thrust_units == "newton" else c
    return clip_control(params, jnp.concatenate([thrust[None], w_cmd]))


def geometric_controller(cfg: EnvConfig, gains: GeometricGains | None = None) -> Controller:
    """:func:`geometric_control` fed with the analytic reference at the current step."""
    gains = gains or GeometricGains()

    def act(carry, state):
        ps = state.pipeline_state
        p_ref, v_ref, a_ref = tr.evaluate(ps.track, ps.k, cfg.dt)
        u = geometric_control(cfg.vehicle.quad, gains, ps.quad, p_ref=p_ref, v_ref=v_ref, a_ref=a_ref)
        return control_to_action(cfg, u), carry

    return Controller(init=lambda s: (), act=act)
