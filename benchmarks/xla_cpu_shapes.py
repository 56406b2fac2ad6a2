"""What one elementwise pass costs on this backend, by array shape: the floor under the env step.

Under ``jax.vmap`` every per-env vector of the env becomes an ``(envs, F)`` array with the
env axis first: ``(N, 3)`` positions, ``(N, 4)`` quaternions, the ``(N, 17)`` observation.
Each case here is a jitted ``lax.scan`` of ``--steps`` steps whose body is one multiply
of such an array (one XLA kernel), timed beside the same number of entries laid out as
``(F, N)``, so the two columns differ only in which axis is the minor (contiguous) one.
The ``trig`` row is ``cos + sin`` of ``N`` angles (the spiral reference needs both).

    python benchmarks/xla_cpu_shapes.py            # N = 1024
    python benchmarks/xla_cpu_shapes.py --quick    # smoke run (CI)

Read the ``(N, F)`` column against ``(F, N)``: where it is several times slower, the
backend does not vectorise along the env axis for that shape, and every kernel of the
env step that writes such an array pays for it.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp

FEATURES = (1, 3, 4, 8, 16, 17, 32)


def _scan(fn, x, steps):
    def run(x):
        return jax.lax.scan(lambda c, _: (fn(c), None), x, None, steps)[0]

    return jax.jit(run).lower(x).compile()


def per_step_us(fn, x, steps: int, repeats: int) -> float:
    """Best-of-``repeats`` time of one scan step, µs."""
    compiled = _scan(fn, x, steps)
    jax.block_until_ready(compiled(x))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(x))
        best = min(best, time.perf_counter() - t0)
    return best / steps * 1e6


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    args = ap.parse_args(argv)
    if args.quick:
        args.envs, args.steps, args.repeats = 64, 20, 1
    if min(args.envs, args.steps, args.repeats) < 1:
        ap.error("--envs, --steps and --repeats must be >= 1")
    n = args.envs
    dev = jax.devices()[0]
    print(f"device={dev.platform} ({dev.device_kind}) cpus={os.cpu_count()} jax={jax.__version__} N={n}")
    print(f"{'F':>4} {'(N, F) us':>10} {'(F, N) us':>10} {'ratio':>6}")
    rows = []

    def scale(y):
        return y * 1.0001

    for f in FEATURES:
        key = jax.random.PRNGKey(f)
        a = per_step_us(scale, jax.random.normal(key, (n, f)), args.steps, args.repeats)
        b = per_step_us(scale, jax.random.normal(key, (f, n)), args.steps, args.repeats)
        rows.append(dict(features=f, env_major_us=a, env_minor_us=b))
        print(f"{f:>4} {a:>10.2f} {b:>10.2f} {a / b:>6.2f}")

    def trig(y):
        return jnp.cos(y) + jnp.sin(y)

    t = per_step_us(trig, jax.random.uniform(jax.random.PRNGKey(0), (n,)), args.steps, args.repeats)
    print(
        f"trig: cos + sin of {n} angles: {t:.2f} us per step ({t * 1e3 / (2 * n):.2f} ns per function value)"
    )
    return rows


if __name__ == "__main__":
    main()
