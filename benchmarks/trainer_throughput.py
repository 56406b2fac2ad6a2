"""Trainer throughput: transitions/s and gradient updates/s of one compiled epoch.

All cases are compiled first (compile time reported apart), then timed interleaved,
best of ``--repeats``, so machine noise hits every case alike.  Ratios are against the
first case of each group, measured in the same process.

    python benchmarks/trainer_throughput.py            # the study in docs/performance.md
    python benchmarks/trainer_throughput.py --quick    # smoke run (CI)

Cases (quadrotor, ``fast_dpg`` preset, the TD3 actor update through the critic, unless stated):
  fast            that preset: 64 envs x 16 updates per vector step, 64-64 networks
  fast_vmap1      the same, run through ``vmap`` over a seed axis of size 1 (what the
                  runner did before single-seed runs skipped vmap: lax.cond becomes select)
  envs16_utd16    16 envs x 16 updates: one update per transition
  envs256_utd16   256 envs x 16 updates: collection-heavy
  net256          256-256 networks (the paper's width)
  batch1024       minibatches of 1024 instead of 256 (4x the samples per update)
  seeds4          4 seeds vmapped in one program (per-seed figures are the total / 4)
  model_h50       the ``fast`` preset: per vector step a 50-step differentiable rollout of
                  the 64 envs (the actor update), then 16 critic updates
  model_h50_utd1  model_h50 with 1 critic update per vector step instead of 16

``--large`` (for a GPU) replaces the CPU study with thousands of envs:
  fast                    the ``fast_dpg`` preset as above (the reference)
  envs1024_b1024          1024 envs x 16 updates, batch 1024
  envs4096_b4096          4096 envs x 16 updates, batch 4096
  envs4096_b4096_net256   the same with 256-256 networks
  seeds16                 16 seeds of the preset vmapped in one program
"""

from __future__ import annotations

import argparse
import os
import time

import _peers
import jax

from ttd3_jax import spec as sp
from ttd3_jax.td3.trainer import seed_keys


def large_cases() -> dict:
    base = dict(epochs=1, warmup_transitions=8_192, buffer_size=1_048_576)

    def cfg(num_envs=64, vsteps=500, **kw):
        total = base["warmup_transitions"] + num_envs * vsteps
        return sp.preset("fast_dpg", **{**base, "num_envs": num_envs, "total_transitions": total, **kw})

    return {
        "fast": (cfg(), False),
        "envs1024_b1024": (cfg(num_envs=1024, batch_size=1024, vsteps=200), False),
        "envs4096_b4096": (cfg(num_envs=4096, batch_size=4096, vsteps=100), False),
        "envs4096_b4096_net256": (cfg(num_envs=4096, batch_size=4096, vsteps=100, hidden=(256, 256)), False),
        "seeds16": (cfg(num_seeds=16, buffer_size=262_144), True),
    }


def cases(quick: bool) -> dict:
    steps = 2_000 if quick else 40_000  # transitions per timed epoch, per seed
    base = dict(epochs=1, warmup_transitions=4_096, buffer_size=100_000)
    if quick:
        base.update(hidden=(32, 32), warmup_transitions=512, buffer_size=8_192)

    def cfg(num_envs=64, **kw):
        total = kw.pop("total", steps) + base["warmup_transitions"]
        return sp.preset("fast_dpg", **{**base, "num_envs": num_envs, "total_transitions": total, **kw})

    model_steps = 4 if quick else 40  # vector steps (actor updates) of the model-based case
    model_total = base["warmup_transitions"] + 64 * 50 * model_steps
    model = sp.preset("fast", **{**base, "total_transitions": model_total})
    out = {
        "fast": (cfg(), False),
        "fast_vmap1": (cfg(), True),
        "envs16_utd16": (cfg(num_envs=16, total=steps // 4), False),
        "envs256_utd16": (cfg(num_envs=256, total=steps * 4), False),
        "net256": (cfg(hidden=(256, 256), total=steps // 4), False),
        "seeds4": (cfg(num_seeds=4, total=steps // 2), True),
        # the fast preset itself: a 50-step differentiable rollout (the actor update) per vector step
        "model_h50": (model, False),
        # the same with one critic update per vector step instead of 16 (the model-based actor
        # does not use the critics; T-TD3's sigma is still updated per critic update)
        "model_h50_utd1": (sp.replace(model, updates_per_step=1), False),
    }
    if quick:
        return {k: out[k] for k in ("fast", "fast_vmap1", "model_h50")}
    out["batch1024"] = (cfg(batch_size=1024, total=steps // 2), False)  # needs warm-up >= 1024
    return out


def build(s: sp.RunSpec, vmapped: bool):
    t = sp.trainer_for(s)
    keys = seed_keys(s.seed, s.num_seeds)
    if vmapped:
        init = jax.jit(jax.vmap(t.init, in_axes=(0, None)))
        epoch = jax.vmap(t.epoch, in_axes=(0, None))
        ts = init(keys, s.hp)
    else:
        ts = jax.jit(t.init)(keys[0], s.hp)
        epoch = t.epoch
    jax.block_until_ready(ts)
    t0 = time.perf_counter()
    compiled = jax.jit(epoch).lower(ts, s.hp).compile()
    return compiled, ts, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    ap.add_argument("--large", action="store_true", help="thousands of envs (a GPU study)")
    ap.add_argument("--only", nargs="+", default=None, help="run these cases (and fast, the reference)")
    ap.add_argument("--out", default="benchmarks/results/trainer_throughput.jsonl")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.quick:
        args.repeats = 1

    built = {}
    chosen = large_cases() if args.large else cases(args.quick)
    if args.only:
        bad = sorted(set(args.only) - set(chosen))
        if bad:
            ap.error(f"unknown case(s) {bad}; allowed: {sorted(chosen)}")
        chosen = {k: v for k, v in chosen.items() if k in args.only or k == "fast"}  # fast: the reference
    for name, (s, vmapped) in chosen.items():
        built[name] = (s, *build(s, vmapped))
    best = {name: float("inf") for name in built}
    for _ in range(args.repeats):
        for name, (s, fn, ts, _) in built.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(ts, s.hp))
            best[name] = min(best[name], time.perf_counter() - t0)

    dev = jax.devices()[0]
    print(f"device={dev.platform} ({dev.device_kind}) cpus={os.cpu_count()} jax={jax.__version__}")
    print(
        f"{'case':<22} {'envs':>5} {'UTD':>4} {'hidden':>8} {'seeds':>5} {'compile s':>9} {'run s':>7} "
        f"{'trans/s':>9} {'upd/s':>8} {'x fast':>6} {'samples/s':>9}"
    )
    fc = built["fast"][0].train
    fast_upd = fc.steps_per_epoch * fc.updates_per_step / best["fast"]
    rows = []
    for name, (s, _, _, comp) in built.items():
        c = s.train
        trans = s.num_seeds * c.steps_per_epoch * c.num_envs * c.env_steps_per_step
        upd = s.num_seeds * c.steps_per_epoch * c.updates_per_step
        row = dict(
            case=name,
            num_envs=c.num_envs,
            updates_per_step=c.updates_per_step,
            hidden=list(c.hidden),
            num_seeds=s.num_seeds,
            compile_s=comp,
            run_s=best[name],
            transitions_per_s=trans / best[name],
            updates_per_s=upd / best[name],
            batch_size=c.batch_size,
            samples_per_s=upd * c.batch_size / best[name],  # minibatch rows through the critic update
        )
        row["updates_per_s_vs_fast"] = row["updates_per_s"] / fast_upd
        rows.append(row)
        print(
            f"{name:<22} {c.num_envs:>5} {c.updates_per_step:>4} {'-'.join(map(str, c.hidden)):>8} "
            f"{s.num_seeds:>5} {comp:>9.1f} {best[name]:>7.2f} {row['transitions_per_s']:>9.3g} "
            f"{row['updates_per_s']:>8.3g} {row['updates_per_s_vs_fast']:>6.2f} {row['samples_per_s']:>9.3g}"
        )
    record = _peers.machine_record(argv)
    record.update(
        quick=args.quick,
        large=args.large,
        rows=rows,
    )
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
