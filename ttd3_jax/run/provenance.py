"""What produced a run: one line per launch (a start or a resume) in the run directory's
``launches.jsonl``: when, the code (the git commit of the checkout ``ttd3_jax`` was imported
from, ``+dirty`` when its tracked files differ from it; else the installed version), JAX,
the machine and the XLA flags.  Results trained by two commits, or resumed on another
machine, say so in their own files.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess

import jax

FILE = "launches.jsonl"
PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # .../ttd3_jax


def _git(*args: str) -> str | None:
    try:
        p = subprocess.run(["git", "-C", os.path.dirname(PACKAGE), *args], capture_output=True, text=True,
                           timeout=10)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return p.stdout.strip() if p.returncode == 0 else None


def code_version() -> str:
    """``git:<commit>`` (``+dirty`` when the package's tracked files were changed) when the
    package lies in a git checkout that tracks it, else ``ttd3_jax <version>``."""
    if _git("ls-files", "--error-unmatch", os.path.join(PACKAGE, "__init__.py")) is not None:
        head = _git("rev-parse", "HEAD")
        if head:
            dirty = _git("status", "--porcelain", "--untracked-files=no", "--", PACKAGE)
            return f"git:{head}" + ("+dirty" if dirty else "")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"ttd3_jax {version('ttd3_jax')}"
    except PackageNotFoundError:
        return "ttd3_jax (version unknown)"


def cpu() -> str:
    """The CPU's model name, with ``AVX-512`` where it has it (XLA:CPU's code differs)."""
    try:
        with open("/proc/cpuinfo") as fh:
            text = fh.read()
    except OSError:
        return platform.processor() or platform.machine()
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), "")
    return (model or platform.machine()) + (" (AVX-512)" if " avx512f" in text else "")


def launch_record(kind: str) -> dict:
    """This process's record for a launch of ``kind`` (``start`` or ``resume``)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return dict(
        launch=kind, time=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        code=code_version(), jax=jax.__version__, device=jax.devices()[0].device_kind, cpu=cpu(),
        cores=cores, xla_flags=os.environ.get("XLA_FLAGS", ""),
    )  # fmt: skip


def record(run_dir: str, kind: str) -> dict:
    """Append this launch's record to ``run_dir``'s ``launches.jsonl`` and return it."""
    rec = launch_record(kind)
    with open(os.path.join(run_dir, FILE), "a") as fh:
        fh.write(json.dumps(rec) + "\n")
    return rec


def launches(run_dir: str) -> list[dict]:
    """The run's launch records, oldest first (none for a run from before they were kept)."""
    path = os.path.join(run_dir, FILE)
    if not os.path.exists(path):
        return []
    with open(path) as fh:
        return [json.loads(line) for line in fh if line.strip()]
