"""Single-seed variants of the ``fast_dpg`` preset (the paper's actor update; it was the ``fast``
preset until 2026-12-01), as explored while tuning it (docs/results.md).

Each variant is the ``fast_dpg`` run spec with a few fields changed: of the env (the spec's
``task``, an :class:`~ttd3_jax.sim.config.EnvConfig`), of the ``TrainConfig`` or of the
``Hyper``.  The run directory's ``config.json`` records the whole spec, so
``python -m ttd3_jax.evaluate RUN_DIR`` and ``--resume`` rebuild the same env.  The script
trains each variant, then prints the median Spiral-RT and LOS-RT tracking error over the
last five evaluations (evaluations are noisy from epoch to epoch), the best single
evaluation (an optimistic figure: chosen on the test tracks) and the policy selected on the
validation tracks (the honest one).  (Variants of options that no longer exist are in git
history.)

    python experiments/tune_fast.py --list
    python experiments/tune_fast.py --variant fast_dpg --variant world_frame
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

from ttd3_jax.cli.console import show_messages
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.run.rundir import read_metrics
from ttd3_jax.sim.trajectories import TrackConfig

# name: (EnvConfig changes, TrainConfig changes, Hyper changes)
VARIANTS = {
    "fast_dpg": ({}, {}, {}),
    "world_frame": ({"obs_frame": "world"}, {}, {}),
    "e_max_2m": ({"e_max": 2.0}, {}, {}),
    "no_obs_norm": ({}, {"normalize_obs": False}, {}),
    "no_wind": ({"wind_sigma": 0.0}, {}, {}),
    "target_noise_small": ({}, {}, {"target_sigma": 0.05, "target_clip": 0.05}),
    "reward_scale_0.1": ({}, {}, {"reward_scale": 0.1}),
    "yaw_effort_10": ({"effort_weights": (1.0, 1.0, 1.0, 10.0)}, {}, {}),
    "td3_sigma_0.05": ({}, {"algo": "td3"}, {"sigma": 0.05}),
    "ttd3_lambda_0.001": ({}, {}, {"lam": 0.001}),
    "actor_lr_1e-3_delay_1": ({}, {"policy_delay": 1}, {"lr_actor": 1e-3}),
    "gamma_0.995": ({}, {}, {"gamma": 0.995}),
    "hidden_128": ({}, {"hidden": (128, 128)}, {}),
    "batch_1024_lr_1e-3": (
        {},
        {"batch_size": 1024, "updates_per_step": 8},
        {"lr_actor": 1e-3, "lr_critic": 1e-3},
    ),  # fmt: skip
    "no_dynamics_tracks": ({"tracks": TrackConfig(train_mix=(0.0, 0.5, 0.5))}, {}, {}),
    "actor_lr_5e-5": ({}, {}, {"lr_actor": 5e-5}),
    "tau_0.001": ({}, {}, {"tau": 0.001}),
    "repeat_20": ({"action_repeat": 20, "crash_penalty": 2000.0}, {}, {}),
    "repeat_20_gamma_0.98": ({"action_repeat": 20, "crash_penalty": 1000.0}, {}, {"gamma": 0.98}),
    "small_init": ({"init_pos": 0.01, "init_vel": 0.02, "init_tilt_deg": 1.0}, {}, {}),
    "utd_1": ({}, {"num_envs": 16, "total_transitions": 300_000, "buffer_size": 300_000}, {}),
}


def spec_for(name: str) -> sp.RunSpec:
    """The run spec of variant ``name``: ``fast_dpg`` with the variant's changes."""
    task_o, train_o, hp_o = VARIANTS[name]
    s = sp.preset("fast_dpg")
    return sp.replace(s, task=dataclasses.replace(s.task, **task_o), hp=s.hp.replace(**hp_o), **train_o)


def run_variant(name: str, out: str) -> dict:
    summary = run(spec_for(name), out=f"{out}/{name}")
    rows = read_metrics(summary["run_dir"])
    sp = [float(r["spiral_tracking_error"]) for r in rows]
    los = [float(r["los_tracking_error"]) for r in rows]
    sel = summary.get("selected") or [{}]  # chosen on the validation tracks (older runs: none)
    return dict(
        variant=name,
        spiral_last5=statistics.median(sp[-5:]),
        los_last5=statistics.median(los[-5:]),
        spiral_best=min(sp),
        los_best=min(los),
        spiral_selected=sel[0].get("spiral_tracking_error", float("nan")),
        los_selected=sel[0].get("los_tracking_error", float("nan")),
        run_dir=summary["run_dir"],
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variant", action="append", default=None, help="repeatable; default: all")
    ap.add_argument("--out", default="runs/tune_fast")
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args(argv)
    show_messages()  # the runner's log, as plain lines
    if args.list:
        for name, (e, c, h) in VARIANTS.items():
            print(f"{name:<24} task={e} train={c} hp={h}")
        return 0
    names = args.variant or list(VARIANTS)
    bad = [n for n in names if n not in VARIANTS]
    if bad:
        ap.error(f"unknown variant(s) {bad}; allowed: {list(VARIANTS)}")
    results = [run_variant(n, args.out) for n in names]
    head = f"{'variant':<24} {'Spiral last-5 median':>21} {'LOS last-5 median':>18}"
    print(f"{head} {'best Spiral':>11} {'best LOS':>9} {'selected (val) Spiral / LOS':>28}")
    for r in results:
        print(
            f"{r['variant']:<24} {r['spiral_last5']:>21.1f} {r['los_last5']:>18.1f} "
            f"{r['spiral_best']:>11.1f} {r['los_best']:>9.1f} "
            f"{r['spiral_selected']:>17.1f} / {r['los_selected']:.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
