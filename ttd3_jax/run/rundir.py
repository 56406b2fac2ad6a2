"""A run directory on disk: ``config.json`` (the whole :class:`~ttd3_jax.run.spec.RunSpec`;
everything that reads a run rebuilds it from this alone), ``metrics.csv`` (one row per epoch
and seed), ``checkpoints/`` (orbax, the whole train state), ``best/`` (each seed's policy
selected on the validation tracks), ``eval.json``, ``learning_curve.png`` and
``launches.jsonl`` (the code and machine of each launch: :mod:`ttd3_jax.run.provenance`).
"""

from __future__ import annotations

import csv
import datetime
import itertools
import json
import logging
import os
from typing import Any, NamedTuple

import jax
import numpy as np

from ttd3_jax.checks import writable_dir
from ttd3_jax.control.closed_loop import policy_controller
from ttd3_jax.control.evaluator import Build, index
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import provenance, status
from ttd3_jax.run import spec as sp
from ttd3_jax.run.sharding import per_seed
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.td3 import networks
from ttd3_jax.td3.trainer import Trainer, act, initial_actor, seed_keys

logger = logging.getLogger(__name__)

CONFIG = "config.json"


def check_out_dir(out: str) -> None:
    """Refuse an ``--out`` that is a file or cannot be written, before anything compiles."""
    writable_dir("--out", out)


def new_run_dir(out: str, spec: sp.RunSpec) -> str:
    """A fresh ``out/<env>-<algo>-s<seed>-<time>`` directory, with ``config.json`` in it.  The
    directory is created atomically: a name another process took first gets a suffix."""
    check_out_dir(out)
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    base = os.path.join(out, f"{spec.env}-{spec.algo}-s{spec.seed}-{stamp}")
    for i in itertools.count():
        path = base if i == 0 else f"{base}-{i}"
        try:
            os.makedirs(path)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise ValueError(f"--out {out!r}: cannot create {path!r} ({e.strerror})") from None
    tmp = os.path.join(path, CONFIG + ".tmp")  # whole or not at all: a kill may land mid-write
    with open(tmp, "w") as fh:
        json.dump(sp.to_dict(spec), fh, indent=2)
    os.replace(tmp, os.path.join(path, CONFIG))
    return path


def find_run(path: str) -> tuple[str, str | None]:
    """``(run_dir, note)``: ``path`` itself when it holds a ``config.json``, else the newest
    run directly under it (a training ``--out`` directory) that did not fail, with a note
    naming the choice and the failed runs passed over."""
    if os.path.isfile(os.path.join(path, CONFIG)) or not os.path.isdir(path):
        return path, None
    found = sorted((e for e in os.scandir(path) if os.path.isfile(os.path.join(e.path, CONFIG))),
                   key=lambda e: os.path.getmtime(os.path.join(e.path, CONFIG)))  # fmt: skip
    if not found:
        msg = f"no {CONFIG} in {path!r} or its subdirectories: not a ttd3_jax run directory"
        raise FileNotFoundError(msg)
    states = {e.name: status.state(e.path) for e in found}
    failed = [e for e in found if states[e.name]["state"] == "failed"]
    usable = [e for e in found if e not in failed]
    notes = [f"skipped {e.name} (failed: {states[e.name].get('reason', '?')})" for e in failed]
    if not usable:
        raise FileNotFoundError(f"every run in {path!r} failed: {'; '.join(notes)}")
    if len(found) > 1:
        notes.append(f"{path!r} holds {len(found)} runs; using the newest{' usable' * bool(failed)}, "
                     f"{usable[-1].name}")  # fmt: skip
    return usable[-1].path, "\n".join(notes) or None


# what training writes in a run directory, which the readers (evaluate, export) never write over
OWN_FILES = (CONFIG, "metrics.csv", status.STATE, status.LOCK, "eval.json", "learning_curve.png",
             ckpt.DIGESTS, ckpt.FILES, provenance.FILE)  # fmt: skip
OWN_FOLDERS = ("checkpoints", "best", "tb")


def refuse_run_files(flag: str, path: str, folder: bool = False) -> None:
    """Refuse an output ``path`` (a file, or a ``folder`` to write in) that is one of a run
    directory's own files or lies in its ``checkpoints/``, ``best/`` or ``tb/``, naming the
    flag: a reader never writes into what training wrote."""
    real = os.path.realpath(path)
    head, name = os.path.split(real)
    if not folder and name in OWN_FILES and os.path.isfile(os.path.join(head, CONFIG)):
        raise ValueError(f"{flag} {path!r} is {name} of the run {head}: evaluate and export never write over "
                         "a run's own files; pick another path")  # fmt: skip
    probe = real
    while True:
        parent = os.path.dirname(probe)
        if parent == probe:
            return
        if os.path.basename(probe) in OWN_FOLDERS and os.path.isfile(os.path.join(parent, CONFIG)):
            raise ValueError(f"{flag} {path!r} is inside {os.path.basename(probe)}/ of the run {parent}: "
                             "evaluate and export never write there; pick another path")  # fmt: skip
        probe = parent


def load_spec(run_dir: str) -> sp.RunSpec:
    """A run's spec from its ``config.json``; errors name the file and what is wrong."""
    path = os.path.join(run_dir, CONFIG)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no {CONFIG} in {run_dir!r}: not a ttd3_jax run directory")
    try:
        with open(path) as fh:
            d = json.load(fh)
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}); the file is damaged") from None
    try:
        return sp.from_dict(d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None


class CsvLog:
    """metrics.csv, one row per (epoch, seed); on resume, rows past the checkpoint are dropped."""

    def __init__(self, path: str, keep_through_epoch: int | None = None):
        self.path = path
        self.fields: list[str] | None = None
        if keep_through_epoch is not None and os.path.exists(path):
            with open(path) as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["epoch"]) <= keep_through_epoch]
            if rows:
                self.fields = list(rows[0].keys())
            with open(path, "w", newline="") as fh:
                if self.fields:
                    w = csv.DictWriter(fh, self.fields)
                    w.writeheader()
                    w.writerows(rows)
        elif os.path.exists(path):
            os.remove(path)

    def write(self, rows: list[dict]) -> None:
        new = self.fields is None
        if new:
            self.fields = list(rows[0].keys())
        with open(self.path, "a", newline="") as fh:
            w = csv.DictWriter(fh, self.fields)
            if new:
                w.writeheader()
            w.writerows(rows)


def read_metrics(run_dir: str) -> list[dict]:
    with open(os.path.join(run_dir, "metrics.csv")) as fh:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def improves_selection(record: dict, seed: int, value: float) -> bool:
    """Spec T8's rule: ``value``, a finite validation error, is lower than the one ``record``
    holds for ``seed`` (so the earlier epoch keeps a tie)."""
    return bool(np.isfinite(value)) and (seed not in record or value < record[seed]["val_tracking_error"])


def select_best(run_dir: str, spec: sp.RunSpec, epoch: int, ev, ts) -> None:
    """Keep each seed's policy with the lowest validation error so far (spec T8: selection
    on the 10 validation tracks, never on the test tracks) in ``run_dir/best/``; with
    ``train.selection = "last"``, its newest policy."""
    record, last = ckpt.best_record(run_dir), spec.train.selection == "last"
    for i in range(spec.num_seeds):
        seed, v = spec.seed + i, float(np.asarray(ev["val_tracking_error"])[i])
        if last or improves_selection(record, seed, v):
            actor, stats = jax.device_get((ts.actor, ts.obs_stats))  # sliced on the host: nothing compiles
            stats = index(stats, i) if spec.train.normalize_obs else None
            ckpt.save_policy(run_dir, seed, epoch, v, {"actor": index(actor, i), "obs_stats": stats})


def selected_policies(run_dir: str) -> list[dict]:
    """Per seed: the epoch selected on the validation tracks and that epoch's test figures
    (from metrics.csv).  Empty for runs without ``best/``."""
    record, rows = ckpt.best_record(run_dir), read_metrics(run_dir)
    keys = ("spiral_tracking_error", "los_tracking_error", "spiral_crashed", "los_crashed")
    out = []
    for seed, b in sorted(record.items()):
        row = next(r for r in rows if int(r["epoch"]) == b["epoch"] and int(r["seed"]) == seed)
        out.append(dict(seed=seed, epoch=b["epoch"], val_tracking_error=b["val_tracking_error"],
                        **{k: float(row[k]) for k in keys}))  # fmt: skip
    return out


class LoadedState(NamedTuple):
    spec: sp.RunSpec
    trainer: Trainer
    state: Any  # TrainState with the seed axis in front, on the host
    epoch: int
    skipped: list  # [(epoch, reason)] of newer checkpoints that did not load


def reader_trainer(run_dir: str, spec: sp.RunSpec, epoch: int | None = None) -> Trainer:
    """The run's trainer as a reader builds it (evaluation, export: they restore the run's
    state, never train it): users' training tracks are not read, so a run whose CSV files
    have moved still loads, and the training envs' track tables take the size its checkpoint
    ``epoch`` (default: the newest) holds, so that the state restores (none readable: the
    mixture's size, and the restore says what does not load)."""
    if not (spec.is_quadrotor and spec.task.tracks.train_tracks):
        return sp.trainer_for(spec)
    return sp.trainer_for(spec, track_rows=ckpt.saved_track_rows(run_dir, epoch) or 0)


def load_train_state(run_dir: str, epoch: int | None = None) -> LoadedState:
    """A run's checkpoint ``epoch`` (default: the newest that loads)."""
    spec = load_spec(run_dir)
    trainer = reader_trainer(run_dir, spec, epoch)
    keys = seed_keys(spec.seed, spec.num_seeds)
    like = jax.eval_shape(per_seed(trainer.init, spec.num_seeds, (0, None)), keys, spec.hp)
    epoch, state, skipped = ckpt.restore_newest(run_dir, like, epoch)
    return LoadedState(spec, trainer, state, epoch, skipped)


def selected_policy(run_dir: str, seed: int, index_: int, like, epoch: int):
    """Seed ``seed``'s policy from ``best/``; a damaged file (digest mismatch, or it does not
    load) is rebuilt in memory from checkpoint ``epoch`` when that one is still kept, and
    said so on stderr; otherwise refused, with what to do."""
    try:
        return ckpt.load_policy(run_dir, seed, like)
    except ValueError as e:
        damaged = str(e)
    try:
        st = load_train_state(run_dir, epoch).state
    except FileNotFoundError:
        why = f"its epoch {epoch} checkpoint is no longer kept, so it cannot be rebuilt"
        raise ValueError(f"{damaged}; {why}: use the newest checkpoint (leave out --best)") from None
    stats = index(st.obs_stats, index_) if like["obs_stats"] is not None else None
    logger.warning(f"note: {damaged}; rebuilt from checkpoint {epoch}, the epoch it was selected at")
    return {"actor": index(st.actor, index_), "obs_stats": stats}


class LoadedRun(NamedTuple):
    spec: sp.RunSpec
    env_config: EnvConfig  # the run's (training) env config
    epoch: int | dict  # the checkpoint's epoch, or {seed: epoch} of the selected policies
    build: Build  # theta = (actor params, obs stats or None) -> policy Controller
    thetas: list  # [(seed, theta)] for every seed of the run
    skipped: list  # [(epoch, reason)] of newer checkpoints that did not load


def load_run(run_dir: str, epoch: int | None = None, best: bool = False) -> LoadedRun:
    """A quadrotor run's checkpoint ``epoch`` (default: the newest that loads) as policy
    controllers, one per seed, with the env config the run trained on (the policy must see
    the observation layout it was trained with).  ``best``: instead, each seed's policy
    selected on the validation tracks during training (``run_dir/best/``)."""
    spec = load_spec(run_dir)
    if not spec.is_quadrotor:
        raise ValueError(f"{run_dir!r} is a {spec.env!r} run; only quadrotor runs can be evaluated here")
    setup = reader_trainer(run_dir, spec, epoch).setup

    def build(theta):
        actor, stats = theta
        return policy_controller(lambda obs: act(setup, actor, stats, obs))

    seeds = range(spec.seed, spec.seed + spec.num_seeds)
    if best:
        record = ckpt.best_record(run_dir)
        missing = [s for s in seeds if s not in record]
        if missing:
            raise FileNotFoundError(
                f"no selected policy for seed(s) {missing} in {run_dir!r} (best/best.json)"
            )
        stats = networks.init_obs_stats(setup.env.obs_size) if spec.train.normalize_obs else None
        like = {"actor": initial_actor(setup, jax.random.PRNGKey(0)), "obs_stats": stats}
        policies = [selected_policy(run_dir, s, i, like, record[s]["epoch"]) for i, s in enumerate(seeds)]
        thetas = [(s, (p["actor"], p["obs_stats"])) for s, p in zip(seeds, policies, strict=True)]
        return LoadedRun(spec, spec.task, {s: record[s]["epoch"] for s in seeds}, build, thetas, [])
    loaded = load_train_state(run_dir, epoch)
    st = loaded.state
    thetas = [(s, (index(st.actor, i), index(st.obs_stats, i) if spec.train.normalize_obs else None))
              for i, s in enumerate(seeds)]  # fmt: skip
    return LoadedRun(spec, spec.task, loaded.epoch, build, thetas, loaded.skipped)
