"""T-TD3's exploration σ against collected transitions, for each reading the spec keeps
(A1 ``delta_reduce`` sum | mean, A3 ``t_unit`` episode | env_step | update), in the quadrotor
(``fast_dpg``) and MuJoCo (protocol) settings.

    σ = β·u_max·exp(−λ t) + (1 − β)·u_max·exp(−δ),   δ = Σ_j or mean_j (r_j − r_min)/(r_max − r_min)

The time term is exact.  δ depends on the rewards of each minibatch: it is measured here on
2000 minibatches of B = 256 drawn from a real replay buffer (a run's newest checkpoint with
``--quad-run`` / ``--mujoco-run``, else the random warm-up of that setting), and the curve uses
its median (the band: 5 – 95 %).  The σ that a run logged (metrics.csv, the run's own reading)
is drawn on top as a check of the formula against the trainer.  Writes ``--out``/sigma.png
and sigma.json.

    python experiments/sigma_schedule.py --quad-run RUN_DIR --mujoco-run RUN_DIR
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np

from ttd3_jax.run import spec as sp
from ttd3_jax.run.rundir import load_train_state, read_metrics
from ttd3_jax.td3.trainer import seed_keys

READINGS = [(d, t) for d in ("sum", "mean") for t in ("episode", "env_step", "update")]
DRAWS, BATCH = 2000, 256
FLOOR = 1e-9  # σ below this is drawn on the plot's floor


def setting(name: str) -> sp.RunSpec:
    """The run spec whose schedule is drawn: ``quadrotor`` (fast_dpg) or ``mujoco`` (hopper)."""
    return sp.preset("fast_dpg" if name == "quadrotor" else "mujoco")


def buffer_rewards(spec: sp.RunSpec, run_dir: str | None) -> tuple[np.ndarray, str]:
    """Rewards (as stored: times reward_scale) of seed 0's replay buffer, and where from."""
    if run_dir:
        st = load_train_state(run_dir).state
        n = int(np.asarray(st.buffer.size)[0])
        return np.asarray(st.buffer.data.reward[0, :n]), f"{run_dir} (newest checkpoint, {n} transitions)"
    small = sp.replace(spec, warmup_transitions=min(spec.train.warmup_transitions, 10_000),
                       buffer_size=min(spec.train.buffer_size, 10_000))  # fmt: skip
    ts = jax.jit(sp.trainer_for(small).init)(seed_keys(0, 1)[0], small.hp)
    n = int(ts.buffer.size)
    return np.asarray(ts.buffer.data.reward[:n]), f"random warm-up ({n} transitions)"


def delta_samples(rewards: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """δ under each reduction on ``DRAWS`` minibatches of ``BATCH`` rewards."""
    rng = np.random.default_rng(seed)
    r = rewards[rng.integers(0, len(rewards), (DRAWS, BATCH))]
    lo, hi = r.min(1, keepdims=True), r.max(1, keepdims=True)
    norm = (r - lo) / np.maximum(hi - lo, 1e-8)
    return {"sum": norm.sum(1), "mean": norm.mean(1)}


def sigma_curve(spec: sp.RunSpec, n_tr: np.ndarray, reduce: str, t_unit: str, delta: float, L: int):
    """σ after ``n_tr`` transitions per seed (after the warm-up; u_max, β, λ from ``spec.hp``)."""
    hp, c = spec.hp, spec.train
    n_upd = c.updates_per_step * np.maximum(n_tr - c.warmup_transitions, 0) / c.num_envs
    t = {"episode": n_tr / L, "env_step": n_tr, "update": n_upd}[t_unit]
    return hp.beta * hp.u_max * np.exp(-hp.lam * t) + (1 - hp.beta) * hp.u_max * np.exp(-delta)


def logged_sigma(run_dir: str | None):
    """(transitions, σ) at the end of each epoch of the run's first seed, or None."""
    if not run_dir:
        return None
    rows = read_metrics(run_dir)
    rows = [r for r in rows if r["seed"] == rows[0]["seed"]]  # the run's first seed
    return [float(r["env_steps"]) for r in rows], [float(r["sigma"]) for r in rows]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quad-run", default=None, help="a quadrotor run (fast_dpg env) for δ and its logged σ")
    ap.add_argument("--mujoco-run", default=None, help="a hopper run for δ and its logged σ")
    ap.add_argument("--out", default="results/sigma")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(a.out, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    record = {}
    for ax, (name, run_dir) in zip(axes, (("quadrotor", a.quad_run), ("mujoco", a.mujoco_run)), strict=True):
        spec = setting(name)
        L = sp.env_spec(spec).episode_length
        rewards, source = buffer_rewards(spec, run_dir)
        deltas = delta_samples(rewards)
        n_tr = np.geomspace(spec.train.warmup_transitions, spec.train.total_transitions, 400)
        rec = {"source": source, "episode_length": L, "delta_quantiles": {}, "sigma_end": {}}
        for reduce, t_unit in READINGS:
            q5, q50, q95 = np.quantile(deltas[reduce], [0.05, 0.5, 0.95])
            rec["delta_quantiles"][reduce] = [float(q5), float(q50), float(q95)]
            mid = sigma_curve(spec, n_tr, reduce, t_unit, q50, L)
            style = "-" if reduce == "sum" else "--"
            line = ax.plot(n_tr, np.maximum(mid, FLOOR), style, label=f"{reduce}, t per {t_unit}")[0]
            lo = sigma_curve(spec, n_tr, reduce, t_unit, q95, L)
            hi = sigma_curve(spec, n_tr, reduce, t_unit, q5, L)
            band = np.maximum(lo, FLOOR), np.maximum(hi, FLOOR)
            ax.fill_between(n_tr, *band, color=line.get_color(), alpha=0.15)
            marks = (spec.train.warmup_transitions, 100_000, 300_000, spec.train.total_transitions)
            at = {k: float(sigma_curve(spec, np.array([k]), reduce, t_unit, q50, L)[0]) for k in marks}
            rec["sigma_end"][f"{reduce}/{t_unit}"] = at
        ax.axhline(spec.hp.sigma, color="k", lw=1, ls=":", label=f"TD3 σ = {spec.hp.sigma:g}")
        logged = logged_sigma(run_dir)
        if logged:
            ax.plot(*logged, "k.", ms=6, label="σ logged by the run (sum, episode)")
        title = f"{name}: L_nom {L}, {spec.train.num_envs} env(s), G {spec.train.updates_per_step}"
        ax.set(xscale="log", yscale="log", ylim=(FLOOR / 2, 1.5), xlabel="transitions per seed",
               ylabel="σ (std)", title=title)  # fmt: skip
        ax.grid(True, which="major", alpha=0.3)
        record[name] = rec
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(
        "T-TD3 exploration σ under the spec's readings (δ: median, band 5–95 % of minibatches; "
        f"σ < {FLOOR:g} drawn at the floor)"
    )
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sigma.png"), dpi=120)
    with open(os.path.join(a.out, "sigma.json"), "w") as fh:
        json.dump(record, fh, indent=2)
    print(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
