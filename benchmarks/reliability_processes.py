"""The fault scenarios of benchmarks/reliability.py that need real processes: ``python -m
ttd3_jax.train`` killed (SIGKILL) at chosen moments then resumed, compared with an
uninterrupted run; a second trainer racing for a live run; a full disk (a small tmpfs)."""

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

# tests/tiny.py's CLI run: 4 epochs of 16 vector steps, a checkpoint after each
CLI = ["--num-envs", "16", "--total-transitions", "1024", "--warmup-transitions", "128",
       "--buffer-size", "1024", "--batch-size", "64", "--updates-per-step", "2", "--epochs", "4",
       "--hidden", "32", "32",
       "--model-horizon", "2"]  # fmt: skip
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
    """metrics.csv without the wall-clock columns, and eval.json's evaluations (as text)."""
    with open(os.path.join(run_dir, "metrics.csv")) as fh:
        rows = [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(fh)]
    with open(os.path.join(run_dir, "eval.json")) as fh:
        ev = json.load(fh)
    return rows, json.dumps({k: ev.get(k) for k in ("final_eval", "selected")}, sort_keys=True)


def _checkpoints(run_dir: str | None) -> list[str]:
    folder = os.path.join(run_dir or "", "checkpoints")
    return os.listdir(folder) if os.path.isdir(folder) else []


def moments(out: str, t: Trainer) -> dict:
    """When to kill: each a condition on the run's files and output."""
    d = lambda: run_dir_of(out)  # noqa: E731
    has = lambda name: lambda: d() is not None and os.path.exists(os.path.join(d(), name))  # noqa: E731
    printed = lambda text: lambda: any(text in line for line in t.lines)  # noqa: E731
    return {
        "before the first checkpoint (warm-up)": has("config.json"),
        "compiling the epoch (after checkpoint 0)": printed("init + warm-up"),
        "mid-epoch 2": lambda: printed("epoch   1/4")() and time.sleep(0.3) is None,
        "during a checkpoint write": lambda: any(
            "tmp" in n and not n.startswith("0") for n in _checkpoints(d())
        ),
        "during the final results (after epoch 4)": printed("epoch   4/4"),
    }


def sigkill_then_resume(tmp: str, cache: str, quick: bool) -> dict:
    """Kill a run at each moment, resume it, and compare with an uninterrupted run; the
    uninterrupted run also meets a second trainer (``--resume`` of the same run)."""
    ref_out = os.path.join(tmp, "reference")
    ref = Trainer([*CLI, "--out", ref_out], cache)
    ref.wait_for(
        lambda: run_dir_of(ref_out) and os.path.exists(os.path.join(run_dir_of(ref_out), "lock.json"))
    )
    second = subprocess.run([sys.executable, "-m", "ttd3_jax.train", "--resume", run_dir_of(ref_out),
                             "--compile-cache", cache], capture_output=True, text=True)  # fmt: skip
    race = {"second trainer": f"exit {second.returncode}: {second.stderr.strip()[-300:]}"}
    assert ref.finish() == 0, "\n".join(ref.lines)
    want = results(run_dir_of(ref_out))
    out = {}
    names = list(moments("", ref))
    for i, name in enumerate(names[3:4] if quick else names):
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
                     f"{'identical' if same else 'DIFFERENT'} metrics.csv and eval.json")  # fmt: skip
    return {**out, **race}


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
