"""Per-env vehicle parameters in the env state: one vmapped program flies a different
vehicle in each env; an env given no vehicle flies its config's exactly as before."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.sim.randomization import vehicle_arrays

N_ENVS, N_STEPS = 4, 200


def rollout(env, vehicles=None):
    """Vehicle states, observations and rewards of ``N_ENVS`` envs under fixed random actions."""
    keys = jax.random.split(jax.random.PRNGKey(0), N_ENVS)
    acts = jax.random.uniform(jax.random.PRNGKey(1), (N_STEPS, N_ENVS, 4), minval=-1.0, maxval=1.0)

    @jax.jit
    def run(keys, vehicles, acts):
        s = jax.vmap(env.reset)(keys, vehicles)

        def body(s, a):
            s = jax.vmap(env.step)(s, a)
            return s, (s.pipeline_state.quad, s.obs, s.reward)

        return jax.lax.scan(body, s, acts)[1]

    return jax.device_get(run(keys, vehicles, acts))


def stacked(*quads):
    return jax.tree.map(lambda *x: jnp.stack(x), *(vehicle_arrays(q) for q in quads))


def test_an_env_without_a_vehicle_carries_no_vehicle_leaves():
    env = TrackingEnv(make_config("paper"))
    plain, carried = (
        env.reset(jax.random.PRNGKey(0)),
        env.reset(jax.random.PRNGKey(0), env.config.vehicle.quad),
    )
    assert "vehicle" not in plain.info  # the nominal state keeps its layout (and checkpoints)
    extra = len(jax.tree.leaves(carried)) - len(jax.tree.leaves(plain))
    assert extra == len(jax.tree.leaves(env.config.vehicle.quad)) > 0


@pytest.mark.parametrize("preset", ["paper", "practical"])
def test_the_nominal_vehicle_in_the_state_flies_as_the_configs(preset):
    """Not bit for bit: XLA folds the config's constants into the arithmetic (a division by
    a constant mass becomes a product with its reciprocal), values read from the state are
    not folded, so a few last bits move (3e-9 m over 200 steps when measured)."""
    env = TrackingEnv(make_config(preset, quad=QuadParams.create(rate_model="first_order")))
    old, new = rollout(env), rollout(env, stacked(*[env.config.vehicle.quad] * N_ENVS))
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), old, new)


def test_two_masses_in_one_vmapped_program_diverge():
    env = TrackingEnv(make_config("paper", wind_sigma=0.0))
    nominal = env.config.vehicle.quad
    heavy = dataclasses.replace(nominal, mass=1.2 * nominal.mass)
    mixed = rollout(env, stacked(nominal, heavy, nominal, heavy))[0].p
    same = rollout(env, stacked(*[nominal] * N_ENVS))[0].p
    np.testing.assert_array_equal(mixed[:, 0::2], same[:, 0::2])  # envs do not see each other's vehicle
    sink = same[-1, 1::2, 2] - mixed[-1, 1::2, 2]  # the heavier vehicles end lower under the same actions
    assert (sink > 0.005).all(), sink
