"""The fault scenarios of benchmarks/reliability.py that need real processes: ``python -m
ttd3_jax.train`` killed (SIGKILL) or stopped (SIGINT, SIGTERM, SIGINT twice) at chosen moments
then resumed, compared with an uninterrupted run; a second trainer racing for a live run;
``evaluate`` and ``export`` aimed at a run's own files; a full disk (a small tmpfs)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import rundir, status

# tests/tiny.py's CLI run: 4 epochs of 16 vector steps, a checkpoint after each
CLI = ["--num-envs", "16", "--total-transitions", "1024", "--warmup-transitions", "128",
       "--buffer-size", "1024", "--batch-size", "64", "--updates-per-step", "2", "--epochs", "4",
       "--hidden", "32", "32",
       "--model-horizon", "2"]  # fmt: skip
EPOCHS = 4
TIMING = {"wall_s", "steps_per_s"}  # wall-clock columns: never equal between two runs


class Trainer:
    """``python -m ttd3_jax.train ARGS`` with its output read line by line in a thread."""

    def __init__(self, args: list[str], cache: str):
        cmd = [sys.executable, "-m", "ttd3_jax.train", *args, "--compile-cache", cache]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, cond, timeout: float = 600.0) -> bool:
        """Poll ``cond()`` every 2 ms until it holds (``True``) or the process ends."""
        end = time.time() + timeout
        while time.time() < end and self.proc.poll() is None:
            if cond():
                return True
            time.sleep(0.002)
        return False

    def finish(self, timeout: float = 600.0) -> int:
        code = self.proc.wait(timeout)
        self._reader.join()
        return code

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.finish()


def run_dir_of(out: str) -> str | None:
    dirs = [os.path.join(out, d) for d in os.listdir(out)] if os.path.isdir(out) else []
    return dirs[0] if dirs else None


def results(run_dir: str) -> tuple:
    """metrics.csv without the wall-clock columns, eval.json's evaluations (as text), and the
    digest of the final checkpoint's contents (every leaf's dtype, shape and bytes)."""
    with open(os.path.join(run_dir, "metrics.csv")) as fh:
        rows = [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(fh)]
    with open(os.path.join(run_dir, "eval.json")) as fh:
        ev = json.load(fh)
    evals = json.dumps({k: ev.get(k) for k in ("final_eval", "selected")}, sort_keys=True)
    return rows, evals, ckpt.digests(run_dir).get(EPOCHS)


SAME = "metrics.csv, eval.json and final checkpoint"  # what results() compares


def _checkpoints(run_dir: str | None) -> list[str]:
    folder = os.path.join(run_dir or "", "checkpoints")
    return os.listdir(folder) if os.path.isdir(folder) else []


def _newest(run_dir: str) -> int | None:
    return max((int(n) for n in _checkpoints(run_dir) if n.isdigit()), default=None)


def moments(out: str, t: Trainer) -> dict:
    """When to kill: each a condition on the run's files and output."""
    d = lambda: run_dir_of(out)  # noqa: E731
    has = lambda name: lambda: d() is not None and os.path.exists(os.path.join(d(), name))  # noqa: E731
    printed = lambda text: lambda: any(text in line for line in t.lines)  # noqa: E731
    return {
        "before the first checkpoint (warm-up)": has("config.json"),
        "compiling the epoch (after checkpoint 0)": printed("init + warm-up"),
        "after compiling, before epoch 1": printed("compiled epoch + eval"),
        "mid-epoch 2": lambda: printed("epoch   1/4")() and time.sleep(0.3) is None,
        "during epoch 2 (epoch 1 printed)": printed("epoch   1/4"),
        "during a checkpoint write": lambda: any(
            "tmp" in n and not n.startswith("0") for n in _checkpoints(d())
        ),
        "during the final results (after epoch 4)": printed("epoch   4/4"),
    }


KILL_AT = ("before the first checkpoint (warm-up)", "compiling the epoch (after checkpoint 0)", "mid-epoch 2",
           "during a checkpoint write", "during the final results (after epoch 4)")  # fmt: skip


def reference(tmp: str, cache: str) -> tuple[tuple, str]:
    """An uninterrupted run's :func:`results`, and how a second trainer (``--resume`` of the
    same run while it trains) ended."""
    ref_out = os.path.join(tmp, "reference")
    ref = Trainer([*CLI, "--out", ref_out], cache)
    ref.wait_for(
        lambda: run_dir_of(ref_out) and os.path.exists(os.path.join(run_dir_of(ref_out), "lock.json"))
    )
    second = subprocess.run([sys.executable, "-m", "ttd3_jax.train", "--resume", run_dir_of(ref_out),
                             "--compile-cache", cache], capture_output=True, text=True)  # fmt: skip
    assert ref.finish() == 0, "\n".join(ref.lines)
    return results(run_dir_of(ref_out)), f"exit {second.returncode}: {second.stderr.strip()[-300:]}"


def sigkill_then_resume(tmp: str, cache: str, quick: bool, want: tuple) -> dict:
    """Kill a run at each moment, resume it, and compare with the uninterrupted run ``want``."""
    out = {}
    for i, name in enumerate(KILL_AT[3:4] if quick else KILL_AT):
        run_out = os.path.join(tmp, f"killed{i}")
        t = Trainer([*CLI, "--out", run_out], cache)
        hit = t.wait_for(moments(run_out, t)[name])
        t.kill()
        r = Trainer(["--resume", run_dir_of(run_out)], cache)
        code = r.finish()
        said = next((line for line in r.lines if "resumed" in line or "starting it over" in line), "?")
        same = code == 0 and results(run_dir_of(run_out)) == want
        killed = "killed" if hit else "ended before the moment"
        out[name] = (f"{killed}; resume exit {code} ({said.strip()[:60]}...); "
                     f"{'identical' if same else 'DIFFERENT'} {SAME}")  # fmt: skip
    return out


# (signals, moment, whether the run stops): a signal after the last epoch lets the run finish
STOP_AT = [
    (["SIGINT"], "during epoch 2 (epoch 1 printed)", True),
    (["SIGINT"], "before the first checkpoint (warm-up)", True),
    (["SIGINT"], "after compiling, before epoch 1", True),
    (["SIGINT"], "during a checkpoint write", True),
    (["SIGINT"], "during the final results (after epoch 4)", False),
    (["SIGTERM"], "during epoch 2 (epoch 1 printed)", True),
    (["SIGINT", "SIGINT"], "during epoch 2 (epoch 1 printed)", True),
]


def sigint_then_resume(tmp: str, cache: str, quick: bool, want: tuple) -> dict[str, tuple[bool, str]]:
    """Stop a run with signals at each moment (a second one once the first is acknowledged),
    check how it stopped, then ``train --resume OUT`` (the ``--out`` folder) and compare with
    the uninterrupted run ``want``.  Before resuming the first, the readers are aimed at its
    files (:func:`readers_never_write_into_a_run`).  ``{label: (as promised, what happened)}``."""
    out = {}
    for i, (signals, name, stops) in enumerate(STOP_AT[:1] if quick else STOP_AT):
        run_out = os.path.join(tmp, f"stopped{i}")
        t = Trainer([*CLI, "--out", run_out], cache)
        hit = t.wait_for(moments(run_out, t)[name])
        for n, sig in enumerate(signals):
            if n:  # the second once the first is acknowledged: two pending signals are one
                t.wait_for(lambda s=sig, t=t: any(line.startswith(f"{s}: stopping") for line in t.lines), 60)
            t.proc.send_signal(getattr(signal, sig))
        code = t.finish()
        run_dir = run_dir_of(run_out)
        ok, said = _stopped(t, code, run_dir, signals, stops)
        if i == 0:
            out.update(readers_never_write_into_a_run(run_dir, cache, quick))
        r = Trainer(["--resume", run_out], cache)
        resumed = r.finish()
        again = next((line for line in r.lines if "resumed" in line or "finished" in line), "?")
        same = resumed == 0 and results(run_dir) == want
        label = f"{' twice' if len(signals) > 1 else ''} {name}"
        out[f"{signals[0]}{label}"] = (hit and ok and same, (
            f"{'' if hit else 'ENDED BEFORE THE MOMENT; '}{said}; --resume OUT exit {resumed} "
            f"({_cut(again, run_dir)[:45]}...); {'identical' if same else 'DIFFERENT'} {SAME}"))  # fmt: skip
    return out


def _cut(text: str, run_dir: str) -> str:
    return text.strip().replace(run_dir, "RUN")


def _stopped(t: Trainer, code: int, run_dir: str, signals: list[str], stops: bool) -> tuple[bool, str]:
    """Whether a run sent ``signals`` stopped as promised (exit 130, no traceback, one line
    naming the epoch kept and the resume command, state.json ``stopped``, that epoch the
    newest checkpoint) or, when not ``stops``, finished (exit 0): ``(ok, what happened)``."""
    tracebacks = sum("Traceback" in line for line in t.lines)
    st, newest = status.state(run_dir), _newest(run_dir)
    head = f"exit {code}; Traceback lines: {tracebacks}; state.json {st.get('state')}"
    if not stops:
        return code == 0 and not tracebacks and st.get("state") == "finished", head
    sig, epoch = signals[0], st.get("epoch")
    said = [line for line in t.lines if line.startswith(f"stopped by {sig}")]
    where = f"its newest checkpoint is epoch {epoch}" if len(signals) > 1 else f"after epoch {epoch}/{EPOCHS}"
    line_ok = len(said) == 1 and where in said[0] and said[0].endswith(f"--resume {run_dir}")
    ok = (code == 130 and not tracebacks and line_ok and st.get("state") == "stopped"
          and st.get("reason") == sig and newest == epoch)  # fmt: skip
    return ok, (f"{head} ({st.get('reason')}, epoch {epoch}), newest checkpoint {newest}; "
                f"{len(said)} stop line: {_cut(said[0], run_dir) if said else '-'!r}")  # fmt: skip


# each reader aimed at each of a run's own files and folders (E: its newest checkpoint)
READERS = [
    *(["evaluate", "--no-timing", "--json", f"RUN/{f}"] for f in
      ("config.json", "metrics.csv", "state.json", "checkpoints/E/evaluation.json", "best/evaluation.json")),
    *(["export", "--no-onnx", "--out", f"RUN/{f}"] for f in
      ("checkpoints/E", "best", "config.json", "metrics.csv", "state.json")),
]  # fmt: skip


def _files(run_dir: str) -> dict[str, bytes]:
    """``{path under run_dir: contents}`` of every file (a tiny run: a few MB)."""
    found = {}
    for d, _, names in os.walk(run_dir):
        for n in names:
            with open(os.path.join(d, n), "rb") as fh:
                found[os.path.relpath(os.path.join(d, n), run_dir)] = fh.read()
    return found


def _own(files: dict[str, bytes]) -> dict[str, bytes]:
    own = (*rundir.OWN_FILES, *rundir.OWN_FOLDERS)
    return {p: b for p, b in files.items() if p.split(os.sep)[0] in own}


def readers_never_write_into_a_run(run_dir: str, cache: str, quick: bool) -> dict[str, tuple[bool, str]]:
    """``evaluate --json`` and ``export --out`` aimed at each of a stopped run's own files and
    folders: each refused (exit 2, one error line naming why, no traceback) with every file of
    the run unchanged and none added; then ``evaluate RUN --no-timing`` runs (its outputs go
    beside the run's files) leaving the run's own files unchanged.  The caller resumes it."""
    epoch = str(_newest(run_dir))
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache}  # evaluate's compiled programs
    out = {}
    for argv in READERS[5:6] if quick else READERS:
        before = _files(run_dir)
        args = [a.replace("/E", f"/{epoch}").replace("RUN", run_dir) for a in argv]
        res = subprocess.run([sys.executable, "-m", f"ttd3_jax.{args[0]}", run_dir, *args[1:]],
                             capture_output=True, text=True, env=env)  # fmt: skip
        errors = [line for line in res.stderr.splitlines() if "error:" in line]
        kept = _files(run_dir) == before
        ok = res.returncode == 2 and len(errors) == 1 and "Traceback" not in res.stderr and kept
        why = _cut(errors[0].split("error: ", 1)[1], run_dir) if errors else res.stderr.strip()[-200:]
        out[f"{argv[0]} RUN {' '.join(argv[1:])}"] = (ok, (
            f"exit {res.returncode}, {len(errors)} error line: {why!r}; "
            f"the run's files {'unchanged' if kept else 'CHANGED'}"))  # fmt: skip
    before = _own(_files(run_dir))
    res = subprocess.run([sys.executable, "-m", "ttd3_jax.evaluate", run_dir, "--no-timing"],
                         capture_output=True, text=True, env=env)  # fmt: skip
    kept = _own(_files(run_dir)) == before
    said = f"exit {res.returncode} (checkpoint {epoch}); the run's own files"
    out["evaluate RUN --no-timing (then)"] = (res.returncode == 0 and kept,
                                              f"{said} {'unchanged' if kept else 'CHANGED'}")  # fmt: skip
    return out


def full_disk(tmp: str, cache: str) -> dict:
    """A run whose disk fills after checkpoint 1 (a tmpfs filled by a file), then resumed
    once the file is removed.  Needs root (mount); skipped with a note otherwise."""
    mnt = os.path.join(tmp, "tmpfs")
    os.makedirs(mnt)
    mount = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", mnt], capture_output=True, text=True
    )
    if mount.returncode != 0:
        return {"full disk": f"skipped: mount failed ({mount.stderr.strip()[:100]})"}
    try:
        out = os.path.join(mnt, "runs")
        t = Trainer([*CLI, "--out", out], cache)
        t.wait_for(lambda: "1" in _checkpoints(run_dir_of(out)))
        filler = os.path.join(mnt, "filler")
        subprocess.run(["dd", "if=/dev/zero", f"of={filler}", "bs=1M"], capture_output=True)
        code = t.finish()
        tracebacks = sum("Traceback" in line for line in t.lines)
        progress = [i for i, line in enumerate(t.lines) if line.startswith("[")]
        after = len(t.lines) - 1 - max(progress, default=-1)  # the one error line, and nothing else
        os.remove(filler)
        r = Trainer(["--resume", run_dir_of(out)], cache)
        resumed = r.finish()
        last = t.lines[-1] if t.lines else ""
        return {"full disk": f"exit {code}; last line {last!r}; Traceback lines: {tracebacks}; "
                f"lines after the last progress line: {after}; "
                f"after freeing space, --resume exit {resumed}"}  # fmt: skip
    finally:
        subprocess.run(["umount", mnt], capture_output=True)
        shutil.rmtree(mnt, ignore_errors=True)
