"""Importing the trainer, and building a quadrotor run's trainer, load none of the packages that
only a Brax task, a checkpoint or an optional output needs (issue 51: they cost about 0.8 s of
the CLI's 2.1 s of imports).  Each check runs in a fresh interpreter, whose ``sys.modules``
holds exactly what the code imported."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
# Brax and MJX (a Brax task, brax_compat), orbax (a checkpoint), matplotlib (a plot), tensorboardX
# (a run's TensorBoard log), onnx (an export)
LAZY = ("brax", "mujoco", "orbax", "tensorstore", "matplotlib", "tensorboardX", "onnx")


def loaded_after(code: str) -> list[str]:
    """The packages of :data:`LAZY` that a fresh interpreter has imported after running ``code``."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}})))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT)
    return [m for m in json.loads(out.stdout.splitlines()[-1]) if m in LAZY]


def test_importing_the_trainer_and_the_env_loads_no_brax_mjx_or_orbax():
    assert loaded_after("import ttd3_jax.train, ttd3_jax.sim.env, ttd3_jax.td3.trainer") == []


def test_building_the_fast_presets_trainer_loads_none_of_them():
    code = "from ttd3_jax.run import spec as sp\nsp.trainer_for(sp.preset('fast'))"
    assert loaded_after(code) == []
