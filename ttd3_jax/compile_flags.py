"""The XLA flags ttd3_jax compiles with: 0.52-0.58x the compile time on CPU.

``python benchmarks/compile_time.py`` (the ``fast`` preset's three programs, a fresh process
each, no compilation cache) measures the flags side by side: XLA:CPU's older loop emitters
instead of its fusion emitters (``--xla_cpu_use_fusion_emitters=false``) and LLVM's
optimisation level 1 instead of 3 (``--xla_backend_optimization_level=1``) together compile
in 0.52-0.58x the time, and the compiled epochs run about 1.3x slower (docs/performance.md): a
default run, which compiles once and trains for seconds, is shorter with them.  Both
move the last bits of results, as another CPU's instruction set does.

:func:`apply` adds them to ``XLA_FLAGS`` when ``ttd3_jax`` is imported, before JAX starts a
backend, so the command lines, the Python API, the tests and the benchmarks compile alike.
A flag the user's ``XLA_FLAGS`` already names is left as the user set it; the optimisation
level is left alone where a GPU or TPU plugin is installed (measured on CPU only).
"""

from __future__ import annotations

import importlib.util
import os
import sys
import warnings

CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
CPU_ONLY_FLAGS = ("--xla_backend_optimization_level=1",)  # also read by the GPU backend
_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin", "libtpu")


def wanted(environ: dict, accelerator_plugin: bool) -> list[str]:
    """The flags to add to ``environ``'s ``XLA_FLAGS``: those it does not name already."""
    current = environ.get("XLA_FLAGS", "")
    flags = list(CPU_FLAGS) + ([] if accelerator_plugin else list(CPU_ONLY_FLAGS))
    return [f for f in flags if f.split("=")[0] not in current]


def has_accelerator_plugin() -> bool:
    return any(importlib.util.find_spec(p) is not None for p in _PLUGINS)


def apply() -> None:
    """Add the flags to ``os.environ["XLA_FLAGS"]`` (see the module's docstring); warn once
    when JAX's backends started before, since then they cannot apply."""
    add = wanted(os.environ, has_accelerator_plugin())
    if not add:
        return
    if "jax" in sys.modules:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            warnings.warn(
                f"ttd3_jax: JAX started its backends before ttd3_jax was imported, so its compile flags "
                f"{' '.join(add)} do not apply (compiles take longer; results differ in the last bits "
                "from the documented ones); import ttd3_jax before running JAX code",
                stacklevel=3,
            )
            return
    os.environ["XLA_FLAGS"] = " ".join(x for x in (os.environ.get("XLA_FLAGS", ""), *add) if x)
