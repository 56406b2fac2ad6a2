"""``python -m ttd3_jax.train``: train T-TD3 or TD3 (the CLI; the trainer is :mod:`ttd3_jax.td3`).

    python -m ttd3_jax.train                          # preset "fast": quadrotor, T-TD3, 1 seed
    python -m ttd3_jax.train --preset fast_dpg --algo td3 --num-seeds 3
    python -m ttd3_jax.train --task.reward.e-max 1.5 --hp.lr-actor 5e-4   # any field of the run spec
    python -m ttd3_jax.train --train-tracks my_tracks/ # + your CSV tracks in the training mixture
    python -m ttd3_jax.train --vehicle crazyflie      # a named vehicle (sim.vehicles) for the task
    python -m ttd3_jax.train --resume runs/RUN_DIR    # continue from the newest checkpoint
    python -m ttd3_jax.train --remove runs/RUN_DIR    # delete a run killed before its first checkpoint
    python -m ttd3_jax.train --help                   # every option, its default and units

Exit status: 0 done, 1 a full disk or no memory, 2 bad input (the message names it), 3 the run
diverged, 130 stopped by Ctrl-C or SIGTERM (resumable).
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import logging
import os
import sys
import threading

import tyro

from ttd3_jax.checks import bool_flags, refuse_bool_values
from ttd3_jax.cli.console import show_messages
from ttd3_jax.run import rundir, status
from ttd3_jax.run import spec as sp
from ttd3_jax.run.cache import use_compile_cache
from ttd3_jax.run.loop import TrainingDiverged, run
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim.vehicles import VEHICLE_NAMES, with_vehicle

PROG = "python -m ttd3_jax.train"
DESCRIPTION = (
    "Train T-TD3 or TD3 (preset {preset!r}; defaults below are that preset's). Also: "
    "--preset {presets}, --out DIR (default runs), --resume RUN_DIR, --remove RUN_DIR (delete a run "
    "that stopped before its first checkpoint; a run with one is refused), "
    "--compile-cache DIR|none (XLA compilation cache; default ~/.cache/ttd3_jax/xla), "
    "--train-tracks CSV|DIR (your tracks in the training mixture, in a share "
    "--task.tracks.train-tracks-weight of the episodes), --vehicle {vehicles} (the task's vehicle, "
    "default: the preset's; --task.vehicle.quad.* flags apply on top)."
)


def track_files(path: str) -> tuple[str, ...]:
    """``--train-tracks``: one CSV file, or every ``*.csv`` in a directory (absolute paths)."""
    if os.path.isdir(path):
        files = sorted(os.path.join(path, f) for f in os.listdir(path) if f.endswith(".csv"))
        if not files:
            raise ValueError(f"--train-tracks {path!r}: the directory holds no .csv file")
    elif os.path.isfile(path):
        files = [path]
    else:
        raise ValueError(f"--train-tracks {path!r}: no such file or directory")
    for f in files:
        try:  # a bad file is refused now, naming it, not when the env is built
            ct.from_csv(f)
        except ValueError as e:
            raise ValueError(f"--train-tracks: {e}") from None
    return tuple(os.path.abspath(f) for f in files)


def preset_with_vehicle(name: str, vehicle: str | None) -> sp.RunSpec:
    """Run-spec preset ``name`` whose task flies ``vehicle`` (``None``: the preset's own)."""
    default = sp.preset(name)
    if vehicle is None:
        return default
    if vehicle not in VEHICLE_NAMES:
        raise ValueError(f"--vehicle must be one of {VEHICLE_NAMES}, got {vehicle!r}")
    if not default.is_quadrotor:
        raise ValueError(f"--vehicle sets the quadrotor env's vehicle; env {default.env!r} has none")
    return dataclasses.replace(default, task=with_vehicle(default.task, vehicle))


def parse(argv: list[str]) -> tuple[argparse.Namespace, sp.RunSpec | None]:
    """The launcher's own flags and the run spec (``None`` with ``--resume`` or ``--remove``).  Bad input
    raises ``ValueError`` (or exits 2 through tyro, which prints its own message)."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default=None)
    pre.add_argument("--out", default=None)
    pre.add_argument("--resume", default=None)
    pre.add_argument("--compile-cache", default=None)
    pre.add_argument("--train-tracks", default=None)
    pre.add_argument("--vehicle", default=None)
    pre.add_argument("--remove", default=None)
    known, rest = pre.parse_known_args(argv)
    if known.remove is not None:
        extra = [
            f"--{k.replace('_', '-')}" for k, v in vars(known).items() if v is not None and k != "remove"
        ]
        if extra + rest:
            raise ValueError(
                f"--remove deletes a run and takes nothing else; remove {' '.join(extra + rest)}"
            )
        return known, None
    if known.resume is not None:
        given = [k for k in ("preset", "out", "train_tracks", "vehicle") if getattr(known, k) is not None]
        extra = [f"--{k.replace('_', '-')}" for k in given] + rest
        if extra:
            raise ValueError(f"--resume continues the saved run spec; remove {' '.join(extra)}")
        known.resume, note = rundir.find_run(known.resume)
        if note:
            print(note)
        return known, None
    name = "fast" if known.preset is None else known.preset
    if name not in sp.PRESETS:
        raise ValueError(f"--preset must be one of {sp.PRESETS}, got {name!r}")
    default = preset_with_vehicle(name, known.vehicle)
    refuse_bool_values(rest, bool_flags(sp.RunSpec))
    spec = tyro.cli(
        sp.RunSpec,
        default=default,
        args=rest,
        prog=PROG,
        description=DESCRIPTION.format(
            preset=name, presets="|".join(sp.PRESETS), vehicles="|".join(VEHICLE_NAMES)
        ),
    )
    if not spec.is_quadrotor and spec.task != default.task:
        changed = [f.name for f in dataclasses.fields(spec.task) if getattr(spec.task, f.name) !=
                   getattr(default.task, f.name)]  # fmt: skip
        raise ValueError(f"--task.* sets the quadrotor env; env {spec.env!r} has none (changed: {changed})")
    if known.train_tracks is not None:
        task = spec.task.replace(train_tracks=track_files(known.train_tracks))
        spec = dataclasses.replace(spec, task=task)
    known.out = "runs" if known.out is None else known.out
    rundir.check_out_dir(known.out)
    return known, spec


def main(argv: list[str] | None = None) -> int:
    """The CLI (see the module docstring); returns the exit status."""
    _quiet_background_failures()  # orbax's warnings and errors are ours to phrase
    show_messages()  # the runner's log, as plain lines
    try:
        known, spec = parse(list(sys.argv[1:] if argv is None else argv))
        if known.remove is not None:
            print(status.remove_unstarted(known.remove))
            return 0
        cache = use_compile_cache(known.compile_cache)
        note = " (--compile-cache none turns it off)" if cache else ""
        print(f"XLA compilation cache: {cache or 'off'}{note}")
        with status.Stop().installed() as stop:  # Ctrl-C / SIGTERM: stop after the epoch in progress
            if spec is None:
                out = run(resume=known.resume, stop=stop)
            else:
                out = run(spec, out=known.out, stop=stop)
        if out.get("stopped_by"):
            return 130  # stopped by a signal, resumable (the loop said where and how)
    except status.RunStopped as e:  # a second Ctrl-C
        print(f"{e}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:  # before the run directory was written
        print("stopped by SIGINT before the run started; nothing was written", file=sys.stderr)
        return 130
    except Exception as e:  # one line with what to do, no traceback
        message = failure_message(e)  # first: a full disk reaches us as orbax's ValueError too
        if message is not None:
            print(f"error: {message}", file=sys.stderr)
            return 1
        if isinstance(e, FileNotFoundError | ValueError):  # RunLocked included
            print(f"error: {e}", file=sys.stderr)
            return 2
        if isinstance(e, TrainingDiverged):
            print(f"error: {e}", file=sys.stderr)
            return 3
        raise
    return 0


def _quiet_background_failures() -> None:
    """orbax saves in background threads; when a save fails (a full disk), its threads log
    the error and their asyncio loops print 'Event loop is closed' tracebacks before the
    failure reaches the runner, which reports it in one line.  Keep those off stderr: the
    loggers at CRITICAL, a closed event loop's RuntimeError not printed, and nothing from an
    asyncio loop's finalizer (a second Ctrl-C that lands inside orbax's ``loop.close()``
    leaves the loop half closed, and its ``__del__`` then fails on the closed descriptor).
    Nothing else is filtered."""
    for name in ("absl", "asyncio", "concurrent.futures"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    closed = lambda e: isinstance(e, RuntimeError) and "Event loop is closed" in str(e)  # noqa: E731
    in_loop_finalizer = lambda args: getattr(args.object, "__qualname__", "") == "BaseEventLoop.__del__"  # noqa: E731
    thread_hook, hook = threading.excepthook, sys.excepthook
    unraisable = sys.unraisablehook  # tensorstore's C++ threads report through this one
    threading.excepthook = lambda args: None if closed(args.exc_value) else thread_hook(args)
    sys.excepthook = lambda kind, value, tb: None if closed(value) else hook(kind, value, tb)
    sys.unraisablehook = lambda args: (
        None if closed(args.exc_value) or in_loop_finalizer(args) else unraisable(args)
    )


def _chain(e: BaseException):
    while e is not None:
        yield e
        e = e.__cause__ or e.__context__


def failure_message(e: Exception) -> str | None:
    """The one line for a run stopped by a full disk or by running out of memory (``None``
    for other errors, which keep their traceback)."""
    run_dir = getattr(e, "run_dir", None)
    resume = f"python -m ttd3_jax.train --resume {run_dir}" if run_dir else "--resume RUN_DIR"
    if any(
        getattr(x, "errno", None) == errno.ENOSPC or "No space left on device" in str(x) for x in _chain(e)
    ):
        return f"the disk is full; free space, then continue with {resume}"
    if "RESOURCE_EXHAUSTED" in str(e) or isinstance(e, MemoryError):
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        return (f"out of memory ({first}); lower buffer_size, hidden, num_envs or num_seeds and start a new "
                f"run (or {resume} on a machine with more memory)")  # fmt: skip
    return None


def exit_with(code: int) -> None:
    """End the process with ``main``'s status.  A full disk or no memory (1), or a stop by a
    signal (130): orbax's save threads may still be failing or shutting down, and their
    shutdown (an asyncio loop's finalizer on a closed descriptor, after a second Ctrl-C) would
    print after the one line; the run's state is already written and its lock released, so
    end here, without them."""
    if code in (1, 130):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    raise SystemExit(code)


if __name__ == "__main__":
    exit_with(main())
