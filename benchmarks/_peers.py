"""Shared plumbing of the benchmarks: every record's header and goal lines, and, for the peer
benchmarks (``peer_*.py``), running a peer in its own interpreter.

A peer framework is often not installable next to this project (crazyflow excludes the
jax this project pins), so each peer runs in a *worker*: the benchmark script itself,
started with ``--worker`` by the Python of a venv that has the peer.  The parent sends one
JSON line per command (``build`` a case, ``time`` it once, ``run`` it once for the JSON-able
dict it returns, ``quit``) and reads one JSON line back; timings are taken inside the
worker, around the call only.  The parent interleaves ``time`` calls over all cases (its
own, in-process, and the workers'), so machine noise hits every case alike, as in the other
benchmarks.

Where a peer is looked for, in order: ``$TTD3_PEER_PYTHONS`` (interpreters separated by
``os.pathsep``), this interpreter, ``.venv-peers/bin/python``, ``.venv-crazyflow/bin/python``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PEER_VENVS = (REPO / ".venv-peers", REPO / ".venv-crazyflow")

# how to get each peer (the versions measured in docs/performance.md; see pyproject's extras)
INSTALL = {
    "crazyflow": (
        "python -m venv .venv-crazyflow && .venv-crazyflow/bin/pip install -e '.[transfer]'"
        "  (crazyflow 0.4.0 excludes jax 0.10.2, so it gets its own venv)"
    ),
    "rejax": "python -m venv .venv-peers && .venv-peers/bin/pip install -e '.[peers]'",
    "sbx": "python -m venv .venv-peers && .venv-peers/bin/pip install -e '.[peers]'",
    "stable_baselines3": (
        "python -m venv .venv-peers && .venv-peers/bin/pip install -e '.[peers]'"
        "  (install a CPU-only torch 2.13 build first where pip would pull a CUDA one)"
    ),
    "rltools": (
        "python -m venv .venv-peers && .venv-peers/bin/pip install -e '.[peers]'"
        "  (rltools compiles C++ at run time: it needs g++ or clang++ and the Python headers)"
    ),
}


def _has_module(python: str, module: str) -> bool:
    code = f"import importlib.util, sys; sys.exit(importlib.util.find_spec({module!r}) is None)"
    try:
        return subprocess.run([python, "-c", code], capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def find_python(module: str) -> str | None:
    """An interpreter that can import ``module`` (see the module docstring), or None."""
    env = [p for p in os.environ.get("TTD3_PEER_PYTHONS", "").split(os.pathsep) if p]
    cands = env + [sys.executable] + [str(v / "bin" / "python") for v in PEER_VENVS]
    seen = set()
    for py in cands:
        if py in seen or not Path(py).exists():
            continue
        seen.add(py)
        if _has_module(py, module):
            return py
    return None


def missing(peer: str) -> str:
    return f"peer {peer!r} not found in any interpreter tried; install it with:\n    {INSTALL[peer]}"


def timed(fn: Callable[[], object]) -> float:
    """Seconds of one call of ``fn`` (which must block until its work is done)."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


class Local:
    """Cases built and timed in this process; ``builders[kind](**params) -> (fn, info)``."""

    where = "local"

    def __init__(self, builders: dict[str, Callable]):
        self.builders, self.fns = builders, {}
        self.python = sys.executable

    def build(self, cid: str, kind: str, **params) -> dict:
        """Build case ``cid`` (a name unique within this run); returns its info dict."""
        fn, info = self.builders[kind](**params)
        self.fns[cid] = fn
        return info

    def time(self, cid: str) -> float:
        return timed(self.fns[cid])

    def run(self, cid: str) -> dict:
        """One call of a case whose function returns a JSON-able dict (it times itself)."""
        return self.fns[cid]()

    def forget(self, cid: str):
        self.fns.pop(cid, None)

    def close(self):
        self.fns.clear()


class Worker:
    """The same interface as :class:`Local`, served by ``script --worker`` under ``python``."""

    def __init__(self, python: str, script: str, name: str, path_first: str | None = None):
        """``path_first``: a directory put before the repo on the worker's ``PYTHONPATH`` (a
        ``ttd3_jax`` of another commit)."""
        self.python, self.name, self.where = python, name, f"worker:{name}"
        self.log = tempfile.NamedTemporaryFile("w+", prefix=f"peer-{name}-", suffix=".log", delete=False)
        # the repo on the path (ttd3_jax even where the peer's venv lacks it); a scratch working
        # directory, since MuJoCo (crazyflow) writes MUJOCO_LOG.TXT into it
        path = os.pathsep.join(p for p in (path_first, str(REPO), os.environ.get("PYTHONPATH", "")) if p)
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": path}
        self.scratch = tempfile.TemporaryDirectory(prefix=f"peer-{name}-")
        self.proc = subprocess.Popen(
            [python, script, "--worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
            cwd=self.scratch.name,
            env=env,
        )

    def call(self, op: str, **msg) -> dict:
        if self.proc.poll() is not None:
            raise RuntimeError(f"worker {self.name} exited ({self.proc.returncode}); log: {self.log.name}")
        self.proc.stdin.write(json.dumps({"op": op, **msg}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            self.log.flush()
            tail = Path(self.log.name).read_text()[-3000:]
            raise RuntimeError(f"worker {self.name} died; log {self.log.name}:\n{tail}")
        out = json.loads(line)
        if not out.pop("ok"):
            raise RuntimeError(f"worker {self.name}: {out['error']}\n{out.get('traceback', '')}")
        return out

    def build(self, cid: str, kind: str, **params) -> dict:
        return self.call("build", cid=cid, kind=kind, params=params)

    def time(self, cid: str) -> float:
        return self.call("time", cid=cid)["run_s"]

    def run(self, cid: str) -> dict:
        return self.call("run", cid=cid)

    def forget(self, cid: str):
        self.call("forget", cid=cid)

    def versions(self, modules) -> dict:
        return self.call("versions", modules=list(modules))

    def close(self):
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write(json.dumps({"op": "quit"}) + "\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=60)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
        self.log.close()
        self.scratch.cleanup()
        if self.proc.returncode == 0:  # keep the log of a worker that failed
            os.unlink(self.log.name)


def versions(modules) -> dict:
    """``{module: version}`` of those importable here (``None`` where not)."""
    from importlib import metadata

    dists = {"sbx": "sbx-rl", "stable_baselines3": "stable-baselines3", "ttd3_jax": "ttd3_jax"}
    out = {}
    for m in modules:
        try:
            out[m] = metadata.version(dists.get(m, m))
        except metadata.PackageNotFoundError:
            out[m] = None
    return out


def serve(builders: dict[str, Callable]) -> None:
    """Worker loop: JSON commands on stdin, one JSON reply per line on the real stdout.

    Anything the libraries print goes to stderr (the parent's log file), so it cannot
    corrupt the replies."""
    reply = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    local = Local(builders)
    for line in sys.stdin:
        msg = json.loads(line)
        op = msg.pop("op")
        if op == "quit":
            break
        try:
            if op == "build":
                out = local.build(msg["cid"], msg["kind"], **msg["params"])
            elif op == "time":
                out = {"run_s": local.time(msg["cid"])}
            elif op == "run":
                out = local.run(msg["cid"])
            elif op == "forget":
                local.forget(msg["cid"])
                out = {}
            elif op == "versions":
                out = versions(msg["modules"])
            else:
                raise ValueError(f"unknown op {op!r}")
            reply.write(json.dumps({"ok": True, **out}) + "\n")
        except Exception as e:  # report to the parent, keep serving
            reply.write(
                json.dumps(
                    {"ok": False, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
                )
                + "\n"
            )


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_record(argv: list[str] | None, *, with_jax: bool = True) -> dict:
    """Where and when: the fields every benchmark record starts with (date, command, machine,
    CPU model, cores, Python; jax's device kind and version unless ``with_jax`` is False)."""
    cmd = " ".join(["python", os.path.relpath(sys.argv[0], REPO), *(sys.argv[1:] if argv is None else argv)])
    rec = dict(
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        command=cmd,
        machine=platform.machine(),
        cpu=cpu_model(),
        cpus=os.cpu_count(),
        python=platform.python_version(),
    )
    if with_jax:
        import jax

        rec.update(device=jax.devices()[0].device_kind, jax=jax.__version__)
    return rec


def print_goals(goals: dict, fmt: str = "{:.3g}", label: str = "") -> None:
    """One line per goal: ``goal NAME LABEL: VALUE -> met|MISSED`` (``fmt`` formats VALUE)."""
    for k, v in goals.items():
        print(f"goal {k}{label}: {fmt.format(v['value'])} -> {'met' if v['met'] else 'MISSED'}")


def append_record(path: str, record: dict) -> None:
    if path:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        with open(path, "a") as fh:
            fh.write(json.dumps(record) + "\n")
        print(f"appended to {path}")


def print_machine(record: dict):
    """Print the header line of a peer benchmark's table (our device, cores, jax, CPU)."""
    import jax

    dev = jax.devices()[0]
    print(
        f"device={dev.platform} ({dev.device_kind}) cpus={os.cpu_count()} jax={jax.__version__} "
        f"{record['cpu']}"
    )
