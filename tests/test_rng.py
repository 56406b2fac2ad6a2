"""ttd3_jax.rng draws exactly what jax.random draws, so swapping it in changed no result."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax import rng


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
