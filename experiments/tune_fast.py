"""Single-seed variants of the ``fast_dpg`` preset (the paper's actor update; it was the ``fast``
preset until 2026-12-01), as explored while tuning it (docs/results.md).

Each variant is the ``fast_dpg`` preset plus a few overrides of the env config (as
``TrainConfig.env_overrides``, so the run directory records them and
``python -m ttd3_jax.evaluate RUN_DIR`` and ``--resume`` rebuild the same env), the
``TrainConfig`` or ``Hyper``.  The script trains each variant, then prints the median Spiral-RT
and LOS-RT tracking error over the last five evaluations (evaluations are noisy from
epoch to epoch), the best single evaluation (an optimistic figure: chosen on the test
tracks) and the policy selected on the validation tracks (the honest one).

    python experiments/tune_fast.py --list
    python experiments/tune_fast.py --variant fast_dpg --variant world_frame
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

from ttd3_jax import train as T
from ttd3_jax.runner import read_metrics, run
from ttd3_jax.trajectories import TrackConfig

# name: (env overrides, TrainConfig overrides, Hyper overrides)
VARIANTS = {
    "fast_dpg": ({}, {}, {}),
    "world_frame": ({"obs_frame": "world"}, {}, {}),
    "e_max_2m": ({"e_max": 2.0}, {}, {}),
    "no_obs_norm": ({}, {"normalize_obs": False}, {}),
    "no_wind": ({"wind_sigma": 0.0}, {}, {}),
    "target_noise_small": ({}, {}, {"target_sigma": 0.05, "target_clip": 0.05}),
    "reward_scale_0.1": ({}, {}, {"reward_scale": 0.1}),
    "velocity_cost": ({"rho_vel": 0.3}, {}, {}),
    "yaw_effort_10": ({"effort_weights": (1.0, 1.0, 1.0, 10.0)}, {}, {}),
    "td3_sigma_0.05": ({}, {"algo": "td3"}, {"sigma": 0.05}),
    "ttd3_lambda_0.001": ({}, {}, {"lam": 0.001}),
    "caps": ({}, {}, {"lam": 0.001, "smooth_time": 0.5, "smooth_space": 0.5}),
    "actor_lr_1e-3_delay_1": ({}, {"policy_delay": 1}, {"lr_actor": 1e-3}),
    "gamma_0.995": ({}, {}, {"gamma": 0.995}),
    "hidden_128": ({}, {"hidden": (128, 128)}, {}),
    "batch_1024_lr_1e-3": (
        {},
        {"batch_size": 1024, "updates_per_step": 8},
        {"lr_actor": 1e-3, "lr_critic": 1e-3},
    ),  # fmt: skip
    "slow_tracks": ({"tracks": TrackConfig(train_scale=(0.05, 1.0))}, {}, {}),
    "slow_tracks_small_init": (
        {
            "tracks": TrackConfig(train_scale=(0.05, 1.0)),
            "init_pos": 0.03,
            "init_vel": 0.05,
            "init_tilt_deg": 3.0,
            "init_yaw_deg": 5.0,
        },
        {},
        {},
    ),  # fmt: skip
    "cubic_rates": ({"rate_map": "cubic"}, {}, {}),
    "cubic_rates_0.25": ({"rate_map": "cubic", "rate_map_slope": 0.25}, {}, {}),
    "heading_frame": ({"obs_frame": "heading"}, {}, {}),
    "error_frame": ({"obs_frame": "error"}, {}, {}),
    "advantage_critic": ({}, {"critic": "advantage"}, {}),
    "advantage_critic_lambda_0.001": ({}, {"critic": "advantage"}, {"lam": 0.001}),
    "advantage_critic_error_frame": ({"obs_frame": "error"}, {"critic": "advantage"}, {}),
    "no_dynamics_tracks": ({"tracks": TrackConfig(train_mix=(0.0, 0.5, 0.5))}, {}, {}),
    "no_dynamics_tracks_adv_lambda_0.001": (
        {"tracks": TrackConfig(train_mix=(0.0, 0.5, 0.5))},
        {"critic": "advantage"},
        {"lam": 0.001},
    ),  # fmt: skip
    "hover_only": ({"tracks": TrackConfig(train_scale=(1e-4, 1e-4))}, {}, {}),  # a diagnostic
    "hover_only_td3_sigma_0.1": (
        {"tracks": TrackConfig(train_scale=(1e-4, 1e-4))},
        {"algo": "td3"},
        {"sigma": 0.1},
    ),  # fmt: skip
    "hover_only_repeat_50": (
        {"tracks": TrackConfig(train_scale=(1e-4, 1e-4)), "action_repeat": 50, "crash_penalty": 5000.0},
        {},
        {},
    ),  # fmt: skip
    "hover_only_gamma_0.95": ({"tracks": TrackConfig(train_scale=(1e-4, 1e-4))}, {}, {"gamma": 0.95}),
    "hover_only_effort_10x": ({"tracks": TrackConfig(train_scale=(1e-4, 1e-4)), "rho2": 0.1}, {}, {}),
    "hover_only_no_wind": ({"tracks": TrackConfig(train_scale=(1e-4, 1e-4)), "wind_sigma": 0.0}, {}, {}),
    "hover_only_nstep_5": ({"tracks": TrackConfig(train_scale=(1e-4, 1e-4))}, {"n_step": 5}, {}),
    "nstep_5": ({}, {"n_step": 5}, {}),
    "nstep_10": ({}, {"n_step": 10}, {}),
    "critic_layer_norm": ({}, {"critic_layer_norm": True}, {}),
    "actor_lr_5e-5": ({}, {}, {"lr_actor": 5e-5}),
    "tau_0.001": ({}, {}, {"tau": 0.001}),
    "repeat_20": ({"action_repeat": 20, "crash_penalty": 2000.0}, {}, {}),
    "repeat_20_gamma_0.98": ({"action_repeat": 20, "crash_penalty": 1000.0}, {}, {"gamma": 0.98}),
    "small_init": ({"init_pos": 0.01, "init_vel": 0.02, "init_tilt_deg": 1.0}, {}, {}),
    "precision_bonus": ({"precision_bonus": 0.1, "precision_scale": 0.02}, {}, {}),
    "utd_1": ({}, {"num_envs": 16, "total_transitions": 300_000, "buffer_size": 300_000}, {}),
    "lr_linear_900k": (
        {},
        {"total_transitions": 900_000, "buffer_size": 900_000, "epochs": 30, "lr_schedule": "linear"},
        {},
    ),  # fmt: skip
}


def config_for(name: str) -> T.TrainConfig:
    env_o, cfg_o, hp_o = VARIANTS[name]
    overrides = tuple(T.env_override(k, v) for k, v in env_o.items())
    c = T.preset("fast_dpg", env_overrides=overrides, **cfg_o)
    c = dataclasses.replace(c, hp=dataclasses.replace(c.hp, **hp_o))
    return T.with_algo(c, c.algo)


def run_variant(name: str, out: str) -> dict:
    summary = run(config_for(name), out=f"{out}/{name}")
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
    if args.list:
        for name, (e, c, h) in VARIANTS.items():
            print(f"{name:<24} env={e} cfg={c} hp={h}")
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
