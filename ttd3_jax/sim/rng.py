"""``split`` and ``normal`` for raw Threefry keys, in a form XLA:CPU can fuse.

jax lowers the Threefry-2x32 hash on CPU as a rolled loop of 5 iterations; inside a
scanned env step that loop is a chain of small kernels that costs about twice the rest of
the step.  This module registers the same hash, written out round by round, as a jax PRNG
implementation, so that jax's own ``split`` / ``normal`` run on it and the draw fuses into
the step.  The draws are bit for bit those of ``jax.random`` on the same raw ``uint32[2]``
key (tests/test_rng.py); arithmetic fused with them may round differently in the last bit
(the env's wind is checked identical; its observation noise stays on ``jax.random``).  With
``jax_threefry_partitionable`` off, typed keys, or no ``define_prng_impl``, the functions
here call ``jax.random``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def _rotl(x: jax.Array, d: int) -> jax.Array:
    return lax.shift_left(x, np.uint32(d)) | lax.shift_right_logical(x, np.uint32(32 - d))


def threefry2x32(k1: jax.Array, k2: jax.Array, x1: jax.Array, x2: jax.Array):
    """The Threefry-2x32 hash (20 rounds) of counters ``(x1, x2)`` under key ``(k1, k2)``;
    uint32 arrays that broadcast together.  Unrolled: plain integer ops only."""
    ks = (k1, k2, k1 ^ k2 ^ np.uint32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x1 = x1 + x2
            x2 = x1 ^ _rotl(x2, r)
        x1 = x1 + ks[(i + 1) % 3]
        x2 = x2 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x1, x2


def _counters(shape: tuple[int, ...]):
    """jax's partitionable counters: the row-major index of each entry as (hi, lo) words."""
    n = math.prod(shape)
    if n >= 2**32:
        raise ValueError(f"draw of {n} values; allowed: fewer than 2**32")
    lo = lax.iota(np.uint32, n).reshape(shape) if shape else jnp.zeros((), np.uint32)
    return jnp.zeros(shape, np.uint32), lo


def _split(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    b1, b2 = threefry2x32(key[0], key[1], *_counters(shape))
    return jnp.stack([b1, b2], axis=b1.ndim)


def _random_bits(key: jax.Array, bit_width: int, shape: tuple[int, ...]) -> jax.Array:
    b1, b2 = threefry2x32(key[0], key[1], *_counters(shape))
    if bit_width == 64:
        return lax.shift_left(b1.astype(np.uint64), np.uint64(32)) | b2.astype(np.uint64)
    bits = b1 ^ b2
    return bits if bit_width == 32 else bits.astype(np.dtype(f"uint{bit_width}"))


def _define_impl():
    """The unrolled impl, or ``None`` where this jax lacks the public hooks (then every
    function here falls back to ``jax.random``)."""
    try:
        from jax.extend import random as jex_random

        base = jex_random.threefry_prng_impl
        return jex_random.define_prng_impl(
            key_shape=(2,),
            seed=base.seed,
            split=_split,
            random_bits=_random_bits,
            fold_in=base.fold_in,
            name="threefry2x32_unrolled",
            tag="fru",
        )
    except (ImportError, AttributeError, TypeError):
        return None


_FUSED = _define_impl()


def _raw_threefry(key: jax.Array) -> bool:
    """True when ``key`` is a raw uint32[2] Threefry key and jax draws from it the way
    this module does (``jax_threefry_partitionable`` on, Threefry the default impl)."""
    return (
        _FUSED is not None
        and key.dtype == jnp.uint32
        and key.shape[-1:] == (2,)
        and bool(jax.config.jax_threefry_partitionable)
        and jax.config.jax_default_prng_impl == "threefry2x32"
    )


def split(key: jax.Array, num: int = 2) -> jax.Array:
    """``jax.random.split(key, num)``: (num, 2) uint32, bit for bit."""
    if not _raw_threefry(key):
        return jax.random.split(key, num)
    return jax.random.key_data(jax.random.split(jax.random.wrap_key_data(key, impl=_FUSED), num))


def normal(key: jax.Array, shape: tuple[int, ...] = (), dtype=float) -> jax.Array:
    """``jax.random.normal(key, shape, dtype)``, bit for bit."""
    if not _raw_threefry(key):
        return jax.random.normal(key, shape, dtype)
    return jax.random.normal(jax.random.wrap_key_data(key, impl=_FUSED), shape, dtype)
