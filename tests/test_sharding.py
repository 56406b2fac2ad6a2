"""Sharded sweeps and runner: the same results on 4 (forced CPU) devices as unsharded, and
the argument errors of ``ttd3_jax.run.sharding`` on one device."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest

from ttd3_jax.run import spec as sp
from ttd3_jax.run.sharding import SWEEP, make_mesh, runner_fns, shard_vmapped
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.trainer import seed_keys

HERE = os.path.dirname(os.path.abspath(__file__))
EXPECTED = (
    "OK meshes",
    "OK sweep of 4 on 4 devices equals jit(vmap)",
    "OK padding and divisibility error",
    "OK sharded runner epoch equals the unsharded fused train",
    "OK runner.run sharded with resume",
)


def run_sharded_check(*args: str) -> list[str]:
    """tests/_sharded_check.py in a fresh process that sees 4 CPU devices (the device count
    is fixed when JAX starts, so it cannot run in this process); its stdout lines.

    It compares sharded with unsharded programs, both compiled in that process with the
    same flags, so LLVM's optimisation level cannot matter to what it checks: at -O0 it
    compiles in about two thirds of the time."""
    # XLA's fusion emitters named on (XLA's default): with ttd3_jax.compile_flags' emitters off,
    # the sharded and unsharded sweeps fuse differently, and after 2 epochs of training one of
    # 16384 buffer entries differed by 5.7e-5 relative (2026-12-07; docs/scaling.md)
    flags = ("--xla_force_host_platform_device_count=4 --xla_backend_optimization_level=0 "
             "--xla_cpu_use_fusion_emitters=true")  # fmt: skip
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    p = subprocess.run(
        [sys.executable, os.path.join(HERE, "_sharded_check.py"), *args],
        env=env, cwd=os.path.dirname(HERE), capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    output = f"--- stdout\n{p.stdout}\n--- stderr\n{p.stderr[-6000:]}"
    assert p.returncode == 0, f"_sharded_check.py exited with {p.returncode}\n{output}"
    lines = p.stdout.splitlines()
    for want in EXPECTED[: 3 if args == ("sweep",) else None]:
        assert any(line.startswith(want) for line in lines), f"missing {want!r}\n{output}"
    return lines


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_sharded_sweeps_on_four_cpu_devices():
    """A sweep of 4 (seeds x beta) on 4 devices equals ``jit(vmap)``, with padding."""
    run_sharded_check("sweep")


@pytest.mark.slow
def test_sharded_runner_on_four_cpu_devices():
    """The runner on a 2 x 2 (seed, env) mesh equals the unsharded fused train, resume included."""
    run_sharded_check()


def _toy(k, b):
    return jax.random.normal(k, (3,)) * b


def test_mesh_and_shard_errors_on_one_device():
    one = jax.devices()[:1]
    mesh = make_mesh(devices=one)
    assert dict(mesh.shape) == {SWEEP: 1, "env": 1}
    with pytest.raises(ValueError, match="n_env"):
        make_mesh(n_env=0, devices=one)
    with pytest.raises(ValueError, match="n_env"):
        make_mesh(n_env=2, devices=one)
    with pytest.raises(ValueError, match="needs 2 devices"):
        make_mesh(n_sweep=2, devices=one)

    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    b = jnp.arange(3.0)
    out = shard_vmapped(_toy, (0, 0), mesh=mesh)(keys, b)  # any size divides one device
    assert out.shape == (3, 3)
    with pytest.raises(ValueError, match="in_axes entries 0 or None"):
        shard_vmapped(_toy, (1, None), mesh=mesh)
    with pytest.raises(ValueError, match="one entry per argument"):
        shard_vmapped(_toy, 0, mesh=mesh)
    with pytest.raises(ValueError, match="different sizes"):
        shard_vmapped(_toy, (0, 0), mesh=mesh)(keys, jnp.arange(2.0))
    with pytest.raises(ValueError, match="maps no argument"):
        shard_vmapped(_toy, (None, None), mesh=mesh)(keys[0], 1.0)


def test_non_divisible_sweep_needs_pad():
    """On one device, a mesh listing that device twice stands in for 2 sweep devices: the size
    checks run before anything is placed (tests/_sharded_check.py runs the real thing)."""
    d = jax.devices()[0]
    fake = make_mesh(devices=[d, d])
    assert fake.shape[SWEEP] == 2
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    with pytest.raises(ValueError, match="3 entries, not a multiple of the 2 devices"):
        shard_vmapped(_toy, (0, None), mesh=fake)(keys, 2.0)
    hp_axes = Hyper(**{**{f.name: None for f in dataclasses.fields(Hyper)}, "beta": 0})
    with pytest.raises(ValueError, match="3 entries"):
        shard_vmapped(lambda k, hp: hp.beta, (0, hp_axes), mesh=fake)(keys, Hyper(beta=jnp.zeros(3)))
    with pytest.raises(ValueError, match="num_seeds"):
        runner_fns(sp.trainer_for(sp.preset("fast")), seed_keys(0, 3), None, mesh=fake)
