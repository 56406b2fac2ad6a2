"""Replay buffer held on the device: a ring of transitions, written one env batch at a time.

The capacity is a multiple of the number of parallel envs, so every insert is one
``dynamic_update_slice`` of ``num_envs`` rows at ``pos``, and sampling is one ``randint``
gather: nothing is O(capacity) per step.  Row ``r`` holds env ``r % num_envs``.
Hand-written on purpose: a pytree of the train state (vmapped, checkpointed and resumed with it).
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


def sample_n_step(buf: ReplayBuffer, key: jax.Array, batch_size: int, *, n: int, num_envs: int, gamma):
    """A uniform minibatch whose rows carry n-step returns (``TrainConfig.n_step``).

    Row ``r + num_envs`` is env ``r % num_envs``'s next step, so from each sampled row the
    same env's next ``n - 1`` rows follow at strides of ``num_envs``.  A row's return sums
    ``γ^k r_k`` over the m <= n steps until its episode ended (``done``: termination or
    truncation) or the newest row written; ``next_obs`` and ``terminated`` are the m-th step's,
    so a truncated episode bootstraps from its last observation and a terminated one does not.
    Returns ``(batch, γ^m (B,), the sampled rows' one-step rewards (B,))``."""
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buf.size, 1))
    avail = (buf.pos - idx - 1) % buf.capacity + 1  # rows from idx (included) to the newest
    steps = num_envs * jnp.arange(n)
    data = jax.tree.map(lambda d: d[(idx[:, None] + steps[None, :]) % buf.capacity], buf.data)  # (B, n, ...)
    ended_before = jnp.cumsum(data.done, axis=1) - data.done  # episodes ended at an earlier step
    use = (steps[None, :] < avail[:, None]) & (ended_before == 0)  # (B, n): prefixes, step 0 always
    m = jnp.sum(use, axis=1)
    reward = jnp.sum(jnp.where(use, gamma ** jnp.arange(n) * data.reward, 0.0), axis=1)
    rows = jnp.arange(batch_size)
    batch = Transition(obs=data.obs[:, 0], action=data.action[:, 0], reward=reward,
                       next_obs=data.next_obs[rows, m - 1], terminated=data.terminated[rows, m - 1],
                       done=data.done[rows, m - 1])  # fmt: skip
    return batch, gamma**m, data.reward[:, 0]
