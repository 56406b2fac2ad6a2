"""The experiments/ scripts as modules, for the tests that check them (not a test module)."""

from __future__ import annotations

import importlib.util
import os
import sys

EXPERIMENTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "experiments")


def experiment(name: str):
    """``experiments/<name>.py`` loaded as a module (its ``__main__`` block does not run),
    registered in ``sys.modules`` as ``name`` (dataclasses look their module up there)."""
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXPERIMENTS, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
