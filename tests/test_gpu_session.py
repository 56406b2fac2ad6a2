"""``benchmarks/gpu/session1.sh`` runs only on a GPU machine, where a stale name costs a
session: every module it imports or runs, every script it starts and every flag it passes
must exist today (checked here on the CPU, without running the session)."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "gpu" / "session1.sh"
OURS = ("ttd3_jax",)  # modules whose CLI the test runs with --help (others need only import)


def session_text() -> str:
    return SCRIPT.read_text().replace("\\\n", " ")  # continuation lines joined


def commands() -> list[tuple[str, list[str]]]:
    """``(target, flags)`` of each ``python3 -m MODULE`` / ``python3 PATH.py`` in the script:
    the module or script, and the ``--flags`` up to the command's first redirection or pipe."""
    out = []
    for line in session_text().splitlines():
        for m in re.finditer(r"python3 (?:-m ([\w.]+)|([\w/.\-]+\.py))([^|>&;#)]*)", line):
            out.append((m.group(1) or m.group(2), re.findall(r"(--[\w\-]+)", m.group(3))))
    return out


def imported_modules() -> list[str]:
    """Modules of the ``import`` statements inside ``python3 -c "..."`` lines."""
    mods = []
    for code in re.findall(r"python3 -c [\"']([^\"']*)[\"']", session_text()):
        for names in re.findall(r"import ([\w., ]+?)\s*(?:;|$)", code):
            mods += [n.strip() for n in names.split(",")]
    return mods


def test_the_parser_finds_the_session_commands():
    targets = [t for t, _ in commands()]
    assert "ttd3_jax.train" in targets and "experiments/mujoco_compare.py" in targets
    assert "ttd3_jax.sim.env" in imported_modules()


def test_every_module_and_script_the_session_names_exists():
    missing = [t for t, _ in commands() if t.endswith(".py") and not (REPO / t).is_file()]
    modules = [t for t, _ in commands() if not t.endswith(".py")] + imported_modules()
    missing += [m for m in modules if importlib.util.find_spec(m) is None]
    assert not missing, f"session1.sh names what does not exist: {missing}"


CLIS = sorted({t for t, _ in commands() if t.endswith(".py") or t.startswith(OURS)})


@pytest.mark.parametrize("target", CLIS)
def test_every_cli_the_session_runs_takes_its_flags(target):
    cmd = [sys.executable, *(["-m", target] if not target.endswith(".py") else [str(REPO / target)])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([*cmd, "--help"], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    flags = {f for t, fs in commands() if t == target for f in fs}
    unknown = sorted(f for f in flags if not re.search(re.escape(f) + r"\b", r.stdout))
    assert not unknown, f"{target} --help does not list {unknown}"
