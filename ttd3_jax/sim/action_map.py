"""The action map: a normalised action ``a ∈ [-1, 1]^4`` <-> the physical control ``[thrust,
ω_cmd]`` of the config's (nominal) vehicle (O2).  Every controller and the env use it; a
randomised plant's errors are applied after it (``sim.env``), never in it.  Each function
takes an optional nominal vehicle ``quad`` (arrays) whose map it is instead of the config's:
an episode's drawn vehicle under ``randomization.vehicles`` (``sim.vehicle_mix``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.dynamics import QuadParams


def thrust_range(cfg: EnvConfig, quad: QuadParams | None = None):
    """``(min, max, hover)`` collective thrust of the action map (N, or the thrust units)."""
    if quad is not None:  # a nominal vehicle of randomization.vehicles (thrust_map_mass None)
        return quad.thrust_min, quad.thrust_max, quad.hover_thrust
    q = cfg.vehicle.quad
    hover = q.hover_thrust
    if cfg.vehicle.thrust_map_mass is not None and q.thrust_units == "newton":
        hover = q.gravity * cfg.vehicle.thrust_map_mass
    return q.thrust_min, q.thrust_max, hover


def action_to_control(cfg: EnvConfig, a: jax.Array, quad: QuadParams | None = None) -> jax.Array:
    """Normalised action (..., 4) in [-1, 1] -> physical control ``[thrust, ω_cmd]`` (O2).

    Default: thrust = f_min + (a0 + 1)/2 (f_max - f_min); rates affine onto
    [rate_min, rate_max].  ``hover_centered_thrust`` maps a0 = 0 to the hover thrust.
    """
    lo, hi, hover = thrust_range(cfg, quad)
    a0 = a[..., 0]
    if cfg.vehicle.hover_centered_thrust:
        f = jnp.where(a0 >= 0, hover + a0 * (hi - hover), hover + a0 * (hover - lo))
    else:
        f = lo + 0.5 * (a0 + 1.0) * (hi - lo)
    q = cfg.vehicle.quad if quad is None else quad
    rlo, rhi = q.rate_min, q.rate_max
    w = rlo + 0.5 * (a[..., 1:] + 1.0) * (rhi - rlo)
    return jnp.concatenate([f[..., None], w], -1)


def control_to_action(cfg: EnvConfig, u: jax.Array, quad: QuadParams | None = None) -> jax.Array:
    """Inverse of :func:`action_to_control` (for controllers with physical outputs)."""
    lo, hi, hover = thrust_range(cfg, quad)
    f = u[..., 0]
    if cfg.vehicle.hover_centered_thrust:
        a0 = jnp.where(f >= hover, (f - hover) / (hi - hover), (f - hover) / (hover - lo))
    else:
        a0 = 2.0 * (f - lo) / (hi - lo) - 1.0
    q = cfg.vehicle.quad if quad is None else quad
    rlo, rhi = q.rate_min, q.rate_max
    aw = 2.0 * (u[..., 1:] - rlo) / (rhi - rlo) - 1.0
    return jnp.concatenate([a0[..., None], aw], -1)


def hover_action(cfg: EnvConfig, quad: QuadParams | None = None) -> jax.Array:
    """Normalised action that holds hover (a0 = 0.4715 with the paper's numbers).  With
    ``thrust_map_mass`` set: the hover action of that (nominal) mass."""
    u = jnp.array([thrust_range(cfg, quad)[2], 0.0, 0.0, 0.0])
    return control_to_action(cfg, u, quad)
