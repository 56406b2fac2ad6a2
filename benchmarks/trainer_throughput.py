"""Trainer throughput: transitions/s and gradient updates/s of one compiled epoch.

All cases are compiled first (compile time reported apart), then timed interleaved,
best of ``--repeats``, so machine noise hits every case alike.  Ratios are against the
first case of each group, measured in the same process.

    python benchmarks/trainer_throughput.py            # the study in docs/performance.md
    python benchmarks/trainer_throughput.py --only paper --baseline 34cab62 --repeats 5
    python benchmarks/trainer_throughput.py --quick    # smoke run (CI)

``--baseline COMMIT`` also builds every case from the package as it was at COMMIT (``git
archive`` into a temporary directory, served by a worker process of this script, as the peer
benchmarks' workers are, see ``_peers.py``) and times it interleaved with today's: the
``x base`` column is today's transitions/s over COMMIT's.  ``peak`` is a 2048^3 float32
matmul timed in the same run, ``layers`` the matmuls of a 256-256 hidden layer at the
``paper`` case's shapes (:func:`build_layers`): ``GFLOP/s``, ``% peak`` and ``% layers``
count the arithmetic of a TD3 update (:func:`update_flops`) at each case's updates/s.

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
                  the 16 envs (the actor update), no critic
  model_h50_envs64  model_h50 with 64 envs per rollout (the preset until c0d0d59)
  model_h50_utd1  model_h50 with 1 critic update per vector step
  paper           the ``paper`` preset's epoch: 20 envs x 20 updates of batch 256 per vector
                  step, 256-256 networks, 3 seeds vmapped, 1e6-row buffers (totals of 3 seeds)

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
import subprocess
import sys
import tempfile
import time

import _peers
import jax
import jax.numpy as jnp

from ttd3_jax.run import spec as sp
from ttd3_jax.td3.trainer import seed_keys

PEAK_N = 2048  # the peak matmul: (N, N) @ (N, N) float32


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


def paper_case(quick: bool) -> sp.RunSpec:
    """The ``paper`` preset's epoch, 3 seeds: 1000 transitions (50 vector steps) per seed."""
    warm, steps = (512, 200) if quick else (4_096, 1_000)
    kw = dict(hidden=(32, 32), buffer_size=8_192) if quick else {}
    return sp.preset(
        "paper", num_seeds=3, epochs=1, warmup_transitions=warm, total_transitions=warm + steps, **kw
    )


def cases(quick: bool) -> dict:
    steps = 2_000 if quick else 40_000  # transitions per timed epoch, per seed
    base = dict(epochs=1, warmup_transitions=4_096, buffer_size=100_000)
    if quick:
        base.update(hidden=(32, 32), warmup_transitions=512, buffer_size=8_192)

    def cfg(num_envs=64, **kw):
        total = kw.pop("total", steps) + base["warmup_transitions"]
        return sp.preset("fast_dpg", **{**base, "num_envs": num_envs, "total_transitions": total, **kw})

    model_steps = 4 if quick else 40  # vector steps (actor updates) of the model-based cases

    def model_cfg(num_envs=16, **kw):  # the fast preset (16 envs, no critic) at another env count
        total = base["warmup_transitions"] + num_envs * 50 * model_steps
        return sp.preset("fast", **{**base, "num_envs": num_envs, "total_transitions": total, **kw})

    model = model_cfg()
    out = {
        "fast": (cfg(), False),
        "fast_vmap1": (cfg(), True),
        "envs16_utd16": (cfg(num_envs=16, total=steps // 4), False),
        "envs256_utd16": (cfg(num_envs=256, total=steps * 4), False),
        "net256": (cfg(hidden=(256, 256), total=steps // 4), False),
        "seeds4": (cfg(num_seeds=4, total=steps // 2), True),
        # the fast preset itself: a 50-step differentiable rollout (the actor update) per vector step
        "model_h50": (model, False),
        "model_h50_envs64": (model_cfg(64), False),  # c0d0d59's fast: 64 envs per rollout
        # the same with one critic update per vector step (the model-based actor does not use
        # the critics; T-TD3's sigma is then updated per critic update)
        "model_h50_utd1": (sp.replace(model, updates_per_step=1), False),
        "paper": (paper_case(quick), True),
    }
    if quick:
        return {k: out[k] for k in ("fast", "fast_vmap1", "model_h50", "paper")}
    out["batch1024"] = (cfg(batch_size=1024, total=steps // 2), False)  # needs warm-up >= 1024
    return out


def update_flops(s: sp.RunSpec) -> float | None:
    """Multiply-adds x 2 of one TD3 update of ``s`` (per seed): the critic step (target actor,
    both target critics and both critics forward, both critics' backward for their
    weights) plus, every ``policy_delay`` updates, the actor step (actor and critic 1 forward,
    critic 1 backward to its action input, actor backward).  ``None`` where it does not apply
    (the model-based actor update, the residual critic)."""
    c = s.train
    if c.model_horizon > 0 or c.critic_arch != "mlp":
        return None
    env = sp.env_spec(s)
    critic = [env.obs_size + env.action_size, *c.hidden, 1]
    actor = [env.actor_obs_size, *c.hidden, env.action_size]

    def fwd(sizes):  # one forward pass of the batch
        return sum(2 * c.batch_size * a * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))

    def bwd_weights(sizes):  # weight gradients, and input gradients of every layer but the first
        return fwd(sizes) + fwd(sizes[1:])

    critic_step = fwd(actor) + 4 * fwd(critic) + 2 * bwd_weights(critic)
    actor_step = fwd(actor) + 2 * fwd(critic) + bwd_weights(actor)
    return float(critic_step + actor_step / c.policy_delay)


def build_trainer(case: str, quick: bool = False, large: bool = False):
    """``(fn, info)``: one compiled epoch of ``case`` and what the table needs of it."""
    s, vmapped = (large_cases() if large else cases(quick))[case]
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
    c = s.train
    info = dict(
        num_envs=c.num_envs,
        updates_per_step=c.updates_per_step,
        hidden=list(c.hidden),
        num_seeds=s.num_seeds,
        batch_size=c.batch_size,
        compile_s=time.perf_counter() - t0,
        transitions=s.num_seeds * c.steps_per_epoch * c.num_envs * c.env_steps_per_step,
        updates=s.num_seeds * c.steps_per_epoch * c.updates_per_step,
        rollouts=s.num_seeds * c.steps_per_epoch if c.model_horizon > 0 else 0,  # model-based actor updates
        flops_per_update=update_flops(s),
    )
    return lambda: jax.block_until_ready(compiled(ts, s.hp)), info


def build_peak(n: int = PEAK_N):
    """A float32 (n, n) @ (n, n) matmul: the CPU's FP32 rate on a large matmul."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    t0 = time.perf_counter()
    mm = jax.jit(jnp.matmul).lower(a, a).compile()
    return lambda: jax.block_until_ready(mm(a, a)), dict(flops=2.0 * n**3, compile_s=time.perf_counter() - t0)


def build_layers(seeds: int = 3, width: int = 256, batch: int = 256, steps: int = 20):
    """The matmuls of a 256-256 update's hidden layer alone, at its shapes: for ``seeds`` x 2
    critics, a batched (batch, width) @ (width, width) forward with bias and ReLU, its weight
    gradient and its input gradient, ``steps`` times in a scan (the attainable FP32 rate at
    the shapes the update multiplies)."""
    k = jax.random.split(jax.random.PRNGKey(0), 2)
    x = jax.random.normal(k[0], (seeds, 2, batch, width), jnp.float32)
    w = jax.random.normal(k[1], (seeds, 2, width, width), jnp.float32) / width**0.5

    def layer(w, _):
        h = jax.nn.relu(jnp.einsum("...ni,...io->...no", x, w) + 0.1)
        g_in = jnp.einsum("...no,...io->...ni", h, w) * (x > 0)  # input gradient (through a ReLU)
        g_w = jnp.einsum("...ni,...no->...io", x, h)  # weight gradient
        return w - 1e-6 * g_w + 1e-9 * jnp.mean(g_in), None

    t0 = time.perf_counter()
    fn = jax.jit(lambda w: jax.lax.scan(layer, w, None, length=steps)[0]).lower(w).compile()
    flops = 3 * 2.0 * batch * width * width * seeds * 2 * steps
    return lambda: jax.block_until_ready(fn(w)), dict(flops=flops, compile_s=time.perf_counter() - t0)


BUILDERS = {"trainer": build_trainer, "peak": build_peak, "layers": build_layers}


def baseline_worker(commit: str, tmp: str) -> _peers.Worker:
    """A worker of this script whose ``ttd3_jax`` is the package at ``commit``."""
    git = ["git", "-C", str(_peers.REPO), "archive", commit, "ttd3_jax"]
    tar = subprocess.run(git, check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", tmp], input=tar.stdout, check=True)
    return _peers.Worker(sys.executable, os.path.abspath(__file__), f"baseline-{commit}", path_first=tmp)


def time_all(args, chosen) -> tuple[dict, dict]:
    """Build every case (and its baseline), then time them interleaved; ``(built, best)``."""
    local, worker, built = _peers.Local(BUILDERS), None, {}
    tmp = tempfile.TemporaryDirectory(prefix="ttd3-baseline-")
    try:
        if args.baseline:
            worker = baseline_worker(args.baseline, tmp.name)
        built["peak"] = (local, local.build("peak", "peak"))
        built["layers"] = (local, local.build("layers", "layers"))
        for name in chosen:
            kw = dict(case=name, quick=args.quick, large=args.large)
            built[name] = (local, local.build(name, "trainer", **kw))
            if worker is not None:
                built[f"{name}@base"] = (worker, worker.build(f"{name}@base", "trainer", **kw))
        best = {cid: float("inf") for cid in built}
        for _ in range(args.repeats):
            for cid, (backend, _) in built.items():
                best[cid] = min(best[cid], backend.time(cid))
    finally:
        if worker is not None:
            worker.close()
        tmp.cleanup()
    return {cid: info for cid, (_, info) in built.items()}, best


def table(infos: dict, best: dict) -> tuple[list[dict], float, float]:
    """Prints the table; returns one row per case, the peak FLOP/s and the layers' FLOP/s."""
    peak = infos["peak"]["flops"] / best["peak"]
    layers = infos["layers"]["flops"] / best["layers"]
    fast = infos["fast"]["updates"] / best["fast"] if "fast" in infos else None
    print(f"peak: {peak / 1e9:.1f} GFLOP/s ({PEAK_N}^3 float32 matmul, best of the repeats)")
    print(
        f"layers: {layers / 1e9:.1f} GFLOP/s (3 seeds x 2 critics' 256x256 layer at batch 256: fwd + grads)"
    )
    print(
        f"{'case':<22} {'envs':>5} {'UTD':>4} {'hidden':>8} {'seeds':>5} {'compile s':>9} {'run s':>7} "
        f"{'trans/s':>9} {'upd/s':>8} {'x fast':>6} {'x base':>6} {'GFLOP/s':>7} {'% peak':>6} "
        f"{'% layers':>8}"
    )
    rows = []
    for cid, info in infos.items():
        if cid in ("peak", "layers"):
            continue
        run_s, flops = best[cid], info["flops_per_update"]
        row = dict(case=cid, **info, run_s=run_s, transitions_per_s=info["transitions"] / run_s)
        row["updates_per_s"] = info["updates"] / run_s
        row["samples_per_s"] = row["updates_per_s"] * info["batch_size"]  # minibatch rows through updates
        row["updates_per_s_vs_fast"] = row["updates_per_s"] / fast if fast else None
        base = f"{cid}@base"
        row["vs_baseline"] = best[base] / run_s if base in best else None  # today over baseline
        row["gflops"] = row["updates_per_s"] * flops / 1e9 if flops else None
        row["peak_fraction"] = row["gflops"] * 1e9 / peak if flops else None
        row["layers_fraction"] = row["gflops"] * 1e9 / layers if flops else None
        rows.append(row)
        fmt = lambda v, f: format(v, f) if v is not None else "-"  # noqa: E731
        print(
            f"{cid:<22} {info['num_envs']:>5} {info['updates_per_step']:>4} "
            f"{'-'.join(map(str, info['hidden'])):>8} {info['num_seeds']:>5} {info['compile_s']:>9.1f} "
            f"{run_s:>7.2f} {row['transitions_per_s']:>9.3g} {row['updates_per_s']:>8.3g} "
            f"{fmt(row['updates_per_s_vs_fast'], '6.2f'):>6} {fmt(row['vs_baseline'], '6.2f'):>6} "
            f"{fmt(row['gflops'], '7.1f'):>7} {fmt(row['peak_fraction'], '6.1%'):>6} "
            f"{fmt(row['layers_fraction'], '8.1%'):>8}"
        )
    for row in rows:
        if row.get("rollouts"):
            row["ms_per_rollout"] = 1e3 * row["run_s"] / row["rollouts"]
            print(f"{row['case']}: {row['ms_per_rollout']:.1f} ms per model-based actor update "
                  f"({row['num_envs']} envs x 50 steps, differentiated)")  # fmt: skip
    return rows, peak, layers


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    ap.add_argument("--large", action="store_true", help="thousands of envs (a GPU study)")
    ap.add_argument("--only", nargs="+", default=None, help="run only these cases")
    ap.add_argument("--baseline", default=None, help="also time each case at this git commit, interleaved")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default="benchmarks/results/trainer_throughput.jsonl")
    args = ap.parse_args(argv)
    if args.worker:
        return _peers.serve(BUILDERS)
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.quick:
        args.repeats = 1
    chosen = list(large_cases() if args.large else cases(args.quick))
    if args.only:
        bad = sorted(set(args.only) - set(chosen))
        if bad:
            ap.error(f"unknown case(s) {bad}; allowed: {sorted(chosen)}")
        chosen = [k for k in chosen if k in args.only]
    infos, best = time_all(args, chosen)
    dev = jax.devices()[0]
    print(f"device={dev.platform} ({dev.device_kind}) cpus={os.cpu_count()} jax={jax.__version__}")
    rows, peak, layers = table(infos, best)
    record = _peers.machine_record(argv)
    record.update(
        quick=args.quick,
        large=args.large,
        baseline=args.baseline,
        peak_flops_per_s=peak,
        layers_flops_per_s=layers,
        rows=rows,
    )
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
