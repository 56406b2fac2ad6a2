"""Brax's env API, ``State`` and ``Env``, without importing Brax.

``brax.envs.base`` imports all of Brax and MuJoCo MJX (about 0.5 s, a quarter of the trainer's
import), which a quadrotor run never uses.  These two classes are the interface the tracking
env and the trainer rely on, field for field and method for method as in
``brax/envs/base.py``, so that Brax's wrappers and trainers drive an env built on them:
:mod:`ttd3_jax.interop.brax_compat` registers :class:`Env` as a ``brax.envs.Env``, for the
``isinstance`` checks of Brax's SAC and ARS.
"""

from __future__ import annotations

import abc
from typing import Any

import jax
from flax import struct


@struct.dataclass
class State:
    """An env's state between steps: Brax's ``State`` fields (not its arithmetic of
    ``brax.base.Base``, which only Brax's physics pipelines and renderer use)."""

    pipeline_state: Any  # the simulator's own pytree (the tracking env's: sim.env_state)
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array] = struct.field(default_factory=dict)
    info: dict[str, Any] = struct.field(default_factory=dict)


class Env(abc.ABC):
    """Brax's ``Env`` interface: ``reset``, ``step``, the observation and action sizes, the
    physics backend's name, and ``unwrapped`` (the env under any wrappers)."""

    @abc.abstractmethod
    def reset(self, rng: jax.Array) -> State:
        """The initial state of an episode."""

    @abc.abstractmethod
    def step(self, state: State, action: jax.Array) -> State:
        """The state one env step after ``state`` under ``action``."""

    @property
    @abc.abstractmethod
    def observation_size(self) -> int:
        """The length of ``State.obs``."""

    @property
    @abc.abstractmethod
    def action_size(self) -> int:
        """The length of the action ``step`` takes."""

    @property
    @abc.abstractmethod
    def backend(self) -> str:
        """The name of the physics backend."""

    @property
    def unwrapped(self) -> Env:
        return self
