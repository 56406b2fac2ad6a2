"""The tracking env's state pytrees (Brax ``State.pipeline_state``), one class per kind of
env, so that each keeps its layout (and its training runs' checkpoints) when another gains
a part; and the two reads of a state that the closed loop shares with the env: the action
the plant applies next, and the shift of the observed reference.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.dynamics import QuadState


@struct.dataclass
class TrackingState:
    """What the simulator carries between steps (Brax ``State.pipeline_state``)."""

    quad: QuadState
    k: jax.Array  # int32, physics step index
    track: tr.Track
    wind: jax.Array  # (3,) m/s^2, OU acceleration disturbance
    key: jax.Array  # PRNG key for wind and observation noise
    ref_next: jax.Array  # (3,) m, p_d(k+1), cached by ``observe`` for the next reward


@struct.dataclass
class DelayedTrackingState(TrackingState):
    """The state of an env with ``action_delay = 1``.  A subclass, so that undelayed envs
    (and the checkpoints of their training runs) keep the layout of :class:`TrackingState`."""

    prev_action: jax.Array  # (4,) action the next step applies (the hover action at reset)


@struct.dataclass
class MemoryTrackingState(TrackingState):
    """The state of an env with ``obs_memory`` (a subclass, like the delayed one)."""

    last_action: jax.Array  # (4,) the action applied by the last step (zeros at reset)
    err_int: jax.Array  # (3,) m·s, leaky ∫(p_d − p) dt of the observed p


@struct.dataclass
class RandomizedTrackingState(TrackingState):
    """The state of an env with domain randomisation (``sim.randomization.active``): the
    episode's plant, the commands still in flight, and the memory parts (a subclass, like
    the others, so that an env without randomisation keeps its layout)."""

    plant: rz.Plant
    pending: jax.Array  # (M, 4) the last M commanded actions, newest first (hover at reset)
    last_action: jax.Array  # (4,) the action the last step commanded (zeros at reset)
    err_int: jax.Array  # (3,) m·s, leaky ∫(p_d − p) dt of the observed p (obs_memory)


@struct.dataclass
class IntegralMemoryState(MemoryTrackingState):
    """:class:`MemoryTrackingState` with ``observation.ref_integral_gain`` > 0."""

    ref_int: jax.Array  # (3,) m·s, ∫ (p_d − p) dt of the observed p, per axis while within ± band


@struct.dataclass
class IntegralRandomizedState(RandomizedTrackingState):
    """:class:`RandomizedTrackingState` with ``observation.ref_integral_gain`` > 0."""

    ref_int: jax.Array  # (3,) m·s, as IntegralMemoryState's


def reference_shift(cfg: EnvConfig, ps: TrackingState) -> jax.Array | float:
    """s (3,) m, added to every reference point the observation shows (integral action around
    the policy, ``observation.ref_integral_gain``); 0.0 without it."""
    o = cfg.observation
    if o.ref_integral_gain == 0:
        return 0.0
    return jnp.clip(o.ref_integral_gain * ps.ref_int, -o.ref_integral_limit, o.ref_integral_limit)


def last_applied_action(cfg: EnvConfig, ps: TrackingState, a: jax.Array) -> jax.Array:
    """The normalised action that the last physics step of the next control step applies,
    when ``a`` (4,) is commanded from state ``ps``: ``a`` clipped, the previous one under
    ``action_delay``, or the one the randomised plant's latency picks."""
    a = jnp.clip(a, -1.0, 1.0)
    if isinstance(ps, RandomizedTrackingState):
        stack = jnp.concatenate([a[None].astype(ps.pending.dtype), ps.pending])
        return stack[rz.commanded_lags(cfg, ps.plant.latency)[-1]]
    if cfg.disturbances.action_delay:
        return ps.prev_action
    return a


@struct.dataclass
class HistoryMemoryState(IntegralMemoryState):
    """:class:`IntegralMemoryState` with ``observation.action_history_s`` (its ``ref_int`` stays
    0 where ``ref_integral_gain`` is 0)."""

    act_hist: jax.Array  # (n, 4) leaky averages of the applied action, one row per time constant


@struct.dataclass
class HistoryRandomizedState(IntegralRandomizedState):
    """:class:`IntegralRandomizedState` with ``observation.action_history_s``."""

    act_hist: jax.Array  # (n, 4) as HistoryMemoryState's
