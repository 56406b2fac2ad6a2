"""Who writes a run directory, and how its training ended.

``lock.json`` (pid, host, start time) is held by the one process that trains a run (a new
run or ``--resume``); a second writer is refused with the holder's name, and a lock whose
process is gone (same host, dead pid) is taken over with a note.  The lock is created with
its contents in one step (a hard link of a finished file), so no reader sees it half written.

``state.json`` says how the run stands: ``running``, ``stopped`` (by Ctrl-C, SIGTERM or
``stop_after``: resumable), ``failed`` (with the reason) or ``finished``.  A ``running`` run
whose lock holder is gone was killed: it resumes from its newest checkpoint.

Ctrl-C is a normal way to stop (:class:`Stop`): the first SIGINT or SIGTERM asks the loop to
stop after the epoch in progress, which it checkpoints; a second stops at once, and the run
keeps its newest checkpoint (:class:`RunStopped`).
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import shutil
import signal
import socket
import sys
import threading
from contextlib import contextmanager

LOCK = "lock.json"
STATE = "state.json"
STATES = ("running", "stopped", "failed", "finished")
logger = logging.getLogger(__name__)


class RunLocked(ValueError):
    """Another live process is training this run."""


class RunStopped(Exception):
    """A run stopped at once by a second Ctrl-C or SIGTERM: ``epoch`` is its newest checkpoint
    (``None``: none yet), ``reason`` the signal."""

    def __init__(self, run_dir: str, epoch: int | None, reason: str):
        self.run_dir, self.epoch, self.reason = run_dir, epoch, reason
        kept = f"its newest checkpoint is epoch {epoch}" if epoch is not None else "it has no checkpoint yet"
        how = "--resume" if epoch is not None else "--resume (it starts over) or --remove"
        super().__init__(
            f"stopped by {reason}; {kept}; continue with python -m ttd3_jax.train {how} {run_dir}"
        )


class Stop:
    """A request to stop training, set by SIGINT or SIGTERM while :meth:`installed`: the first
    signal asks the epoch loop to stop after the epoch in progress (``signal`` names it); a
    second raises ``KeyboardInterrupt`` at once."""

    def __init__(self):
        self.signal: str | None = None

    def requested(self) -> bool:
        return self.signal is not None

    def _handle(self, signum, frame):
        if self.signal is not None:
            raise KeyboardInterrupt
        self.signal = signal.Signals(signum).name
        print(f"{self.signal}: stopping after the epoch in progress (again to stop at once, keeping the "
              "newest checkpoint)", file=sys.stderr, flush=True)  # fmt: skip

    @contextmanager
    def installed(self):
        """Handle SIGINT and SIGTERM in this block (the main thread only; elsewhere, nothing)."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        before = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield self
        finally:
            for s, handler in before.items():
                signal.signal(s, handler)


def _now() -> str:
    return datetime.datetime.now().isoformat(timespec="seconds")


def _read(path: str) -> dict | None:
    try:
        with open(path) as fh:
            d = json.load(fh)
        return d if isinstance(d, dict) else None
    except (OSError, ValueError):
        return None


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def holder(run_dir: str) -> dict | None:
    """The lock's contents, or ``None`` when the run is not locked."""
    return _read(os.path.join(run_dir, LOCK))


def is_stale(lock: dict | None) -> bool:
    """A lock that holds nothing readable, or whose process on this host is gone."""
    if lock is None or not isinstance(lock.get("pid"), int):
        return True
    return lock.get("host") == socket.gethostname() and not alive(lock["pid"])


def acquire(run_dir: str) -> str | None:
    """Take ``run_dir``'s lock; returns a note when a stale lock was taken over.  Raises
    :class:`RunLocked` naming the holder when a live process has it."""
    path, note = os.path.join(run_dir, LOCK), None
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as fh:
        json.dump({"pid": os.getpid(), "host": socket.gethostname(), "since": _now()}, fh)
    try:
        for _ in range(3):
            try:
                os.link(tmp, path)  # atomic: fails when the lock exists
                return note
            except FileExistsError:
                lock = holder(run_dir)
                if not is_stale(lock):
                    raise RunLocked(
                        f"{run_dir} is being trained by pid {lock['pid']} on {lock.get('host')} (since "
                        f"{lock.get('since')}; {path}): one writer per run. Wait for it to end or stop it; "
                        "delete the lock file only if that process is gone"
                    ) from None
                who = f"pid {lock['pid']} on {lock.get('host')}" if lock else "an unreadable lock"
                note = f"took over the lock of {who}, which is no longer running"
                with _ignore_missing():
                    os.remove(path)
        raise RunLocked(f"could not take the lock {path}: other processes keep taking it")
    finally:
        os.remove(tmp)


@contextmanager
def _ignore_missing():
    try:
        yield
    except FileNotFoundError:
        pass


def release(run_dir: str) -> None:
    """Give the lock back (only if this process holds it)."""
    lock = holder(run_dir)
    if lock and lock.get("pid") == os.getpid() and lock.get("host") == socket.gethostname():
        with _ignore_missing():
            os.remove(os.path.join(run_dir, LOCK))


def mark(run_dir: str, state: str, **info) -> None:
    """Record the run's ``state`` (one of :data:`STATES`) with ``info`` (reason, epoch)."""
    if state not in STATES:
        raise ValueError(f"state must be one of {STATES}, got {state!r}")
    path = os.path.join(run_dir, STATE)
    with open(path + ".tmp", "w") as fh:
        json.dump({"state": state, "updated": _now(), **info}, fh)
    os.replace(path + ".tmp", path)


def state(run_dir: str) -> dict:
    """The run's recorded state (``{"state": "unknown"}`` for runs written before it was
    kept); a ``running`` run whose lock holder is gone reads ``interrupted``."""
    d = _read(os.path.join(run_dir, STATE)) or {"state": "unknown"}
    if d.get("state") == "running" and is_stale(holder(run_dir)):
        d = {**d, "state": "interrupted"}
    return d


@contextmanager
def writing(run_dir: str, log=None):
    """Hold ``run_dir``'s lock while training it: the state reads ``running``, ``stopped`` if the
    body raises :class:`RunStopped`, and ``failed`` with the reason if it raises anything else;
    the lock is released at the end.
    ``log`` says that a stale lock was taken over (default: this module's logger, INFO)."""
    note = acquire(run_dir)
    if note:
        (logger.info if log is None else log)(f"note: {note}")
    try:
        mark(run_dir, "running", pid=os.getpid())
        yield
    except RunStopped as e:
        mark(run_dir, "stopped", epoch=e.epoch, reason=e.reason)
        raise
    except BaseException as e:
        reason = " ".join(str(e).split())[:300] or type(e).__name__
        try:
            mark(run_dir, "failed", reason=f"{type(e).__name__}: {reason}")
        except OSError:  # a full disk takes the state file too; the lock still goes
            pass
        try:
            e.run_dir = run_dir  # for the CLI's message: what to --resume
        except AttributeError:
            pass
        raise
    finally:
        release(run_dir)


def remove_unstarted(run_dir: str) -> str:
    """Delete ``run_dir``, a run that stopped before its first checkpoint (``train --remove``):
    it holds nothing to resume or evaluate.  Refuses a directory that is not a run, a run
    with a checkpoint, logged epochs or results, and a run a live process is training."""
    if not os.path.isfile(os.path.join(run_dir, "config.json")):
        raise FileNotFoundError(f"no config.json in {run_dir!r}: not a ttd3_jax run directory")
    folder = os.path.join(run_dir, "checkpoints")
    steps = sorted(int(n) for n in os.listdir(folder) if n.isdigit()) if os.path.isdir(folder) else []
    kept = [f"checkpoint(s) {steps}"] if steps else []
    kept += [f for f in ("metrics.csv", "eval.json", "best") if os.path.exists(os.path.join(run_dir, f))]
    if kept:
        raise ValueError(
            f"{run_dir} holds {', '.join(kept)}: it is not a run that stopped before its first checkpoint. "
            f"Continue it with python -m ttd3_jax.train --resume {run_dir}, or delete the directory yourself"
        )
    acquire(run_dir)  # refuses while a live process trains it
    shutil.rmtree(run_dir)
    return f"removed {run_dir} (it stopped before its first checkpoint)"
