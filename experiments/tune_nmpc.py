"""NMPC tuning (spec §2.6): weight scale {¼, 1, 4} × horizon N ∈ {10, 20, 40}.

Judged on the 10 validation tracks only (``sim.trajectories.validation_tracks``, drawn
from the training mixture), or with ``--wide`` on the wide mixture's 18
(``sim.track_families.wide_validation_tracks``: the tracks ``--preset robust`` selects its
policy on); the test tracks Spiral-RT, LOS-RT and the generalisation suite are never run
here.  Every setting runs the full 3000-step evaluation protocol (``paper`` preset,
start on p_d(0) at rest and level, no wind) on all validation tracks in one
``vmap``, and the table reports the mean and worst Σ‖e‖ over the tracks, the mean
RMSE, the worst max error, the crash count and the mean energy Σ‖a‖.  The choice is
the lowest mean Σ‖e‖ with no crash.

The node spacing stays at 0.05 s, so N = 10/20/40 is a 0.5/1/2 s horizon.

    python experiments/tune_nmpc.py                     # about 2-4 min on one CPU core
    python experiments/tune_nmpc.py --solve-every 10 --json tune.json
    python experiments/tune_nmpc.py --wide              # the robust preset's validation tracks
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.control.closed_loop import evaluate_on_tracks
from ttd3_jax.control.nmpc import NMPCConfig, nmpc_controller
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import PRESETS, make_config
from ttd3_jax.sim.env import TrackingEnv, num_validation_tracks, validation_tracks
from ttd3_jax.sim.track_families import WIDE_MIX, wide_validation_families


def run_setting(env: TrackingEnv, tracks: tr.Track, cfg: NMPCConfig) -> tuple[dict, float, float]:
    """Metrics on every track (numpy arrays with a leading track axis), compile s, run s."""
    ctrl = nmpc_controller(env.config, cfg)
    fn = jax.jit(lambda t: evaluate_on_tracks(env, ctrl, t))
    t0 = time.perf_counter()
    compiled = fn.lower(tracks).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(tracks))
    t_run = time.perf_counter() - t0
    return {k: np.asarray(v) for k, v in out.items()}, t_compile, t_run


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scales", type=float, nargs="+", default=[0.25, 1.0, 4.0], help="weight_scale grid")
    ap.add_argument("--horizons", type=int, nargs="+", default=[10, 20, 40], help="horizon N grid")
    ap.add_argument("--solve-every", type=int, default=1, help="control steps between re-solves")
    ap.add_argument("--num-tracks", type=int, default=None, help="first n validation tracks (default: all)")
    ap.add_argument(
        "--wide", action="store_true", help="the wide mixture's validation tracks (--preset robust's)"
    )
    ap.add_argument("--preset", default="paper", choices=PRESETS)
    ap.add_argument("--json", default=None, help="also write the table to this JSON file")
    args = ap.parse_args(argv)
    cfg = make_config(args.preset)
    cfg = cfg.replace(wide_mix=WIDE_MIX) if args.wide else cfg
    n_bank = num_validation_tracks(cfg)
    args.num_tracks = n_bank if args.num_tracks is None else args.num_tracks
    if not 1 <= args.num_tracks <= n_bank:
        ap.error(f"--num-tracks must be in [1, {n_bank}], got {args.num_tracks}")

    env = TrackingEnv(cfg.for_eval("validation"))
    bank = validation_tracks(env.config, env.num_segments)
    tracks = jax.tree.map(lambda x: x[: args.num_tracks], bank)
    if args.wide:
        kinds = list(wide_validation_families(WIDE_MIX))[: args.num_tracks]
    else:
        kinds = ["spiral" if int(k) == tr.SPIRAL else "piecewise" for k in np.asarray(tracks.kind)]
    print(
        f"NMPC tuning on {args.num_tracks} {'wide ' * args.wide}validation tracks ({', '.join(kinds)}); "
        f"preset={args.preset}, solve_every={args.solve_every}, device={jax.devices()[0].platform}"
    )
    head = (
        f"{'scale':>6} {'N':>4} {'mean Σ‖e‖':>10} {'worst Σ‖e‖':>11} {'RMSE':>8} {'max e':>7} "
        f"{'crash':>5} {'Σ‖a‖':>8} {'compile s':>9} {'run s':>7}"
    )
    print(head)
    rows = []
    for n in args.horizons:
        for s in args.scales:
            cfg = NMPCConfig(horizon=n, weight_scale=s, solve_every=args.solve_every)
            m, tc, trun = run_setting(env, tracks, cfg)
            err = m["tracking_error"]
            row = dict(
                weight_scale=s,
                horizon=n,
                mean_error=float(np.mean(err)),
                worst_error=float(np.max(err)),
                rmse=float(np.mean(m["rmse"])),
                max_error=float(np.max(m["max_error"])),
                crashes=int(np.sum(m["crashed"] > 0)),
                energy=float(np.mean(m["energy"])),
                per_track_error=[float(x) for x in err],
                compile_s=tc,
                run_s=trun,
            )
            rows.append(row)
            line = f"{s:>6g} {n:>4d} {row['mean_error']:>10.2f} {row['worst_error']:>11.2f} "
            line += f"{row['rmse']:>8.4f} {row['max_error']:>7.3f} {row['crashes']:>5d} "
            print(line + f"{row['energy']:>8.1f} {tc:>9.1f} {trun:>7.1f}", flush=True)
    ok = [r for r in rows if r["crashes"] == 0 and np.isfinite(r["mean_error"])] or rows
    best = min(ok, key=lambda r: r["mean_error"])
    print(f"choice: weight_scale={best['weight_scale']:g}, horizon={best['horizon']} (lowest mean Σ‖e‖)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"solve_every": args.solve_every, "wide": args.wide, "tracks": kinds, "rows": rows,
                       "choice": best}, fh, indent=2)  # fmt: skip
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing anything
    sys.exit(main())
