"""Numerical helpers of the tracking env (``sim.env``): the OU wind step, the observation's
mask of non-finite entries, and the finiteness test of a state, each written for XLA:CPU's
fusion (one read of the data, no reduction that ends a fusion).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ttd3_jax.sim import rng
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.dynamics import QuadState


def ou_wind_step(c: EnvConfig, wind: jax.Array, key: jax.Array):
    """One physics step (``c.dt``) of the OU wind acceleration ``wind`` (3,) m/s², with
    stationary std ``c.disturbances.wind_sigma`` and correlation time ``c.disturbances.wind_tau``; returns
    ``(wind, key)`` (one split and 3 normals of ``ttd3_jax.sim.rng``)."""
    key, sub = rng.split(key)
    phi = math.exp(-c.dt / c.disturbances.wind_tau)
    xi = rng.normal(sub, (3,), wind.dtype)
    return phi * wind + c.disturbances.wind_sigma * math.sqrt(1.0 - phi * phi) * xi, key


@jax.custom_jvp
def _zero_non_finite(x: jax.Array) -> jax.Array:
    """``x`` with its NaN and inf entries set to +0.0, as ``jnp.where(jnp.isfinite(x), x, 0)``
    (values and derivative), but testing the exponent bits so that ``x`` is read once: XLA:CPU
    then fuses the observation's concatenation into the mask instead of writing it out."""
    return _mask_bits(x)


def _mask_bits(x: jax.Array) -> jax.Array:
    f = jnp.finfo(x.dtype)
    ints = jnp.dtype(f"int{f.bits}")
    exp = ((1 << f.nexp) - 1) << f.nmant  # all exponent bits set: inf or NaN
    bits = jax.lax.bitcast_convert_type(x, ints)
    mask = jnp.asarray(exp, ints)
    return jax.lax.bitcast_convert_type(jnp.where(bits & mask == mask, 0, bits), x.dtype)


@_zero_non_finite.defjvp
def _zero_non_finite_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return _mask_bits(x), jnp.where(jnp.isfinite(x), t, 0.0)


def _finite(x: QuadState) -> jax.Array:
    """True when every state entry is finite (a NaN or inf anywhere makes the sum non-finite);
    added one by one, since a ``jnp.sum`` reduction would end the step's fusion on XLA:CPU."""
    return jnp.isfinite(sum(leaf[..., i] for leaf in jax.tree.leaves(x) for i in range(leaf.shape[-1])))
