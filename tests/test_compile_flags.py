"""The XLA flags ttd3_jax compiles with (``ttd3_jax.compile_flags``): added on import, a flag
the user names kept as the user set it, none added once JAX's backends have started."""

from __future__ import annotations

import os
import subprocess
import sys

from ttd3_jax import compile_flags as cf

FUSION, LEVEL = "--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=1"


def test_the_flags_wanted_leave_the_users_and_an_accelerators_alone():
    assert cf.wanted({}, accelerator_plugin=False) == [FUSION, LEVEL]
    assert cf.wanted({}, accelerator_plugin=True) == [FUSION]  # the level is read by the GPU backend too
    mine = {"XLA_FLAGS": "--xla_backend_optimization_level=3 --xla_force_host_platform_device_count=2"}
    assert cf.wanted(mine, accelerator_plugin=False) == [FUSION]
    both = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true --xla_backend_optimization_level=3"}
    assert cf.wanted(both, accelerator_plugin=False) == []


def _python(code: str, xla_flags: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    cmd = [sys.executable, "-W", "always", "-c", code]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)


def test_importing_the_package_sets_them_before_jax_starts_and_keeps_the_users():
    show = "import os, ttd3_jax, jax; jax.numpy.ones(1).block_until_ready(); print(os.environ['XLA_FLAGS'])"
    p = _python(show, None)
    assert p.returncode == 0, p.stderr
    flags = p.stdout.split()
    assert FUSION in flags and (LEVEL in flags or not cf.has_accelerator_plugin())
    p = _python(show, "--xla_cpu_use_fusion_emitters=true")
    assert p.returncode == 0, p.stderr
    assert "--xla_cpu_use_fusion_emitters=true" in p.stdout and FUSION not in p.stdout


def test_a_backend_started_first_gets_a_warning_and_no_flags():
    late = "import os, jax; jax.numpy.ones(1).block_until_ready(); import ttd3_jax; "
    late += "print(os.environ.get('XLA_FLAGS'))"
    p = _python(late, None)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "None"
    assert "JAX started its backends before ttd3_jax was imported" in p.stderr
