"""The Python loop around the compiled epochs: progress, evaluation, logs, checkpoints,
resume.  Each epoch is one compiled call; a checkpoint of the whole train state follows it,
so a kill loses at most the epoch in flight and a resume continues bit for bit.  What the
loop does is logged (``logging``, INFO; :mod:`ttd3_jax.cli.console` shows it); the per-epoch
progress line is printed on stdout.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable

import jax
import numpy as np

from ttd3_jax.control.paper import PAPER_TTD3, beats_paper
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import memory, provenance, report, rundir, status
from ttd3_jax.run import spec as sp
from ttd3_jax.run.cache import StoredProgram, program_store
from ttd3_jax.run.sharding import runner_fns
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.trainer import seed_keys

logger = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """Raised when losses or parameters stop being finite."""


@dataclasses.dataclass
class Stages:
    """Seconds of each stage of a launch (eval.json's ``stages``; ``None``: the stage did not
    run in this launch, e.g. ``restore_s`` on a fresh run or ``init_*`` on a resume)."""

    construct_s: float | None = None  # the trainer and its programs' Python objects
    restore_s: float | None = None  # a resume's checkpoint
    init_lower_s: float | None = None  # trace (or load the stored program) and lower
    epoch_lower_s: float | None = None
    eval_lower_s: float | None = None
    compile_s: float | None = None  # after tracing, the waits for init's and the epoch's compiles
    # (the eval program's, when still compiling, is waited for by the first evaluation)
    init_compile_s: float | None = None  # each program's own compile, overlapping the others'
    epoch_compile_s: float | None = None
    eval_compile_s: float | None = None
    warmup_s: float | None = None  # the init program's run (with the random warm-up's collection)
    first_checkpoint_s: float | None = None
    epochs: list = dataclasses.field(default_factory=list)  # per epoch: train_s, eval_s, host_s

    def as_dict(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


class LiveBar:
    """In-epoch progress on a terminal, redrawn in place by a host thread while the compiled
    epoch runs: the seconds so far and, from the second epoch on, the share of the previous
    epoch's time (an estimate: the compiled epoch reports nothing until it ends, so that its
    program holds no host callback and can be stored, :class:`~ttd3_jax.run.cache.StoredProgram`)."""

    def __init__(self, epochs: int, interval_s: float = 0.25):
        self.epochs, self.interval_s, self.last_s = epochs, interval_s, None
        self._stop, self._thread, self.epoch, self.t0 = threading.Event(), None, 0, 0.0

    def line(self, elapsed_s: float) -> str:
        """The bar ``elapsed_s`` seconds into the epoch."""
        head = f"  epoch {self.epoch}/{self.epochs}"
        if not self.last_s:
            return f"{head}  running {elapsed_s:6.1f} s"
        frac = min(elapsed_s / self.last_s, 0.99)
        bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
        return f"{head} [{bar}] ~{100 * frac:3.0f}%  {elapsed_s:6.1f} s of ~{self.last_s:.1f} s"

    def start(self, epoch: int) -> None:
        self.epoch, self.t0 = epoch, time.perf_counter()
        self._stop.clear()
        self._thread = threading.Thread(target=self._draw, daemon=True)
        self._thread.start()

    def _draw(self) -> None:
        while not self._stop.wait(self.interval_s):
            sys.stdout.write("\r" + self.line(time.perf_counter() - self.t0) + " ")
            sys.stdout.flush()

    def stop(self) -> None:
        """End the epoch's bar and clear it (call before printing anything else)."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread, self.last_s = None, time.perf_counter() - self.t0
        sys.stdout.write("\r" + " " * 80 + "\r")
        sys.stdout.flush()


def progress_line(epoch: int, epochs: int, m: dict, ev: dict, sps: float) -> str:
    """One line per epoch: env steps, steps/s, σ and the evaluation (medians over seeds)."""
    bar = "#" * int(20 * epoch / epochs) + "." * (20 - int(20 * epoch / epochs))
    steps, sigma = float(np.mean(m["env_steps"])), float(np.mean(m["sigma"]))
    if "val_tracking_error" in ev:
        sp_, los, val = (float(np.median(ev[k])) for k in ("spiral_tracking_error", "los_tracking_error",
                                                            "val_tracking_error"))  # fmt: skip
        tail = f"Spiral-RT {sp_:8.2f}  LOS-RT {los:8.2f}  val {val:8.2f}"
    else:
        tail = f"eval return {float(np.mean(ev['eval_return'])):9.2f}"
    return f"[{bar}] epoch {epoch:>3}/{epochs}  steps {steps:9.3g}  {sps:8.3g}/s  σ {sigma:.3g}  {tail}"


def check_finite(m: dict, ts, epoch: int, run_dir: str, mngr, critics: bool = True) -> None:
    """Stop a diverged run: name the losses and parameter groups that went non-finite, the
    epoch and the last good checkpoint, and what to try (``critics``: whether the critics
    train, so that their losses exist)."""
    losses = ("critic_loss", "q_mean", "actor_loss") if critics else ("actor_loss",)
    bad = [k for k in losses if not np.all(np.isfinite(np.asarray(m[k])))]
    for group in ("critic", "actor", "target_critic", "target_actor"):
        if not all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(getattr(ts, group))):
            bad.append(f"{group} parameters")
    if not bad:
        return
    critic_first = bad[0] in ("critic_loss", "q_mean", "critic parameters", "target_critic parameters")
    hint = "--hp.lr-critic" if critic_first else "--hp.lr-actor"
    steps = int(np.max(np.asarray(m["env_steps"])))
    raise TrainingDiverged(
        f"non-finite {', '.join(bad)} in epoch {epoch} (up to env step {steps}); stopped. The last good "
        f"checkpoint is epoch {ckpt.latest_epoch(mngr)} in {os.path.join(run_dir, 'checkpoints')}. Try a "
        f"lower learning rate ({hint}) or a smaller reward scale (--hp.reward-scale)."
    )


def run(spec: sp.RunSpec | None = None, out: str = "runs", *, resume: str | None = None,
        verbose: bool = True, stop_after: int | None = None, checkpoint_every: int = 1,
        stop: status.Stop | None = None) -> dict:  # fmt: skip
    """Train ``spec`` into a new run directory under ``out``, or continue the run in
    ``resume`` from its newest checkpoint that loads (a run without one starts over; a
    finished run is left as it is).  ``stop_after`` ends this call after that many epochs,
    as an interruption would (resume continues).  A checkpoint is written every
    ``checkpoint_every`` epochs and after the last one (a kill loses at most the epochs
    since; large replay buffers make each save cost seconds).  The memory the run needs is
    checked before anything is written or compiled, and the run directory is locked while
    it trains (:mod:`ttd3_jax.run.status`).  Returns a summary dict (run_dir, final eval,
    timings).  ``verbose``: log what the run does and print a progress line per epoch.
    ``stop`` (the CLI's Ctrl-C, :class:`~ttd3_jax.run.status.Stop`): once requested, the run
    stops after the epoch in progress, checkpointed, as ``stop_after`` does; a second request
    raises :class:`~ttd3_jax.run.status.RunStopped` (the run keeps its newest checkpoint)."""
    if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int) or checkpoint_every < 1:
        raise ValueError(f"checkpoint_every must be an integer >= 1, got {checkpoint_every!r}")
    log = logger.info if verbose else _quiet
    if resume is not None:
        spec = rundir.load_spec(resume)
        done = finished_note(resume, spec)
        if done:
            log(done)
            return {"run_dir": resume, "finished": True}
        check_train_tracks(resume, spec)
    elif spec is None:
        raise ValueError("run() needs a RunSpec or a run directory to resume")
    else:
        rundir.check_out_dir(out)
    c = spec.train
    if c.transitions_run != c.total_transitions:
        log(f"budget: {c.transitions_run:,} of total_transitions {c.total_transitions:,} per seed "
            f"({c.warmup_steps * c.num_envs:,} warm-up, then {c.epochs} epochs x {c.steps_per_epoch} vector "
            f"steps x {c.env_steps_per_step} env steps x {c.num_envs} envs)")  # fmt: skip
    if c.warmup_rollouts:
        log(f"warm-up: the first {c.warmup_rollouts} rollouts act at random ({c.warmup_transitions:,} "
            "transitions asked) and leave the actor alone")  # fmt: skip
    stages, t = Stages(), time.perf_counter()
    trainer = sp.trainer_for(spec)
    rows = getattr(trainer.env.env, "num_segments", None)  # the tracking env's table size (users' tracks)
    memory.check(spec, trainer.env.obs_size, trainer.env.action_size, track_rows=rows)  # before any write
    run_dir = resume if resume is not None else rundir.new_run_dir(out, spec)
    with status.writing(run_dir, log):
        provenance.record(run_dir, "resume" if resume is not None else "start")
        stop = stop or status.Stop()  # (never requested unless the CLI installed it)
        r = _Run(spec=spec, trainer=trainer, run_dir=run_dir, resuming=resume is not None, log=log,
                 verbose=verbose, stages=stages, stop=stop)  # fmt: skip
        try:
            return _train(r, t, stop_after, checkpoint_every)
        except KeyboardInterrupt:  # a second Ctrl-C: _train has closed its checkpoint writer
            raise status.RunStopped(run_dir, _newest_checkpoint(run_dir), stop.signal or "SIGINT") from None


def _newest_checkpoint(run_dir: str) -> int | None:
    m = ckpt.manager(run_dir, read_only=True)
    try:
        return m.latest_step()
    finally:
        m.close()


def _quiet(message: str) -> None:
    """``log`` of a run that is not verbose."""


@dataclasses.dataclass(frozen=True)
class _Run:
    """What one launch of :func:`run` works with."""

    spec: sp.RunSpec
    trainer: object
    run_dir: str
    resuming: bool
    log: Callable[[str], None]  # the module logger's ``info``, or ``_quiet``
    verbose: bool  # the progress line and the in-epoch bar
    stages: Stages
    stop: status.Stop  # Ctrl-C: stop after the epoch in progress


def finished_note(run_dir: str, spec: sp.RunSpec) -> str | None:
    """What to say instead of resuming a run that already finished (``None``: it did not)."""
    st = status.state(run_dir).get("state")
    folder = os.path.join(run_dir, "checkpoints")
    steps = [int(n) for n in os.listdir(folder) if n.isdigit()] if os.path.isdir(folder) else []
    legacy = st == "unknown" and os.path.isfile(os.path.join(run_dir, "eval.json"))
    if st == "finished" or (legacy and max(steps, default=-1) >= spec.train.epochs):
        return (f"{run_dir} finished all {spec.train.epochs} epochs (eval.json); nothing to resume. "
                f"Evaluate it with python -m ttd3_jax.evaluate {run_dir}")  # fmt: skip
    return None


def check_train_tracks(run_dir: str, spec: sp.RunSpec) -> None:
    """Refuse to resume a run whose training-track CSV is no longer where it trained from:
    training reads it (evaluation and export do not)."""
    gone = [p for p in spec.task.tracks.train_tracks if not os.path.isfile(p)]
    if gone:
        raise FileNotFoundError(
            f"--resume {run_dir}: its training track {gone[0]!r} is not a file (moved or deleted?); "
            "continuing the training reads the run's training tracks: put it back there (evaluate and "
            "export read the run without it)"
        )


def _train(r: _Run, t: float, stop_after: int | None, checkpoint_every: int) -> dict:
    """The run under its lock: start (or restore), compile, the epochs, the results."""
    spec, run_dir, log, stages, c = r.spec, r.run_dir, r.log, r.stages, r.spec.train
    live = LiveBar(c.epochs) if r.verbose and sys.stdout.isatty() else None
    keys, hp = seed_keys(spec.seed, spec.num_seeds), spec.hp
    # plain jit on one device; seeds (and envs) split over all visible devices otherwise
    init_fn, epoch_fn, eval_fn, place = _stored(spec, runner_fns(r.trainer, keys, hp))
    stages.construct_s, t = _since(t)
    mngr, pool = None, concurrent.futures.ThreadPoolExecutor(3)
    try:  # until the checkpoint being written in the background is on disk (also on errors, Ctrl-C)
        if r.resuming and (_has_checkpoint(run_dir) or os.path.exists(os.path.join(run_dir, "metrics.csv"))):
            ts, start, csv_log = _resume(run_dir, init_fn=init_fn, keys=keys, hp=hp, place=place, log=log)
            mngr = ckpt.manager(run_dir, asynchronous=True)  # after _resume deleted what does not load
            stages.restore_s, t = _since(t)
            shape = jax.eval_shape(lambda t: t, ts)
            programs = {"epoch": (epoch_fn, (shape, hp))} if start < c.epochs else {}
            pending, t = _compile({**programs, "eval": (eval_fn, (shape,))}, stages, t, pool)
        else:
            if r.resuming:
                log(f"{run_dir} has no checkpoint (it stopped before its first): starting it over")
            shape = init_fn.eval_shape(keys, hp)  # (traces init, or loads it; its lowering comes later)
            stages.init_lower_s, t = _since(t)  # the epoch, the longest compile, goes first
            programs = {"epoch": (epoch_fn, (shape, hp)), "init": (init_fn, (keys, hp))}
            pending, t = _compile({**programs, "eval": (eval_fn, (shape,))}, stages, t, pool)
            mngr = ckpt.manager(run_dir, asynchronous=True)  # (imports orbax while the programs compile)
            init_c, t = pending.wait("init", t)
            ts, start, csv_log, t = _fresh(r, mngr=mngr, init_c=init_c, keys=keys, hp=hp, t=t)
        # (a checkpointed last epoch needs only eval, whose compile is waited for when first called)
        epoch_c, t = pending.wait("epoch", t) if "epoch" in programs else (None, t)
        eval_c = pending.when_ready("eval")
        lowered = sum(getattr(stages, f"{n}_lower_s") for n in pending.names)
        log(f"compiled {' + '.join(pending.names)} in {lowered + stages.compile_s:.1f} s (trace "
            f"{lowered:.1f} s, then compile {stages.compile_s:.1f} s, at once); "
            f"{spec.num_seeds} seed(s) x {c.num_envs} envs, {c.steps_per_epoch} vector steps x "
            f"{c.updates_per_step} updates per epoch")  # fmt: skip
        last = c.epochs if stop_after is None else min(c.epochs, start + stop_after)
        loop = EpochLoop(spec=spec, run_dir=run_dir, mngr=mngr, csv_log=csv_log, epoch_c=epoch_c,
                         eval_c=eval_c, live=live, verbose=r.verbose, every=checkpoint_every,
                         stop=r.stop)  # fmt: skip
        ts, ev, run_s, stages.epochs = _epochs(loop, ts, start, last)
        if r.stop.requested():
            last = start + len(stages.epochs)  # the epochs this launch finished, the last checkpointed
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
        if mngr is not None:
            ckpt.close(mngr)
    if last < c.epochs:
        by = r.stop.signal
        status.mark(run_dir, "stopped", epoch=last, **({"reason": by} if by else {}))
        log(f"stopped{f' by {by}' if by else ''} after epoch {last}/{c.epochs} (checkpointed); continue "
            f"with python -m ttd3_jax.train --resume {run_dir}")  # fmt: skip
        return {"run_dir": run_dir, "stopped_at": last, "stopped_by": by}
    ev = ev if ev is not None else jax.device_get(eval_c(ts))
    summary = _finish(run_dir, spec, ev, compile_s=lowered + stages.compile_s, run_s=run_s, stages=stages)
    status.mark(run_dir, "finished", epoch=last)
    log(f"results in {run_dir}: metrics.csv, eval.json, learning_curve.png, checkpoints/{best_note(spec)}")
    return summary


def _has_checkpoint(run_dir: str) -> bool:
    return _newest_checkpoint(run_dir) is not None


def _fresh(r: _Run, *, mngr, init_c, keys, hp, t: float):
    """Initialise (with the warm-up, where it precedes the epochs) and write checkpoint 0:
    ``(ts, 0, csv_log, t)``."""
    stages, c = r.stages, r.spec.train
    ts = jax.block_until_ready(init_c(keys, hp))
    stages.warmup_s, t = _since(t)
    ckpt.save(mngr, 0, ts, wait=False)  # written while the first epoch trains (the programs are compiled)
    stages.first_checkpoint_s, t = _since(t)
    csv_log = rundir.CsvLog(os.path.join(r.run_dir, "metrics.csv"))
    r.log(f"run dir {r.run_dir}")
    r.log(f"init + warm-up ({c.warmup_steps * c.num_envs:,} transitions per seed): run "
          f"{stages.warmup_s:.1f} s, checkpoint {stages.first_checkpoint_s:.1f} s")  # fmt: skip
    return ts, 0, csv_log, t


def _stored(spec: sp.RunSpec, fns: tuple) -> tuple:
    """The runner's functions with their traced programs kept beside the compilation cache
    (:class:`~ttd3_jax.run.cache.StoredProgram`), so a warm launch skips tracing; keyed on the spec
    without its traced values and on the contents of the files it names.  Not over several
    devices (``fns`` as they are then)."""
    store = program_store()
    if store is None or jax.device_count() > 1:
        return fns
    init_fn, epoch_fn, eval_fn, place = fns
    context = repr(dataclasses.replace(spec, seed=0, hp=Hyper()))  # the seed and hp values are traced
    kw = dict(context_files=spec)  # the contents of the files it names (training-track CSVs)
    return (StoredProgram(init_fn, "init", context, store, **kw),
            StoredProgram(epoch_fn, "epoch", context, store, donate_argnums=(0,), **kw),
            StoredProgram(eval_fn, "eval", context, store, **kw), place)  # fmt: skip


def _compile(programs: dict, stages: Stages, t: float, pool: concurrent.futures.Executor):
    """``programs`` (name: ``(fn, args)``) traced one after the other (tracing holds the GIL),
    then compiling all at once in ``pool`` (XLA's compiles release it; the persistent
    compilation cache may answer them): ``(Pending, the time now)``.  Adds each program's
    trace to ``<name>_lower_s``; its compile sets ``<name>_compile_s`` as it ends.
    (Compiling each program as soon as it was traced, beside the next one's trace, was
    slower on 2 cores: the eval program's trace took 4.5 s instead of 1.7.)"""
    lowered, stages.compile_s = {}, 0.0
    for name, (fn, args) in programs.items():
        lowered[name] = fn.lower(*args)
        key = f"{name}_lower_s"
        setattr(stages, key, (getattr(stages, key) or 0.0) + time.perf_counter() - t)
        t = time.perf_counter()
    futures = {name: pool.submit(_compile_one, name, lo, stages) for name, lo in lowered.items()}
    return Pending(futures, stages), t


def _compile_one(name: str, lowered, stages: Stages):
    t0 = time.perf_counter()
    exe = lowered.compile()
    setattr(stages, f"{name}_compile_s", time.perf_counter() - t0)
    return exe


@dataclasses.dataclass(frozen=True)
class Pending:
    """The programs compiling in the background (:func:`_compile`)."""

    futures: dict  # name: the future of its executable
    stages: Stages

    @property
    def names(self) -> tuple:
        return tuple(self.futures)

    def wait(self, name: str, t: float):
        """``(executable, the time now)``, adding the wait to ``stages.compile_s``."""
        exe = self.futures[name].result()
        waited, now = _since(t)
        self.stages.compile_s += waited
        return exe, now

    def when_ready(self, name: str) -> Callable:
        """The executable as a function that waits for its compile when first called (that
        wait is part of the caller's stage: the first evaluation's)."""
        return lambda *args: self.futures[name].result()(*args)


def _since(t: float) -> tuple[float, float]:
    """``(seconds since t, the time now)``."""
    now = time.perf_counter()
    return now - t, now


def _resume(run_dir: str, *, init_fn, keys, hp, place, log):
    """The newest checkpoint that loads (newer ones that do not are deleted, and said so),
    and the metrics log cut back to it.  Refuses a run that logged epochs but holds no
    checkpoint (one that stopped before its first starts over instead)."""
    if not _has_checkpoint(run_dir):  # yet it logged epochs: its checkpoints were removed
        raise FileNotFoundError(
            f"{os.path.join(run_dir, 'checkpoints')} holds no checkpoint, so there is nothing to resume; "
            "start a new run (its metrics.csv is left as it is)"
        )
    start, state, skipped = ckpt.restore_newest(run_dir, init_fn.eval_shape(keys, hp))
    for epoch, reason in skipped:
        log(f"skipped checkpoint {epoch}, which does not load ({reason}); it is deleted")
        m = ckpt.manager(run_dir)
        m.delete(epoch)
        m.close()
    csv_log = rundir.CsvLog(os.path.join(run_dir, "metrics.csv"), keep_through_epoch=start)
    log(f"resumed {run_dir} at epoch {start}/{rundir.load_spec(run_dir).train.epochs}")
    return place(state), start, csv_log


@dataclasses.dataclass(frozen=True)
class EpochLoop:
    """What the epochs of one launch share."""

    spec: sp.RunSpec
    run_dir: str
    mngr: object  # the writer's orbax checkpoint manager
    csv_log: rundir.CsvLog
    epoch_c: object  # compiled epoch program
    eval_c: object  # compiled evaluation program
    live: LiveBar | None  # the in-epoch bar on a terminal
    verbose: bool  # print the progress line
    every: int  # epochs between checkpoints
    stop: status.Stop  # once requested: no further epoch


def _epochs(loop: EpochLoop, ts, start: int, last: int):
    """Epochs ``start + 1 … last``: train, check, evaluate, log, select, checkpoint."""
    spec, run_dir, mngr, csv_log = loop.spec, loop.run_dir, loop.mngr, loop.csv_log
    epoch_c, eval_c, live, every = loop.epoch_c, loop.eval_c, loop.live, loop.every
    tb = report.tensorboard(run_dir)
    report.import_pyplot_in_background()  # for the learning curve at the end, while the epochs run
    run_s, ev, timings = 0.0, None, []
    for epoch in range(start + 1, last + 1):
        if loop.stop.requested():
            if epoch > start + 1 and (epoch - 1) % every != 0:  # the last finished epoch, not yet saved
                ckpt.save(mngr, epoch - 1, ts, wait=False)
            break
        te = time.perf_counter()
        steps_before = float(np.mean(np.asarray(ts.n_tr)))
        if live is not None:
            live.start(epoch)
        try:
            ts, m = epoch_c(ts, spec.hp)
            m = jax.device_get(m)
            t_train = time.perf_counter() - te
            check_finite(m, ts, epoch, run_dir, mngr, spec.train.trains_critics)
            ev = jax.device_get(eval_c(ts))
        finally:
            if live is not None:
                live.stop()
        dt = time.perf_counter() - te
        run_s += dt
        sps = spec.num_seeds * (float(np.mean(m["env_steps"])) - steps_before) / dt
        rows = []
        for i in range(spec.num_seeds):
            row = {"epoch": epoch, "seed": spec.seed + i, "wall_s": dt, "steps_per_s": sps}
            row.update({k: float(np.asarray(v)[i]) for k, v in {**m, **ev}.items()})
            rows.append(row)
        csv_log.write(rows)
        if spec.is_quadrotor:
            rundir.select_best(run_dir, spec, epoch, ev, ts)
        if tb is not None:
            for row in rows:
                for k, v in row.items():
                    if math.isfinite(v):  # e.g. no episode ended: train_return is nan
                        tb.add_scalar(f"seed{row['seed']}/{k}", v, int(row["env_steps"]))
        if epoch % every == 0 or epoch == last:
            ckpt.save(mngr, epoch, ts, wait=False)  # written during the next epoch
        host_s = time.perf_counter() - te - dt  # logs, selection, checkpoint
        timings.append(dict(epoch=epoch, train_s=t_train, eval_s=dt - t_train, host_s=host_s))
        if loop.verbose:
            print(progress_line(epoch, spec.train.epochs, m, ev, sps), flush=True)
    if tb is not None:
        tb.close()
    return ts, ev, run_s, timings


def best_note(spec: sp.RunSpec) -> str:
    """What the run keeps in best/, for its last line."""
    if not spec.is_quadrotor:
        return ""
    if spec.train.selection == "last":
        return ", best/ (each seed's last policy)"
    return ", best/ (the policy selected on the validation tracks)"


def _finish(run_dir: str, spec: sp.RunSpec, ev, *, compile_s: float, run_s: float, stages: Stages) -> dict:
    seed_evals = [{k: float(np.asarray(v)[i]) for k, v in ev.items()} for i in range(spec.num_seeds)]
    seeds = list(range(spec.seed, spec.seed + spec.num_seeds))
    summary = dict(run_dir=run_dir, env=spec.env, algo=spec.algo, seeds=seeds, final_eval=seed_evals,
                   compile_s=compile_s, train_s=run_s, device=jax.devices()[0].device_kind,
                   stages=stages.as_dict())  # fmt: skip
    if spec.is_quadrotor:
        summary["paper_ttd3"] = PAPER_TTD3
        summary["beats_paper"] = [beats_paper(s) for s in seed_evals]
        # the policy chosen on the validation tracks, or the last (best/; evaluate it with --best)
        summary["selected"] = rundir.selected_policies(run_dir)
        summary["selected_beats_paper"] = [beats_paper(s) for s in summary["selected"]]
    with open(os.path.join(run_dir, "eval.json"), "w") as fh:
        json.dump(report.json_safe(summary), fh, indent=2)  # strict JSON: nan and inf become null
    title = f"{spec.algo.upper()} on {spec.env} ({os.path.basename(os.path.abspath(run_dir))})"
    report.plot_learning_curve(run_dir, rundir.read_metrics(run_dir), title)
    return summary
