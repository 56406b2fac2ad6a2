"""The Python loop around the compiled epochs: progress, evaluation, logs, checkpoints, resume.

A run directory holds ``config.json`` (the resolved config), ``metrics.csv`` (one row
per epoch and seed), ``checkpoints/`` (orbax, the whole train state), ``eval.json``
(final evaluation) and ``learning_curve.png``; plus ``tb/`` when tensorboardX is
installed.  Each epoch is one compiled call; nothing recompiles between epochs.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax import checkpoint as ckpt
from ttd3_jax import noise as nz
from ttd3_jax import train as train_lib
from ttd3_jax.sharding import runner_fns
from ttd3_jax.train import (
    QUADROTOR,
    Hyper,
    TrainConfig,
    buffer_bytes,
    make_trainer,
    seed_keys,
)

PAPER_TTD3 = {"spiral_tracking_error": 25.99, "los_tracking_error": 398.74}


class TrainingDiverged(RuntimeError):
    """Raised when losses or parameters stop being finite."""


# --------------------------------------------------------------------------- config I/O


def config_to_dict(c: TrainConfig) -> dict:
    return dataclasses.asdict(c)


def config_from_dict(d: dict) -> TrainConfig:
    d = dict(d)
    d["noise"] = nz.NoiseConfig(**d["noise"])
    d["hp"] = Hyper(**d["hp"])
    d["hidden"] = tuple(d["hidden"])
    d["env_overrides"] = tuple(d.get("env_overrides", ()))  # runs from before the field: none
    return TrainConfig(**d)


def env_config_dict(c: TrainConfig) -> dict | None:
    """The quadrotor env config a run trains and evaluates with, as plain JSON values."""
    if c.env != QUADROTOR:
        return None
    # looked up at call time, so experiments that swap the env builder are recorded truly
    return json.loads(json.dumps(dataclasses.asdict(train_lib.quad_env_config(c))))


def load_config(run_dir: str) -> TrainConfig:
    """A run's config.  Raises ``ValueError`` if the env config the code builds for it
    today differs from the one it was trained with (``env_config.json``), e.g. after a
    preset changed: its policy would then see a different observation or reward."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no config.json in {run_dir!r}: not a ttd3_jax run directory")
    with open(path) as fh:
        c = config_from_dict(json.load(fh))
    env_path = os.path.join(run_dir, "env_config.json")
    if os.path.isfile(env_path):
        with open(env_path) as fh:
            saved = json.load(fh)
        now = env_config_dict(c)
        diff = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
        if diff:
            raise ValueError(
                f"run {run_dir!r} was trained with a different env config than preset "
                f"{c.env_preset!r} builds today (fields {diff}: saved "
                f"{ {k: saved.get(k) for k in diff} }, now { {k: now.get(k) for k in diff} }); "
                "use the code version that trained it"
            )
    return c


# --------------------------------------------------------------------------- compile cache

COMPILE_CACHE_OFF = "none"


def default_compile_cache() -> str:
    """``$JAX_COMPILATION_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/ttd3_jax/xla``
    (``~/.cache/ttd3_jax/xla``)."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "ttd3_jax", "xla")


def use_compile_cache(path: str | None = None) -> str | None:
    """Turn on jax's persistent compilation cache in directory ``path`` for this process
    (``None``: :func:`default_compile_cache`; ``"none"``: turn it off).  Returns the
    directory in use, or ``None`` when off.  An explicit ``path`` that cannot be created is
    a ``ValueError``; the default one only gives a warning (the run goes on without a cache).

    A later launch of the same programs (same configuration and shapes, another seed
    included) then loads the compiled XLA executables instead of compiling them again:
    about 25 s of the ``fast`` preset's start-up on 2 CPU cores.  A cached executable is
    the one that was compiled, so results do not change.  Call it before anything is
    compiled; the CLI does (``--compile-cache``)."""
    chosen = path is not None
    if path is None:
        path = default_compile_cache()
    if path.strip().lower() == COMPILE_CACHE_OFF:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    path = os.path.abspath(os.path.expanduser(path))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        if not chosen:  # the default place is not writable here: run without a cache
            _stderr(f"warning: no XLA compilation cache ({path!r}: {e.strerror}); pass --compile-cache DIR")
            jax.config.update("jax_enable_compilation_cache", False)
            return None
        raise ValueError(
            f"compile cache directory {path!r} cannot be created ({e.strerror}); "
            f"pass --compile-cache DIR with a writable DIR, or --compile-cache {COMPILE_CACHE_OFF}"
        ) from e
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", path)
    return path


def per_seed(fn, c: TrainConfig, in_axes: tuple):
    """``fn`` mapped over the leading seed axis of the arguments marked 0 in ``in_axes``.

    A single seed skips ``vmap`` (keeping the axis of length 1), so the trainer's
    ``lax.cond`` branches stay branches instead of becoming selects that run both sides.
    """
    if c.num_seeds > 1:
        return jax.vmap(fn, in_axes=in_axes)

    def one(*args):
        args = [
            jax.tree.map(lambda x: x[0], a) if ax == 0 else a for a, ax in zip(args, in_axes, strict=True)
        ]
        return jax.tree.map(lambda x: x[None], fn(*args))

    return one


def load_train_state(run_dir: str, epoch: int | None = None):
    """``(config, trainer, state)`` of a run directory's checkpoint ``epoch`` (default: the
    latest).  ``state`` has the seed axis in front, as the runner saved it."""
    c = load_config(run_dir)
    trainer = make_trainer(c)
    mngr = ckpt.manager(run_dir)
    epoch = ckpt.latest_epoch(mngr) if epoch is None else epoch
    if epoch is None or epoch not in mngr.all_steps():
        saved = sorted(mngr.all_steps())
        raise FileNotFoundError(
            f"no checkpoint {'' if epoch is None else epoch} in {run_dir!r}; saved: {saved}"
        )
    like = jax.eval_shape(per_seed(trainer.init, c, (0, None)), seed_keys(c), c.hp)
    return c, trainer, jax.device_put(ckpt.restore(mngr, epoch, like))


# --------------------------------------------------------------------------- memory


def available_memory_bytes() -> int | None:
    """Free memory of the default device (GPU) or of the host (CPU), if known."""
    dev = jax.devices()[0]
    if dev.platform != "cpu":
        stats = dev.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(c: TrainConfig, obs_size: int, action_size: int) -> int:
    """Replay-buffer bytes for the run; refuses budgets over 70 % of free memory."""
    need = buffer_bytes(c, obs_size, action_size)
    free = available_memory_bytes()
    if free is not None and need > 0.7 * free:
        raise ValueError(
            f"the replay buffers need {need / 2**30:.2f} GiB (buffer_size={c.buffer_size} x "
            f"num_seeds={c.num_seeds} x {obs_size}-D observations) but only {free / 2**30:.2f} GiB is "
            "free; lower buffer_size or num_seeds"
        )
    return need


# --------------------------------------------------------------------------- logging


def _row_values(tree, seed_index: int) -> dict:
    return {k: float(np.asarray(v)[seed_index]) for k, v in tree.items()}


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


def plot_learning_curve(run_dir: str, c: TrainConfig) -> str | None:
    """learning_curve.png from metrics.csv (None when matplotlib is missing)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    rows = read_metrics(run_dir)
    seeds = sorted({int(r["seed"]) for r in rows})
    keys = ["spiral_tracking_error", "los_tracking_error"] if c.env == QUADROTOR else ["eval_return"]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 4), squeeze=False)
    for ax, key in zip(axes[0], keys, strict=True):
        for s in seeds:
            rs = [r for r in rows if int(r["seed"]) == s]
            ax.plot([r["env_steps"] for r in rs], [r[key] for r in rs], marker="o", ms=3, label=f"seed {s}")
        if key in PAPER_TTD3:
            ax.axhline(PAPER_TTD3[key], color="k", ls="--", lw=1, label="paper T-TD3")
            ax.set_yscale("log")
        ax.set_xlabel("env transitions")
        ax.set_ylabel(key.replace("_", " ") + (" [m]" if "error" in key else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{c.algo.upper()} on {c.env} ({os.path.basename(os.path.abspath(run_dir))})")
    fig.tight_layout()
    path = os.path.join(run_dir, "learning_curve.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


class _LiveBar:
    """In-epoch progress on a terminal: vector steps done and steps/s, redrawn in place."""

    def __init__(self, c: TrainConfig):
        self.c, self.epoch, self.t0 = c, 0, time.perf_counter()

    def start(self, epoch: int) -> None:
        self.epoch, self.t0 = epoch, time.perf_counter()

    def __call__(self, done) -> None:
        c = self.c
        done = int(np.max(np.asarray(done)))
        frac = done / c.steps_per_epoch
        steps = c.num_seeds * c.num_envs * c.env_steps_per_step * done
        sps = steps / max(time.perf_counter() - self.t0, 1e-9)
        bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
        sys.stdout.write(f"\r  epoch {self.epoch}/{c.epochs} [{bar}] {100 * frac:5.1f}%  {sps:8.3g} steps/s ")
        sys.stdout.flush()

    def clear(self) -> None:
        sys.stdout.write("\r" + " " * 72 + "\r")


def _progress_line(epoch, epochs, m, ev, sps, c: TrainConfig) -> str:
    width = 20
    done = int(width * epoch / epochs)
    bar = "#" * done + "." * (width - done)
    steps = float(np.mean(m["env_steps"]))
    sigma = float(np.mean(m["sigma"]))
    if c.env == QUADROTOR:
        sp, los, val = (float(np.median(ev[k])) for k in ("spiral_tracking_error", "los_tracking_error",
                                                           "val_tracking_error"))  # fmt: skip
        tail = f"Spiral-RT {sp:8.2f}  LOS-RT {los:8.2f}  val {val:8.2f}"
    else:
        tail = f"eval return {float(np.mean(ev['eval_return'])):9.2f}"
    return f"[{bar}] epoch {epoch:>3}/{epochs}  steps {steps:9.3g}  {sps:8.3g}/s  σ {sigma:.3g}  {tail}"


# --------------------------------------------------------------------------- run


def new_run_dir(out: str, c: TrainConfig) -> str:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    base = os.path.join(out, f"{c.env}-{c.algo}-s{c.seed}-{stamp}")
    path, i = base, 1
    while os.path.exists(path):
        path, i = f"{base}-{i}", i + 1
    os.makedirs(path)
    return path


def run(
    c: TrainConfig | None = None,
    out: str = "runs",
    resume: str | None = None,
    verbose: bool = True,
    stop_after: int | None = None,
    checkpoint_every: int = 1,
) -> dict:
    """Train with config ``c`` into a new run directory under ``out``, or continue the run
    in ``resume``.  ``stop_after`` ends this call after that many epochs, as an
    interruption would (resume continues).  A checkpoint is written every
    ``checkpoint_every`` epochs and after the last one (a kill loses at most the epochs
    since; large replay buffers make each save cost seconds).  Returns a summary dict
    (run_dir, final eval, timings)."""
    if not (isinstance(checkpoint_every, int) and checkpoint_every >= 1):
        raise ValueError(f"checkpoint_every must be an integer >= 1, got {checkpoint_every!r}")
    log = print if verbose else (lambda *a, **k: None)
    if resume is not None:
        c = load_config(resume)
        run_dir = resume
    elif c is None:
        raise ValueError("run() needs a TrainConfig or a run directory to resume")
    live = _LiveBar(c) if verbose and sys.stdout.isatty() else None
    trainer = make_trainer(c, on_progress=live)
    check_memory(c, trainer.spec.obs_size, trainer.spec.action_size)
    if resume is None:
        run_dir = new_run_dir(out, c)
        with open(os.path.join(run_dir, "config.json"), "w") as fh:
            json.dump(config_to_dict(c), fh, indent=2)
        if c.env == QUADROTOR:
            with open(os.path.join(run_dir, "env_config.json"), "w") as fh:
                json.dump(env_config_dict(c), fh, indent=2)
    mngr = ckpt.manager(run_dir)
    keys, hp = seed_keys(c), c.hp
    # plain jit on one device; seeds (and envs) split over all visible devices otherwise
    init_fn, epoch_fn, eval_fn, place = runner_fns(trainer, c, per_seed)

    t0 = time.perf_counter()
    start = ckpt.latest_epoch(mngr) if resume is not None else None
    if start is None:
        ts = init_fn(keys, hp)  # warm-up collection included
        start = 0
        jax.block_until_ready(ts)
        ckpt.save(mngr, 0, ts)
        csv_log = CsvLog(os.path.join(run_dir, "metrics.csv"))
        log(f"run dir {run_dir}")
        n_warm = c.warmup_steps * c.num_envs
        log(f"init + warm-up ({n_warm} random transitions/seed): {time.perf_counter() - t0:.1f} s")
    else:
        like = jax.eval_shape(init_fn, keys, hp)
        ts = place(ckpt.restore(mngr, start, like))
        csv_log = CsvLog(os.path.join(run_dir, "metrics.csv"), keep_through_epoch=start)
        log(f"resumed {run_dir} at epoch {start}/{c.epochs}")

    t1 = time.perf_counter()
    epoch_c = epoch_fn.lower(ts, hp).compile()
    eval_c = eval_fn.lower(jax.eval_shape(lambda t: t, ts)).compile()
    compile_s = time.perf_counter() - t1
    log(f"compiled epoch + eval in {compile_s:.1f} s; {c.num_seeds} seed(s) x {c.num_envs} envs, "
        f"{c.steps_per_epoch} vector steps x {c.updates_per_step} updates per epoch")  # fmt: skip
    tb = _tensorboard(run_dir)
    run_s = 0.0
    ev = None
    last = c.epochs if stop_after is None else min(c.epochs, start + stop_after)
    for epoch in range(start + 1, last + 1):
        te = time.perf_counter()
        if live is not None:
            live.start(epoch)
        steps_before = float(np.mean(np.asarray(ts.n_tr)))
        ts, m = epoch_c(ts, hp)
        m = jax.device_get(m)
        _check_finite(m, ts, epoch, c, run_dir, mngr)
        ev = jax.device_get(eval_c(ts))
        dt = time.perf_counter() - te
        run_s += dt
        sps = c.num_seeds * (float(np.mean(m["env_steps"])) - steps_before) / dt
        rows = []
        for i in range(c.num_seeds):
            row = {"epoch": epoch, "seed": c.seed + i, "wall_s": dt, "steps_per_s": sps}
            row.update(_row_values(m, i))
            row.update(_row_values(ev, i))
            rows.append(row)
        csv_log.write(rows)
        if c.env == QUADROTOR:
            _select(run_dir, c, epoch, ev, ts)
        if tb is not None:
            for k, v in rows[0].items():
                tb.add_scalar(k, v, int(rows[0]["env_steps"]))
        if epoch % checkpoint_every == 0 or epoch == last:
            ckpt.save(mngr, epoch, ts)
        if live is not None:
            live.clear()
        log(_progress_line(epoch, c.epochs, m, ev, sps, c), flush=True)
    if last < c.epochs:
        log(f"stopped after epoch {last}/{c.epochs}; continue with --resume {run_dir}")
        return {"run_dir": run_dir, "stopped_at": last}
    if ev is None:
        ev = jax.device_get(eval_c(ts))
    summary = _finish(run_dir, c, ev, compile_s, run_s)
    extra = ", best/ (the policy selected on the validation tracks)" if c.env == QUADROTOR else ""
    log(f"results in {run_dir}: metrics.csv, eval.json, learning_curve.png, checkpoints/{extra}")
    return summary


def _tensorboard(run_dir: str):
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(os.path.join(run_dir, "tb"))


def _check_finite(m, ts, epoch: int, c: TrainConfig, run_dir: str, mngr) -> None:
    bad = [k for k in ("critic_loss", "q_mean") if not np.all(np.isfinite(np.asarray(m[k])))]
    params_ok = all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves((ts.actor, ts.critic)))
    if bad or not params_ok:
        what = ", ".join(bad + ([] if params_ok else ["network parameters"]))
        last = ckpt.latest_epoch(mngr)
        steps = int(np.max(np.asarray(m["env_steps"])))
        raise TrainingDiverged(
            f"non-finite {what} in epoch {epoch} (up to env step {steps}); stopped. The last good "
            f"checkpoint is epoch {last} in {os.path.join(run_dir, 'checkpoints')}. Try a lower learning "
            "rate (--hp.lr-critic) or check the reward scale."
        )


def _select(run_dir: str, c: TrainConfig, epoch: int, ev, ts) -> None:
    """Keep each seed's policy with the lowest validation error so far (spec T8: selection
    on the 10 validation tracks, never on the test tracks) in ``run_dir/best/``."""
    record = ckpt.best_record(run_dir)
    for i in range(c.num_seeds):
        seed, v = c.seed + i, float(np.asarray(ev["val_tracking_error"])[i])
        if np.isfinite(v) and (seed not in record or v < record[seed]["val_tracking_error"]):
            stats = jax.tree.map(lambda x, i=i: x[i], ts.obs_stats) if c.normalize_obs else None
            ckpt.save_policy(run_dir, seed, epoch, v, {"actor": jax.tree.map(lambda x, i=i: x[i], ts.actor),
                                                       "obs_stats": stats})  # fmt: skip


def selected_policies(run_dir: str) -> list[dict]:
    """Per seed: the epoch selected on the validation tracks and that epoch's test figures
    (from metrics.csv).  Empty for runs without ``best/``."""
    record, rows = ckpt.best_record(run_dir), read_metrics(run_dir)
    out = []
    for seed, b in sorted(record.items()):
        row = next(r for r in rows if int(r["epoch"]) == b["epoch"] and int(float(r["seed"])) == seed)
        out.append(
            dict(
                seed=seed,
                epoch=b["epoch"],
                val_tracking_error=b["val_tracking_error"],
                **{
                    k: float(row[k])
                    for k in ("spiral_tracking_error", "los_tracking_error", "spiral_crashed", "los_crashed")
                },  # fmt: skip
            )
        )
    return out


def _finish(run_dir: str, c: TrainConfig, ev, compile_s: float, run_s: float) -> dict:
    seed_evals = [{k: float(np.asarray(v)[i]) for k, v in ev.items()} for i in range(c.num_seeds)]
    summary = {
        "run_dir": run_dir,
        "env": c.env,
        "algo": c.algo,
        "seeds": list(range(c.seed, c.seed + c.num_seeds)),
        "final_eval": seed_evals,
        "compile_s": compile_s,
        "train_s": run_s,
        "device": jax.devices()[0].device_kind,
    }
    if c.env == QUADROTOR:

        def beats(s):
            return bool(s["spiral_tracking_error"] <= PAPER_TTD3["spiral_tracking_error"] and
                        s["los_tracking_error"] <= PAPER_TTD3["los_tracking_error"] and
                        s["spiral_crashed"] == 0 and s["los_crashed"] == 0)  # fmt: skip

        summary["paper_ttd3"] = PAPER_TTD3
        summary["beats_paper"] = [beats(s) for s in seed_evals]
        # the policy chosen on the validation tracks (best/; evaluate it with --best)
        summary["selected"] = selected_policies(run_dir)
        summary["selected_beats_paper"] = [beats(s) for s in summary["selected"]]
    with open(os.path.join(run_dir, "eval.json"), "w") as fh:
        json.dump(
            summary, fh, indent=2, default=lambda x: None if isinstance(x, float) and math.isnan(x) else x
        )
    plot_learning_curve(run_dir, c)
    return summary


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr)
