"""Running observation normalisation (mean / std over every observation collected).  The
statistics live in the train state; the buffer keeps raw observations, and minibatches are
normalised with the current statistics when used, as Brax's trainers do.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

STD_MIN = 1e-3  # floor on the std (features that barely move are not blown up)
CLIP = 10.0  # normalised values are clipped to ±CLIP


@struct.dataclass
class ObsStats:
    count: jax.Array  # () observations seen
    mean: jax.Array  # (n_obs,)
    m2: jax.Array  # (n_obs,) sum of squared deviations from the mean


def init(obs_size: int) -> ObsStats:
    return ObsStats(count=jnp.zeros(()), mean=jnp.zeros(obs_size), m2=jnp.zeros(obs_size))


def update(s: ObsStats, x: jax.Array) -> ObsStats:
    """Merge a batch ``x`` (n, n_obs) into the statistics (Chan et al.'s parallel update)."""
    n = x.shape[0]
    b_mean = jnp.mean(x, axis=0)
    b_m2 = jnp.sum((x - b_mean) ** 2, axis=0)
    count = s.count + n
    delta = b_mean - s.mean
    mean = s.mean + delta * (n / count)
    m2 = s.m2 + b_m2 + delta**2 * (s.count * n / count)
    return ObsStats(count=count, mean=mean, m2=m2)


def std(s: ObsStats) -> jax.Array:
    return jnp.maximum(jnp.sqrt(s.m2 / jnp.maximum(s.count, 1.0)), STD_MIN)


def apply(s: ObsStats | None, x: jax.Array) -> jax.Array:
    """Normalised observations (..., n_obs); ``s=None`` leaves ``x`` unchanged."""
    if s is None:
        return x
    return jnp.clip((x - s.mean) / std(s), -CLIP, CLIP)
