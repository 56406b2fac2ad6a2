"""Test-session setup: a persistent XLA compilation cache shared by the whole run.

Many tests build the same small programs more than once (a run, its interrupted twin and
its resume; the CLI in a subprocess), and on a 2-core CPU compiling them dominates the
suite's time.  The cache lives in a fresh temporary directory for this session only (so no
stale entry from another jax version is read), and the environment variables also reach
the subprocesses that tests start.  Cached programs are the same XLA executables, so
results do not change.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile

import pytest

from ttd3_jax.cli.console import PACKAGE_LOGGER, show_messages

# created here unless the environment names one: pytest-xdist's workers inherit the
# controller's, so that all of them share one cache (and only the controller removes it)
_OWN = "JAX_COMPILATION_CACHE_DIR" not in os.environ
if _OWN:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="ttd3_jax_xla_cache_")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")


def pytest_unconfigure(config):
    if _OWN:
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)


def pytest_report_header(config):
    return f"XLA compilation cache (shared by the workers): {os.environ['JAX_COMPILATION_CACHE_DIR']}"


@pytest.fixture
def shown_messages():
    """The package's log messages shown for one test as the command lines show them (the text
    alone: INFO on stdout, warnings on stderr), to read with ``capsys`` or ``capfd``."""
    log = logging.getLogger(PACKAGE_LOGGER)
    handlers, level, propagate = list(log.handlers), log.level, log.propagate
    show_messages()
    yield
    log.handlers[:], log.propagate = handlers, propagate
    log.setLevel(level)
