"""Brax's own trainers and registry on the tracking env.

Brax 0.14.2 (the newest release) calls ``jax.device_put_replicated``, which JAX removed in
0.10 (google/brax#671, still open). :func:`install` puts back an equivalent built on public
APIs, only when JAX lacks one: a leading axis of ``len(devices)`` copies, sharded one copy per
device (a ``NamedSharding`` over a 1-D mesh, what ``jax.pmap`` takes and Flax's
``jax_utils.replicate`` does). Then ``brax.training.agents.ppo.train`` and ``sac.train`` run
on :class:`~ttd3_jax.sim.env.TrackingEnv` unchanged (tests/test_brax_trainers.py)::

    from ttd3_jax.interop import brax_compat
    brax_compat.install()
    make_policy, params, _ = ppo.train(TrackingEnv(cfg), episode_length=cfg.episode_length, ...)

Importing this module registers the env with Brax as ``"ttd3_quadrotor"`` (:func:`make_env`
takes a preset and ``EnvConfig`` fields), so ``brax.envs.get_environment("ttd3_quadrotor",
preset="practical")`` and ``brax.envs.create("ttd3_quadrotor", episode_length=300,
preset="practical")`` work. Pass ``create`` the env's own ``episode_length`` (its default,
1000, would cut paper episodes of 3000 steps short).

The tracking env is built on :mod:`ttd3_jax.sim.env_api` (Brax's ``Env`` and ``State``
without Brax, which the package loads only for a Brax task); importing this module also
registers that ``Env`` as a subclass of ``brax.envs.Env``, which Brax's SAC and ARS check for.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ttd3_jax.run.tasks import load_brax_envs
from ttd3_jax.sim import env_api
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.env import TrackingEnv

brax_envs = load_brax_envs()

ENV_NAME = "ttd3_quadrotor"
_AXIS = "_replica"


def device_put_replicated(x, devices):
    """Each leaf of ``x`` stacked ``len(devices)`` times on a new leading axis, one copy on
    each device (the removed ``jax.device_put_replicated``)."""
    devices = list(devices)
    if not devices:
        raise ValueError("device_put_replicated needs at least one device, got an empty list")
    sharding = NamedSharding(Mesh(np.array(devices), (_AXIS,)), PartitionSpec(_AXIS))
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)


def install() -> bool:
    """Give JAX ``device_put_replicated`` if it has none; True when it was added now."""
    if hasattr(jax, "device_put_replicated"):
        return False
    jax.device_put_replicated = device_put_replicated
    return True


def make_env(preset: str = "paper", config: EnvConfig | None = None, **fields) -> TrackingEnv:
    """The tracking env of ``make_config(preset, **fields)``, or of ``config`` (then no other
    argument): the factory registered with Brax."""
    if config is not None:
        if fields or preset != "paper":
            raise ValueError(
                f"make_env takes config or preset and fields, not both; got preset={preset!r}, fields "
                f"{sorted(fields)}"
            )
        return TrackingEnv(config)
    return TrackingEnv(make_config(preset, **fields))


def register(name: str = ENV_NAME) -> None:
    """Register :func:`make_env` with Brax's env registry under ``name``, and the package's
    :class:`~ttd3_jax.sim.env_api.Env` as a ``brax.envs.Env`` (idempotent)."""
    brax_envs.Env.register(env_api.Env)
    brax_envs.register_environment(name, make_env)


register()
