"""Replay buffer held on the device: a ring of transitions, written one env batch at a time.

The capacity is a multiple of the number of parallel envs, so every insert is one
``dynamic_update_slice`` of ``num_envs`` rows at ``pos``, and sampling is one ``randint``
gather: nothing is O(capacity) per step.  Row ``r`` holds env ``r % num_envs``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Transition:
    """One transition per row. ``terminated`` is 1.0 only for a true terminal state
    (crash); time-limit truncation is stored as 0 so the target bootstraps through it.
    ``next_obs`` is the observation reached by the step, before any auto-reset."""

    obs: jax.Array  # (..., n_obs)
    action: jax.Array  # (..., n_act) in [-1, 1]
    reward: jax.Array  # (...,)
    next_obs: jax.Array  # (..., n_obs)
    terminated: jax.Array  # (...,) 0.0 or 1.0
    done: jax.Array  # (...,) 1.0 when the episode ended here (terminated or truncated)


@struct.dataclass
class ReplayBuffer:
    data: Transition  # each leaf (capacity, ...)
    pos: jax.Array  # int32, next row to write
    size: jax.Array  # int32, rows filled

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[0]


def transition_bytes(obs_size: int, action_size: int, itemsize: int = 4) -> int:
    """Bytes per stored transition (float32 by default)."""
    return itemsize * (2 * obs_size + action_size + 3)


def init(capacity: int, obs_size: int, action_size: int, dtype=jnp.float32) -> ReplayBuffer:
    z = lambda *shape: jnp.zeros((capacity, *shape), dtype)
    data = Transition(z(obs_size), z(action_size), z(), z(obs_size), z(), z())
    return ReplayBuffer(data=data, pos=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def insert(buf: ReplayBuffer, batch: Transition) -> ReplayBuffer:
    """Write ``batch`` (leading axis n, capacity % n == 0) at ``pos``."""
    n = batch.reward.shape[0]
    data = jax.tree.map(
        lambda d, b: jax.lax.dynamic_update_slice_in_dim(d, b.astype(d.dtype), buf.pos, axis=0),
        buf.data,
        batch,
    )
    pos = (buf.pos + n) % buf.capacity
    return ReplayBuffer(data=data, pos=pos, size=jnp.minimum(buf.size + n, buf.capacity))


def sample(buf: ReplayBuffer, key: jax.Array, batch_size: int) -> Transition:
    """Uniform sample with replacement from the filled rows."""
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buf.size, 1))
    return jax.tree.map(lambda d: d[idx], buf.data)
