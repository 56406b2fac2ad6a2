"""``python -m ttd3_jax.evaluate``: a trained policy or a classical controller in closed loop
on Spiral-RT and LOS-RT (spec §2.5), your own track (a CSV file) or the generalisation
suite: the table, run times, optional robustness, JSON, plots and trace CSVs.

    python -m ttd3_jax.evaluate --controller geometric        # Spiral-RT and LOS-RT seed 0
    python -m ttd3_jax.evaluate --controller nmpc --nmpc-solve-every 10
    python -m ttd3_jax.evaluate --controller geometric --task.vehicle.quad.mass 1.8   # any EnvConfig field
    python -m ttd3_jax.evaluate --controller nmpc --vehicle crazyflie     # a named vehicle (sim.vehicles)
    python -m ttd3_jax.evaluate RUN_DIR [--epoch E | --best] [--seed-index I] [--robustness]
    python -m ttd3_jax.evaluate RUN_DIR --vehicle crazyflie   # one of its --task.randomization.vehicles
    python -m ttd3_jax.evaluate RUN_DIR --track my_track.csv      # header t,x,y,z[,vx,vy,vz,ax,ay,az]
    python -m ttd3_jax.evaluate --controller nmpc --suite generalization
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys

import tyro

from ttd3_jax.checks import bool_flags, refuse_bool_values, writable_dir, writable_file
from ttd3_jax.cli.console import show_messages
from ttd3_jax.control import generalization as gen
from ttd3_jax.control.evaluator import (
    CONTROLLERS,
    Evaluator,
    controller_build,
    evaluate_controller,
    evaluate_tracks,
)
from ttd3_jax.control.nmpc import NMPCConfig
from ttd3_jax.control.paper import PAPER
from ttd3_jax.control.robustness import ROBUSTNESS_DESCRIPTIONS, evaluate_robustness
from ttd3_jax.run import memory, report, rundir
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EVAL_CRASH_M, EVAL_PROTOCOL_FIELDS, PRESETS, EnvConfig, make_config
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.sim.vehicle_mix import pin_vehicle
from ttd3_jax.sim.vehicles import VEHICLE_NAMES, vehicle_of, with_vehicle

_NMPC_OPTIONS = (("horizon", "nmpc_horizon"), ("solve_every", "nmpc_solve_every"),
                 ("weight_scale", "nmpc_weight_scale"))  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m ttd3_jax.evaluate",
        description="Evaluate a trained policy (RUN_DIR) or a classical controller (--controller) in closed "
        "loop on Spiral-RT and LOS-RT: tracking metrics, run times, optional robustness, JSON and plots. "
        "--task.FIELD VALUE sets a field of --controller's env (and of its model) on top of --preset, as in "
        "python -m ttd3_jax.train (e.g. --task.action-repeat 5 --task.vehicle.quad.mass 1.8); the fields the "
        "evaluation protocol sets are refused.",
    )
    add = ap.add_argument
    add("run_dir", nargs="?", default=None, help="training run directory: evaluate its policy")
    add("--controller", default=None, choices=CONTROLLERS, help="classical controller (default geometric)")
    add("--epoch", type=int, default=None, help="checkpoint of RUN_DIR (default: the newest that loads)")
    add("--best", action="store_true", help="RUN_DIR's policies selected on the validation tracks (best/)")
    add("--seed-index", type=int, default=None, help="only this seed of RUN_DIR (default: all)")
    add("--preset", default=None, choices=PRESETS, help="env preset of --controller (default paper)")
    add("--vehicle", default=None, choices=VEHICLE_NAMES, help="vehicle of --controller's env (default "
        "paper; --task.vehicle.quad.* on top); with RUN_DIR the run's own vehicle, or one of its "
        "--task.randomization.vehicles (default: the first)")  # fmt: skip
    add(
        "--track",
        default="all",
        help=f"all (default), {', '.join(tr.TEST_TRACKS)}, or a CSV file with header "
        "t,x,y,z [s, m] and optional vx,vy,vz,ax,ay,az (the episode lasts as long as the track)",
    )
    add("--suite", default=None, choices=gen.SUITES, help="the generalisation suite's tracks instead")
    add("--los-seed", type=int, default=0, help="LOS-RT test instance (0 = headline)")
    add("--json", default=None, help="write results here (default RUN_DIR/evaluation.json)")
    add("--plots", default=None, help="write plots and trace CSVs here (default: the JSON file's directory)")
    add(
        "--timing", action=argparse.BooleanOptionalAction, default=True, help="measure run times (default on)"
    )
    add("--repeats", type=int, default=3, help="timed runs per run-time figure (default 3)")
    add("--robustness", action="store_true", help="also evaluate under a fixed unknown mismatch: wind, mass, "
        "thrust, rate lag, latency, observation noise and bias")  # fmt: skip
    add("--robustness-seeds", type=int, default=20, help="LOS-RT seeds 1..N for --robustness")
    add("--nmpc-horizon", type=int, default=None, help="NMPC nodes N (nmpc only)")
    add("--nmpc-solve-every", type=int, default=None, help="NMPC control steps between re-solves (nmpc only)")
    add("--nmpc-weight-scale", type=float, default=None, help="NMPC state-weight scale")
    return ap


def check_args(ap: argparse.ArgumentParser, args) -> dict:
    """Refuse bad or conflicting flags (``ap.error``, exit 2) before anything compiles;
    returns the NMPC options given."""
    for flag, value, lo in (("--los-seed", args.los_seed, 0), ("--repeats", args.repeats, 1),
                            ("--robustness-seeds", args.robustness_seeds, 1)):  # fmt: skip
        if value < lo:
            ap.error(f"{flag} must be >= {lo}, got {value}")
    if args.robustness:
        try:  # Spiral-RT and the LOS-RT seeds of a condition fly in one batch
            memory.check_flights(args.robustness_seeds + 1, "--robustness-seeds", args.robustness_seeds)
        except ValueError as e:
            ap.error(str(e))
    options = {k: getattr(args, a) for k, a in _NMPC_OPTIONS if getattr(args, a) is not None}
    try:
        check_output_paths(args)
    except ValueError as e:
        ap.error(str(e))
    args.custom = None
    if args.track not in ("all", *tr.TEST_TRACKS):
        if args.suite is not None:
            ap.error("--suite and --track FILE exclude each other")
        try:
            args.custom = ct.from_csv(args.track)
        except ValueError as e:
            ap.error(f"--track: {e}")
    elif args.suite is not None and args.track != "all":
        ap.error(f"--suite runs its own tracks; remove --track {args.track}")
    if options and (args.run_dir is not None or args.controller != "nmpc"):
        ap.error("--nmpc-* options need --controller nmpc")
    if args.run_dir is not None:
        try:
            args.run_dir, note = rundir.find_run(args.run_dir)
        except FileNotFoundError as e:
            ap.error(str(e))
        if note:
            print(note)
        for flag, value in (("--controller", args.controller), ("--preset", args.preset),
                            ("--task.*", args.task_args or None)):  # fmt: skip
            if value is not None:
                ap.error(f"{flag} does not apply to RUN_DIR (the run's policy and env config are used)")
        if args.best and args.epoch is not None:
            ap.error("--best and --epoch exclude each other")
        check_run_vehicle(ap, args)
        return options
    for flag, value in (
        ("--epoch", args.epoch),
        ("--seed-index", args.seed_index),
        ("--best", args.best or None),
    ):
        if value is not None:
            ap.error(f"{flag} needs RUN_DIR")
    try:
        args.env_config = classical_env(args.preset, args.task_args, args.vehicle)
        NMPCConfig(**options)
    except (TypeError, ValueError) as e:
        ap.error(str(e))
    return options


def check_output_paths(args) -> None:
    """``--json`` and ``--plots`` can be written (before the evaluation, not after it)."""
    if args.json is not None:
        writable_file("--json", args.json)
        rundir.refuse_run_files("--json", args.json)
    if args.plots is not None:
        writable_dir("--plots", args.plots)
        rundir.refuse_run_files("--plots", args.plots, folder=True)
    elif args.json is not None:  # the plots go beside the JSON file
        rundir.refuse_run_files("--json", os.path.dirname(os.path.abspath(args.json)), folder=True)


@dataclasses.dataclass(frozen=True)
class _Task:
    task: EnvConfig


def check_run_vehicle(ap: argparse.ArgumentParser, args) -> None:
    """``--vehicle`` with RUN_DIR: accepted only when it names the run's own vehicle, or one
    of its ``randomization.vehicles`` (the run's policy flies each)."""
    if args.vehicle is None:
        return
    try:
        task = rundir.load_spec(args.run_dir).task
    except (FileNotFoundError, ValueError) as e:
        ap.error(str(e))
    own, mix = vehicle_of(task.vehicle.quad), task.randomization.vehicles
    if mix and args.vehicle not in mix:
        ap.error(f"--vehicle {args.vehicle} is not one of RUN_DIR's --task.randomization.vehicles "
                 f"{list(mix)}, which its policy was trained on")  # fmt: skip
    if not mix and own != args.vehicle:
        ap.error(f"--vehicle {args.vehicle} does not match RUN_DIR's vehicle ({own or 'a custom vehicle'}), "
                 "which its policy was trained on; remove --vehicle")  # fmt: skip


def classical_env(preset: str, task_args: list[str], vehicle: str | None = None) -> EnvConfig:
    """The env config a classical controller is evaluated (and modelled) with: ``preset``,
    ``vehicle`` (``None``: the preset's) and the ``--task.*`` flags on top (parsed by tyro,
    which exits 2 on a bad value)."""
    default = make_config(preset)
    default = default if vehicle is None else with_vehicle(default, vehicle)
    refuse_bool_values(task_args, bool_flags(_Task))
    cfg = tyro.cli(_Task, default=_Task(default), args=task_args, prog="python -m ttd3_jax.evaluate").task
    if cfg.randomization.vehicles:
        raise ValueError(f"--task.randomization.vehicles {' '.join(cfg.randomization.vehicles)}: a classical "
                         "controller flies one vehicle; allowed: --vehicle NAME")  # fmt: skip
    protocol = [f for f in EVAL_PROTOCOL_FIELDS if cfg.get(f) != default.get(f)]
    if protocol:
        flag = "--task." + EnvConfig.path(protocol[0]).replace("_", "-")
        raise ValueError(
            f"{flag} is set by the evaluation protocol (--track, --los-seed; "
            "--robustness for wind, noise and a mismatched plant; 3000 steps per episode)"
        )
    return cfg


def policies(args) -> tuple:
    """``(env config, build, {label: theta}, header)`` of RUN_DIR's policies."""
    run = rundir.load_run(args.run_dir, args.epoch, best=args.best)
    for epoch, reason in run.skipped:
        print(f"skipped checkpoint {epoch}, which does not load ({reason})", file=sys.stderr)
    if args.seed_index is not None and not 0 <= args.seed_index < len(run.thetas):
        raise ValueError(f"--seed-index must be in [0, {len(run.thetas) - 1}], got {args.seed_index}")
    thetas = run.thetas if args.seed_index is None else [run.thetas[args.seed_index]]
    s, mix = run.spec, run.spec.task.randomization.vehicles
    which = f"selected on the validation tracks, epochs {run.epoch}" if args.best else f"epoch {run.epoch}"
    cfg = pin_vehicle(run.env_config, args.vehicle if mix else None)  # one of the run's vehicles
    own = cfg.randomization.vehicles[0] if mix else vehicle_of(s.task.vehicle.quad) or "custom"
    trained = f" of the vehicles {' to '.join(mix)} it was trained on" if mix else ""
    print(f"run {args.run_dir} {which} ({s.algo}, vehicle {own}{trained}, hover_centered_thrust="
          f"{s.task.vehicle.hover_centered_thrust})")  # fmt: skip
    header = dict(run_dir=args.run_dir, epoch=run.epoch, algo=s.algo, vehicle=own,
                  **({"trained_vehicles": list(mix)} if mix else {}))  # fmt: skip
    return cfg, run.build, {f"seed {seed}": theta for seed, theta in thetas}, header


def classical(args, options: dict) -> tuple:
    """``(env config, build, {label: None}, header)`` of ``--controller``."""
    cfg = args.env_config
    build = controller_build(args.controller, cfg.for_eval("los_rt"), **options)
    opts = "".join(f" {k}={v}" for k, v in options.items())
    flags = "".join(" " + a for a in args.task_args)
    print(f"controller={args.controller}{opts} preset={args.preset} vehicle={args.vehicle}{flags}")
    header = dict(controller=args.controller, options=options, preset=args.preset, vehicle=args.vehicle,
                  task_args=args.task_args)  # fmt: skip
    return cfg, build, {args.controller: None}, header


def write_outputs(args, out: dict, traces: dict, title: str) -> None:
    """The JSON file, plots and trace CSVs (where ``--json`` / ``--plots`` or RUN_DIR say)."""
    json_path = args.json
    if json_path is None and args.run_dir is not None:
        json_path = os.path.join(args.run_dir, "evaluation.json")
    if json_path:
        os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
        with open(json_path, "w") as fh:
            json.dump(report.json_safe(out), fh, indent=2, default=str)
        print(f"wrote {json_path}")
    plots = args.plots or (os.path.dirname(os.path.abspath(json_path)) if json_path else None)
    if plots:
        paths = report.plot_traces(traces, plots, title=title, los_seed=args.los_seed)
        csvs = report.write_traces(traces, plots)
        names = ", ".join(os.path.basename(p) for p in csvs)
        print(f"wrote {len(paths)} plots and {len(csvs)} trace CSVs ({names}) to {plots}")


def evaluator_for(args, cfg: EnvConfig, build, sequential: bool) -> tuple[Evaluator, dict | None]:
    """The :class:`Evaluator` of the tracks the flags name, and those tracks by name
    (``None``: the test tracks).  A CSV track sets the episode's length."""
    eval_cfg = cfg.for_eval("los_rt", los_seed=args.los_seed)
    tracks = None
    if args.custom is not None:
        c = args.custom
        steps = c.episode_steps(cfg.action_repeat)
        if steps < cfg.action_repeat:
            raise ValueError(f"--track {args.track}: {c.duration_s:g} s is shorter than one control step "
                             f"({cfg.control_dt:g} s)")  # fmt: skip
        eval_cfg = eval_cfg.replace(episode_steps=steps)
        tracks = {c.name: c.track()}
        print(f"track {c.name}: {c.duration_s:g} s ({steps} physics steps evaluated); after its last sample "
              "the reference holds the last point")  # fmt: skip
    elif args.suite is not None:
        tracks = gen.suite_tracks(args.suite, cfg.dt)
    return Evaluator(TrackingEnv(eval_cfg), build, sequential), tracks


def split_task_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """``argv`` without, and with only, the ``--task.FIELD VALUE...`` flags (values are the
    tokens up to the next ``--`` flag)."""
    rest, task, into = [], [], None
    for a in argv:
        if a.startswith("--"):
            into = task if a.startswith("--task.") else rest
        (rest if into is None else into).append(a)
    return rest, task


def notes(args, cfg: EnvConfig, tracks: dict | None, header: dict) -> None:
    """What the table's figures mean, printed under it (and the suite's part of ``header``)."""
    print(f"control rate {1 / cfg.control_dt:g} Hz (physics {1 / cfg.dt:g} Hz); crash: ||e|| > "
          f"{EVAL_CRASH_M:g} m at any physics step, the same threshold for every controller")  # fmt: skip
    if tracks is None:
        print(report.format_paper())
    elif args.suite:
        header["suite"] = dict(name=args.suite, tracks=gen.DESCRIPTIONS, steady_after_s=gen.STEADY_AFTER_S)
        for name, text in gen.DESCRIPTIONS.items():
            print(f"  {name}: {text}")
        print(f"steady: mean ||e|| after {gen.STEADY_AFTER_S:g} s; overshoot: how far past the step's "
              "target, % of the step")  # fmt: skip
    if args.timing:
        print(f"loop s: Python loop over a jitted controller+env step (mean of {args.repeats}); scan s: one "
              "compiled scan; act ms: jitted act alone per call")  # fmt: skip


def main(argv=None) -> int:
    logging.getLogger("absl").setLevel(logging.ERROR)  # orbax's warnings are ours to phrase
    show_messages()  # the package's notes (a damaged file, the compile cache), as plain lines
    ap = build_parser()
    argv, task_args = split_task_args(list(sys.argv[1:] if argv is None else argv))
    args = ap.parse_args(argv)
    args.task_args = task_args
    if args.run_dir is None:
        args.controller, args.preset = args.controller or "geometric", args.preset or "paper"
        args.vehicle = args.vehicle or "paper"
    options = check_args(ap, args)
    device = report.device_description()
    sequential = args.run_dir is None and args.controller == "nmpc" and options.get("solve_every", 1) > 1
    try:
        cfg, build, labels, header = policies(args) if args.run_dir else classical(args, options)
        ev, tracks = evaluator_for(args, cfg, build, sequential)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"device={device}")
    header.update(device=device, los_seed=args.los_seed, env_config=dataclasses.asdict(cfg),
                  crash_threshold_m=EVAL_CRASH_M, control_hz=1 / cfg.control_dt,
                  episode_s=ev.env.config.episode_steps * cfg.dt)  # fmt: skip
    results, traces = {}, {}
    for label, theta in labels.items():
        if tracks is None:
            which = tr.TEST_TRACKS if args.track == "all" else (args.track,)
            results[label], traces[label] = evaluate_controller(
                ev, theta, los_seed=args.los_seed, tracks=which, timing=args.timing, repeats=args.repeats
            )
        else:
            results[label], traces[label] = evaluate_tracks(ev, theta, tracks, args.timing, args.repeats)
    print(report.format_results(results, args.timing))
    notes(args, cfg, tracks, header)
    out: dict = dict(header, results=results, paper=PAPER)
    if args.robustness:
        seeds = range(1, args.robustness_seeds + 1)
        out["robustness"] = {label: evaluate_robustness(build, theta, cfg, seeds, sequential=sequential)
                             for label, theta in labels.items()}  # fmt: skip
        out["robustness_conditions"] = ROBUSTNESS_DESCRIPTIONS
        for label, rob in out["robustness"].items():
            print(report.format_robustness(label, rob))
        for name, text in ROBUSTNESS_DESCRIPTIONS.items():
            print(f"  {name}: {text}")
    try:
        write_outputs(args, out, traces, header.get("algo", args.controller))
    except OSError as e:
        print(f"error: cannot write the results ({e.strerror}: {e.filename}); the table above is complete, "
              "pass --json FILE / --plots DIR where there is room", file=sys.stderr)  # fmt: skip
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
