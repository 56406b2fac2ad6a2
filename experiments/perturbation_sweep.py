"""Tracking error against the size of an unknown mismatch (issue 37): a trained policy and the
NMPC on Spiral-RT and LOS-RT seeds 1..N, each perturbation swept on its own.

    python experiments/perturbation_sweep.py RUN_DIR                  # -> results/perturbation
    python experiments/perturbation_sweep.py RUN_DIR --seeds 10 --out /tmp/sweep
    python experiments/perturbation_sweep.py RUN_DIR --mass=-20,0,20 --latency-ms 0,10 --noise 0,1

Panels: the vehicle's mass error (%), the actuation latency (ms, the same in seconds for
every control rate), and the observation noise (× the robustness row's stds: 0.01 m,
0.05 m/s, 0.005).  Each point is a fixed perturbation on the run's nominal evaluation config
(``ttd3_jax.control.robustness``), unknown to both controllers: the policy is RUN_DIR's,
selected on the validation tracks (``best/``; ``--last``: its newest checkpoint), the NMPC
is built for the run's nominal config (its control rate, vehicle and action map) and reads
the observed state.  Writes ``perturbation.json``, ``perturbation.csv`` and
``perturbation.png`` (LOS-RT mean Σ‖e‖ against the size, log scale; a crash marked ×).
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import os
import shlex
import sys
import time

from ttd3_jax.checks import writable_dir
from ttd3_jax.control import robustness as rob
from ttd3_jax.control.evaluator import controller_build
from ttd3_jax.run import rundir
from ttd3_jax.run.report import _pyplot, device_description, json_safe
from ttd3_jax.sim.config import LATENCY_MAX_S, EnvConfig

CONTROLLERS = ("policy", "nmpc")
CSV_COLUMNS = (
    *("panel", "unit", "size", "controller", "los_rt_error_mean", "los_rt_error_std", "los_rt_crashed"),
    *("los_rt_seeds", "los_rt_energy_mean", "spiral_rt_error", "spiral_rt_crashed"),
)
# panel: (flag, default points, unit, axis label)
PANELS = {
    "mass": ("--mass", "-40,-30,-20,-10,0,10,20,30", "%", "mass error [%]"),
    "latency": ("--latency-ms", "0,10,20,30", "ms", "actuation latency [ms]"),
    "obs_noise": ("--noise", "0,0.5,1,2,3", "x", "observation noise [× robustness stds]"),
}


def panel_config(nominal: EnvConfig, panel: str, x: float) -> EnvConfig:
    """The evaluation config of point ``x`` of ``panel`` (in the panel's unit)."""
    if panel == "mass":
        return rob.mass_error(nominal, x / 100)
    if panel == "latency":
        return rob.latency(nominal, x / 1000)
    return rob.obs_noise(nominal, x)


def parse_points(ap: argparse.ArgumentParser, flag: str, text: str) -> tuple[float, ...]:
    try:
        points = tuple(float(p) for p in text.split(","))
    except ValueError:
        ap.error(f"{flag} takes comma-separated numbers, got {text!r}")
    if not all(math.isfinite(p) for p in points):
        ap.error(f"{flag} takes finite numbers, got {text!r}")
    if len(set(points)) != len(points):
        ap.error(f"{flag} repeats a point: {text!r}")
    return tuple(sorted(points))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python experiments/perturbation_sweep.py",
                                 description=__doc__.split("\n\n")[0])  # fmt: skip
    add = ap.add_argument
    add("run_dir", help="training run directory (python -m ttd3_jax.train makes one)")
    add("--out", default="results/perturbation", help="output directory (default results/perturbation)")
    add("--seeds", type=int, default=5, help="LOS-RT test seeds 1..N (default 5)")
    add("--last", action="store_true", help="the run's newest checkpoint, not its validation-selected policy")
    add("--controllers", default=",".join(CONTROLLERS), help="policy, nmpc or both (default policy,nmpc)")
    for _, (flag, default, unit, _label) in PANELS.items():
        add(
            flag,
            default=default,
            help=f"points, comma-separated, in {unit.replace('%', '%%')} (default {default}; '' skips it)",
        )
    return ap


def check_args(ap: argparse.ArgumentParser, args) -> tuple[rundir.LoadedRun, dict]:
    """Refuse bad flags with one line (exit 2) before anything compiles; returns the run and
    ``{panel: {point: EnvConfig}}``."""
    if args.seeds < 1:
        ap.error(f"--seeds must be >= 1, got {args.seeds}")
    args.controllers = tuple(c.strip() for c in args.controllers.split(","))
    bad = [c for c in args.controllers if c not in CONTROLLERS] or (not args.controllers)
    if bad or len(set(args.controllers)) != len(args.controllers):
        ap.error(
            f"--controllers takes policy, nmpc or both, comma-separated; got {','.join(args.controllers)!r}"
        )
    points = {}
    for panel, (flag, _, _, _) in PANELS.items():
        text = getattr(args, flag[2:].replace("-", "_"))
        if text.strip():
            points[panel] = parse_points(ap, flag, text)
    if not points:
        ap.error("every panel is empty: give --mass, --latency-ms or --noise points")
    bounds = (("--mass", "mass", -100, None), ("--latency-ms", "latency", 0, 1e3 * LATENCY_MAX_S),
              ("--noise", "obs_noise", 0, None))  # fmt: skip
    for flag, panel, lo, hi in bounds:
        for x in points.get(panel, ()):
            if x < lo or (panel == "mass" and x == lo) or (hi is not None and x > hi):
                within = (
                    f"({lo:g}, ∞)" if panel == "mass" else f"[{lo:g}, {'∞' if hi is None else f'{hi:g}'}]"
                )
                ap.error(f"{flag} points must be in {within}, got {x:g}")
    try:
        writable_dir("--out", args.out)
        args.run_dir, note = rundir.find_run(args.run_dir)
        if note:
            print(note)
        run = rundir.load_run(args.run_dir, best=not args.last)
        nominal = run.env_config.for_eval("los_rt")
    except (FileNotFoundError, ValueError) as e:
        ap.error(str(e).splitlines()[0])
    configs = {p: {} for p in points}
    for panel, xs in points.items():
        for x in xs:
            try:
                configs[panel][x] = panel_config(nominal, panel, x)
            except ValueError as e:
                ap.error(f"{PANELS[panel][0]} {x:g}: {str(e).splitlines()[0]}")
    return run, configs


def fmt_point(panel: str, x: float) -> str:
    unit = PANELS[panel][2]
    return f"{x:+g} %" if unit == "%" else (f"{x:g} ms" if unit == "ms" else f"×{x:g}")


def point(x: float, s: dict) -> dict:
    """One point of the figures from a :func:`~ttd3_jax.control.evaluator.summarize` summary."""
    los, spiral = s["los_rt"], s["spiral_rt"]
    e = los["tracking_error"]
    return dict(x=x, los_mean=e["mean"], los_std=e["std"], los_crashed=los["crashed"],
                los_energy=los["energy"]["mean"], spiral=spiral["tracking_error"],
                spiral_crashed=int(spiral["crashed"] > 0))  # fmt: skip


def plot(path: str, data: dict, seeds: int, title: str) -> None:
    """Three panels: LOS-RT mean Σ‖e‖ (± std) against each perturbation's size, log y; a
    point where any track crashed is ringed with a red ×."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(data), figsize=(4.6 * len(data), 3.8), squeeze=False)
    styles = {"policy": dict(color="C0", marker="o"), "nmpc": dict(color="C1", marker="s")}
    for ax, (panel, rows) in zip(axes[0], data.items(), strict=True):
        for who, pts in rows.items():
            xs = [p["x"] for p in pts]
            ys = [p["los_mean"] if math.isfinite(p["los_mean"]) else math.nan for p in pts]
            err = [p["los_std"] if math.isfinite(p["los_std"]) else 0.0 for p in pts]
            ax.errorbar(xs, ys, yerr=err, capsize=3, label=who, **styles[who])
            crashed = [
                (p["x"], y) for p, y in zip(pts, ys, strict=True) if p["los_crashed"] or p["spiral_crashed"]
            ]
            if crashed:
                top = max((y for y in ys if math.isfinite(y)), default=1.0)
                cx = [x for x, _ in crashed]
                cy = [y if math.isfinite(y) else top for _, y in crashed]
                ax.scatter(
                    cx, cy, marker="x", s=90, color="red", zorder=5, label=f"{who}: crash (LOS-RT tracks)"
                )
                for p, x, y in zip(
                    (p for p in pts if p["los_crashed"] or p["spiral_crashed"]), cx, cy, strict=True
                ):
                    ax.annotate(f"{p['los_crashed']}/{seeds}", (x, y), textcoords="offset points",
                                xytext=(-28, 4), fontsize=8, color="red")  # fmt: skip
        ax.set_yscale("log")
        ax.set_xlabel(PANELS[panel][3])
        ax.set_ylabel("LOS-RT Σ‖e‖ [m], mean ± std")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{title}: LOS-RT seeds 1..{seeds}, unknown mismatch", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def cell(p: dict | None) -> str:
    if p is None:
        return "–"
    crash = f" ({p['los_crashed']} crashed)" if p["los_crashed"] else ""
    return f"{p['los_mean']:.1f} ± {p['los_std']:.1f}{crash} | {p['spiral']:.2f}"


def write_outputs(out: str, meta: dict, data: dict) -> None:
    """``README.md`` (the tables), ``perturbation.json``, ``perturbation.csv`` and
    ``perturbation.png`` of a sweep into ``out``."""
    os.makedirs(out, exist_ok=True)
    n = len(meta["los_seeds"])
    with open(os.path.join(out, "perturbation.json"), "w") as fh:
        json.dump(json_safe(dict(meta, panels=data)), fh, indent=2)
    with open(os.path.join(out, "perturbation.csv"), "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for panel, rows in data.items():
            for who, pts in rows.items():
                for p in pts:
                    w.writerow([panel, PANELS[panel][2], f"{p['x']:g}", who, f"{p['los_mean']:.4f}",
                                f"{p['los_std']:.4f}", p["los_crashed"], n, f"{p['los_energy']:.2f}",
                                f"{p['spiral']:.4f}", p["spiral_crashed"]])  # fmt: skip
    title = f"{meta['algo']} ({meta['run']}) vs NMPC, {meta['control_hz']:g} Hz"
    plot(os.path.join(out, "perturbation.png"), data, n, title)
    whos = sorted({who for rows in data.values() for who in rows}, key=CONTROLLERS.index)
    lines = [
        "# Tracking error against the size of an unknown mismatch", "",
        f"`{meta['command']}` on {meta['device']} (a 2-core VM with niced background runs), {meta['date']}, "
        f"{meta['elapsed_s'] / 60:.0f} min. RUN_DIR: `{meta['run']}` (`{meta['algo']}`, seed {meta['seed']}, "
        f"epoch {meta['epoch']}, {meta['policy']}); NMPC {meta['nmpc']}, at the run's "
        f"{meta['control_hz']:g} Hz. LOS-RT seeds 1..{n}: Σ‖e‖ mean ± std [m]; Spiral-RT Σ‖e‖ [m]; crash: "
        "‖e‖ > 1 m. Each point is one fixed perturbation of the nominal evaluation config "
        "(`ttd3_jax.control.robustness`); the others stay nominal. Observation noise ×1 is the robustness "
        "row's: 0.01 m, 0.05 m/s, 0.005 per quaternion component.", "",
        "![Σ‖e‖ against the size](perturbation.png)", "",
    ]  # fmt: skip
    for panel, rows in data.items():
        head = " | ".join(f"{who} LOS-RT | {who} Spiral-RT" for who in whos)
        lines += [
            f"## {PANELS[panel][3]}",
            "",
            f"| size | {head} |",
            "| ---: |" + " ---: | ---: |" * len(whos),
        ]
        xs = sorted({p["x"] for pts in rows.values() for p in pts})
        for x in xs:
            cells = [cell(next((p for p in rows.get(who, ()) if p["x"] == x), None)) for who in whos]
            lines.append(f"| {fmt_point(panel, x)} | " + " | ".join(cells) + " |")
        lines.append("")
    with open(os.path.join(out, "README.md"), "w") as fh:
        fh.write("\n".join(lines))


def main(argv=None) -> int:
    ap = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    run, configs = check_args(ap, args)
    seeds = range(1, args.seeds + 1)
    seed, theta = run.thetas[0]
    epoch = run.epoch[seed] if isinstance(run.epoch, dict) else run.epoch  # best/: {seed: epoch}
    nominal = run.env_config.for_eval("los_rt")
    which = "newest checkpoint" if args.last else "selected on the validation tracks"
    rate = 1 / run.env_config.control_dt
    print(f"run {args.run_dir}: {run.spec.algo} seed {seed}, epoch {epoch} ({which}); NMPC built for its "
          f"nominal config, {rate:g} Hz; LOS-RT seeds 1..{args.seeds}")  # fmt: skip
    device = device_description()
    print(f"device={device}")
    builds = {}
    if "policy" in args.controllers:
        builds["policy"] = (run.build, theta)
    if "nmpc" in args.controllers:
        builds["nmpc"] = (controller_build("nmpc", nominal), None)
    data = {p: {} for p in configs}
    t_all = time.perf_counter()
    for who, (build, th) in builds.items():
        for panel, cfgs in configs.items():
            t0 = time.perf_counter()
            names = {fmt_point(panel, x): x for x in cfgs}

            def progress(name, s, who=who, panel=panel, t0=t0):
                los = s["los_rt"]
                e = los["tracking_error"]
                spiral = s["spiral_rt"]["tracking_error"]
                print(f"[{who}] {panel} {name:>7}: LOS-RT Σ‖e‖ {e['mean']:9.2f} ± {e['std']:7.2f} (crashed "
                      f"{los['crashed']}/{len(los['seeds'])}), Spiral-RT {spiral:8.2f}"
                      f"  [{time.perf_counter() - t0:6.1f} s]", flush=True)  # fmt: skip

            res = rob.evaluate_configs(build, th, {n: cfgs[x] for n, x in names.items()}, seeds,
                                       progress=progress)  # fmt: skip
            data[panel][who] = [point(x, res[n]) for n, x in names.items()]
    elapsed = time.perf_counter() - t_all
    words = [("RUN_DIR" if w == args.run_dir else w) for w in argv]
    command = "python experiments/perturbation_sweep.py " + shlex.join(words)
    meta = dict(command=command, device=device, date=str(datetime.date.today()), elapsed_s=elapsed,
                run=os.path.basename(os.path.normpath(args.run_dir)), algo=run.spec.algo, seed=seed,
                epoch=epoch, policy=which, control_hz=rate, los_seeds=list(seeds),
                units={p: PANELS[p][2] for p in configs}, obs_noise_stds=rob.ROBUSTNESS_OBS_NOISE,
                nmpc="built for the run's nominal config, sensed state, unknown mismatch")  # fmt: skip
    write_outputs(args.out, meta, data)
    print(f"wrote {args.out}/README.md, perturbation.json, .csv and .png ({elapsed:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
