"""The generalisation suite for a trained policy, the NMPC and the geometric controller in
one command: one table (Σ‖e‖, steady-state error after 1 s, max error, overshoot on the
step, crash), the JSON, and plots with the three controllers overlaid.

    python experiments/generalization.py RUN_DIR            # RUN_DIR's policy (seed 0, newest epoch)
    python experiments/generalization.py RUN_DIR --best     # its policy selected on the validation tracks
    python experiments/generalization.py --quick            # CI: geometric only, into a temp directory

Each controller runs at its own control rate (the policy at its run's, NMPC and geometric at
the paper's 1 kHz) on the same tracks, and all are judged crashed by one rule (‖e‖ > 1 m).
Writes ``README.md``, ``generalization.json`` and ``{track}_*.png`` to ``--out`` (default
``results/generalization``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import sys
import tempfile

import numpy as np

from ttd3_jax.control import generalization as gen
from ttd3_jax.control.evaluator import Evaluator, controller_build, evaluate_tracks
from ttd3_jax.run.report import device_description, json_safe, plot_traces
from ttd3_jax.run.rundir import load_run
from ttd3_jax.sim.config import EVAL_CRASH_M, make_config
from ttd3_jax.sim.env import TrackingEnv

SUITE = "generalization"
COLUMNS = (("Σ‖e‖ [m]", "tracking_error", "{:.1f}"), ("steady [mm]", "steady_error", "{:.2f}"),
           ("max [m]", "max_error", "{:.3f}"), ("overshoot", "overshoot", "{:.1f} %"),
           ("crash", "crashed", "{:.0f}"))  # fmt: skip


def controllers(args) -> dict:
    """``{label: (env config, build, theta)}`` of the rows."""
    rows = {}
    if args.run_dir:
        run = load_run(args.run_dir, best=args.best)
        seed, theta = run.thetas[0]
        rows[f"{run.spec.algo} ({os.path.basename(os.path.normpath(args.run_dir))}, seed {seed})"] = (
            run.env_config, run.build, theta)  # fmt: skip
    cfg = make_config("paper")
    for name in ("geometric",) if args.quick else ("nmpc", "geometric"):
        rows[name] = (cfg, controller_build(name, cfg.for_eval("los_rt")), None)
    return rows


def table(results: dict, rates: dict) -> list[str]:
    head = "| track | controller | Hz | " + " | ".join(c for c, _, _ in COLUMNS) + " |"
    lines = [head, "| --- | --- | ---: |" + " ---: |" * len(COLUMNS)]
    for track in gen.DESCRIPTIONS:
        for label, per in results.items():
            m = dict(per[track], steady_error=1e3 * per[track]["steady_error"])
            cells = [f.format(m[k]) if np.isfinite(m[k]) else "–" for _, k, f in COLUMNS]
            lines.append(f"| {track} | {label} | {rates[label]:g} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", nargs="?", default=None)
    ap.add_argument("--best", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.run_dir is None and not args.quick:
        ap.error("give RUN_DIR (a training run; `python -m ttd3_jax.train` makes one), or --quick")
    out = args.out or (tempfile.mkdtemp(prefix="gen-") if args.quick else "results/generalization")
    os.makedirs(out, exist_ok=True)
    results, traces, rates = {}, {}, {}
    for label, (cfg, build, theta) in controllers(args).items():
        ev = Evaluator(TrackingEnv(cfg.for_eval("los_rt")), build, sequential=False)
        results[label], traces[label] = evaluate_tracks(
            ev, theta, gen.suite_tracks(SUITE, cfg.dt), timing=False
        )
        rates[label] = 1 / cfg.control_dt
        print(f"{label}: " + ", ".join(f"{t} {m['tracking_error']:.1f}" for t, m in results[label].items()))
    words = [("RUN_DIR" if w == args.run_dir else w) for w in (argv if argv is not None else sys.argv[1:])]
    command = "python experiments/generalization.py " + shlex.join(words)
    device = device_description()
    lines = [
        "# Generalisation suite", "",
        f"`{command}` on {device}, {datetime.date.today()}.", "",
        *([f"RUN_DIR: `{os.path.basename(os.path.normpath(args.run_dir))}`, made by "
           "`python -m ttd3_jax.train` (the `fast` preset, seed 0).", ""] if args.run_dir else []),
        "3 s from rest on p_d(0); Σ‖e‖ over the 3000 physics steps of 1 ms; steady: mean ‖e‖ after "
        f"{gen.STEADY_AFTER_S:g} s; overshoot: how far past the step's target, % of the step; crash: ‖e‖ > "
        f"{EVAL_CRASH_M:g} m (the same for every controller). No track here is in any training mixture.", "",
        *table(results, rates), "",
        *(f"- {k}: {v}" for k, v in gen.DESCRIPTIONS.items()),
    ]  # fmt: skip
    with open(os.path.join(out, "README.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    with open(os.path.join(out, "generalization.json"), "w") as fh:
        json.dump(json_safe(dict(command=command, device=device, rates=rates, results=results,
                                 tracks=gen.DESCRIPTIONS)), fh, indent=2)  # fmt: skip
    plot_traces(traces, out)
    print("\n".join(lines[6:]))
    print(f"wrote {out}/README.md, generalization.json and plots")
    return 0


if __name__ == "__main__":
    sys.exit(main())
