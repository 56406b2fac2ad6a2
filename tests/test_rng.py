"""ttd3_jax.sim.rng draws exactly what jax.random draws, so swapping it in changed no result."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.sim import rng


def _keys(n=257):
    return jax.random.split(jax.random.PRNGKey(7), n)


@pytest.mark.parametrize("num", [2, 3, 4])
def test_split_is_jax_split_bit_for_bit(num):
    ours = jax.jit(jax.vmap(lambda k: rng.split(k, num)))(_keys())
    theirs = jax.jit(jax.vmap(lambda k: jax.random.split(k, num)))(_keys())
    assert ours.dtype == theirs.dtype == jnp.uint32
    np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("shape", [(), (3,), (4,), (5, 7)])
def test_normal_is_jax_normal_bit_for_bit(shape):
    ours = jax.jit(jax.vmap(lambda k: rng.normal(k, shape, jnp.float32)))(_keys())
    theirs = jax.jit(jax.vmap(lambda k: jax.random.normal(k, shape, jnp.float32)))(_keys())
    assert ours.dtype == jnp.float32
    np.testing.assert_array_equal(ours, theirs)
    assert 0.9 < float(jnp.std(ours)) < 1.1  # and they are unit normals (257+ draws)


def test_normal_float64_is_jax_normal_bit_for_bit():
    with jax.enable_x64(True):
        ours = jax.vmap(lambda k: rng.normal(k, (3,), jnp.float64))(_keys())
        theirs = jax.vmap(lambda k: jax.random.normal(k, (3,), jnp.float64))(_keys())
        assert ours.dtype == jnp.float64
        np.testing.assert_array_equal(ours, theirs)


def test_unrolled_hash_matches_jax_threefry():
    from jax.extend.random import threefry_2x32

    key = jax.random.PRNGKey(123)
    count = jnp.arange(10, dtype=jnp.uint32)
    theirs = threefry_2x32(key, count)  # hashes the two halves of `count` as (x1, x2) pairs
    b1, b2 = rng.threefry2x32(key[0], key[1], count[:5], count[5:])
    np.testing.assert_array_equal(jnp.concatenate([b1, b2]), theirs)


def test_typed_keys_fall_back_to_jax_random():
    key = jax.random.key(0)
    np.testing.assert_array_equal(rng.normal(key, (3,)), jax.random.normal(key, (3,)))
    assert jax.random.key_data(rng.split(key)).shape == (2, 2)


def test_draws_inside_a_scan_have_no_while_loop_on_cpu():
    """The point of the module: the hash lowers to straight-line code, not jax's rolled loop."""

    def draw(k):
        k, sub = rng.split(k)
        return k, rng.normal(sub, (3,))

    hlo = jax.jit(draw).lower(jax.random.PRNGKey(0)).as_text()
    assert "while" not in hlo
    assert "while" in jax.jit(lambda k: jax.random.normal(k, (3,))).lower(jax.random.PRNGKey(0)).as_text()


def test_env_wind_is_unchanged_by_the_fused_draws(monkeypatch):
    """The paper env's OU wind (with observation noise on as well), stepped with
    ttd3_jax.sim.rng and with jax.random: identical observations, rewards and wind.

    Not a given: the draws are identical, but XLA fuses them with the arithmetic around
    them, which can change the last bit.  It did for the observation noise (31 of 6800
    entries off by one ulp), which is why that noise stays on jax.random."""
    import types

    import ttd3_jax.sim.numerics as wind_module  # the OU wind step (sim.numerics.ou_wind_step)
    from ttd3_jax.sim.config import make_config
    from ttd3_jax.sim.env import TrackingEnv

    env = TrackingEnv(make_config("paper", obs_noise_pos=0.01, obs_noise_vel=0.01, obs_noise_quat=0.01))
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    action = jnp.tile(jnp.array([0.47, 0.01, -0.02, 0.0]), (8, 1))

    def rollout():
        def body(s, _):
            s = jax.vmap(env.step)(s, action)
            return s, (s.obs, s.reward, s.pipeline_state.wind)

        return jax.jit(lambda k: jax.lax.scan(body, jax.vmap(env.reset)(k), None, length=50)[1])(keys)

    ours = rollout()
    jax_rng = types.SimpleNamespace(split=jax.random.split, normal=jax.random.normal)
    monkeypatch.setattr(wind_module, "rng", jax_rng)
    theirs = rollout()
    assert float(jnp.abs(ours[2]).max()) > 0  # the wind is on
    for a, b in zip(ours, theirs, strict=True):
        np.testing.assert_array_equal(a, b)
