"""Issue 37's table: the ``robust`` policy (each seed), the ``fast`` policy and our NMPC side by
side on the paper's test tracks, the generalisation suite and the robustness rows, each row
checked against its target.

    python experiments/robust_table.py ROBUST_RUN                      # -> results/robust
    python experiments/robust_table.py ROBUST_RUN --fast-run FAST_RUN \\
        --nmpc-robustness results/robustness/nmpc.json --robustness-seeds 20

The policies are each seed's policy selected on the validation tracks (``best/``; ``--last``:
each seed's last policy, the newest checkpoint), at their
run's control rate; the NMPC is the paper preset's, at 1 kHz, as in
``experiments/generalization.py`` and ``results/robustness``, flying ROBUST_RUN's vehicle (a
``cf2`` run: the ``cf2`` vehicle, its firmware loop in the NMPC's model,
``control.loop_model``).  Every controller is judged crashed by one rule (‖e‖ > 1 m).  The
targets (issue 37, item 4), on every seed of ROBUST_RUN:

- Spiral-RT and LOS-RT seed 0 (nominal): Σ‖e‖ below the paper's T-TD3 (25.99 / 398.74);
- every suite track: Σ‖e‖ ≤ the NMPC's, steady-state error ≤ 2× the NMPC's, and on the step
  an overshoot ≤ 10 %;
- every robustness row (one fixed mismatch, unknown to both controllers, the same
  reference): Spiral-RT Σ‖e‖ and LOS-RT seeds 1..N mean Σ‖e‖ ≤ the NMPC's.

A seed that crashes more often than the NMPC on a row misses that row's target.  The NMPC's
robustness at 1 kHz takes ≈ 20 min for 20 seeds on 2 CPU cores: ``--nmpc-robustness FILE``
reads a saved ``python -m ttd3_jax.evaluate --controller nmpc --robustness --json FILE``
(``--vehicle NAME`` for a run of that vehicle) instead, accepted only when it was written by the
default NMPC on the paper preset's nominal config with the run's vehicle, with today's
robustness conditions (names and descriptions) and LOS-RT seeds
1..``--robustness-seeds``.  Writes ``README.md`` (the table) and ``robust_table.json``
(every number) to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import shlex
import sys
import time

from ttd3_jax.checks import writable_dir
from ttd3_jax.control import generalization as gen
from ttd3_jax.control import robustness as rob
from ttd3_jax.control.evaluator import (
    Evaluator,
    controller_build,
    evaluate_controller,
    evaluate_tracks,
    los_statistics,
)
from ttd3_jax.control.paper import PAPER
from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.report import device_description, json_safe
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EVAL_CRASH_M, make_config
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.sim.vehicles import VEHICLE_NAMES, vehicle_of, with_vehicle

SUITE = "generalization"
NMPC = "NMPC"
PAPER_TTD3 = {t: PAPER["T-TD3"][t]["tracking_error"] for t in tr.TEST_TRACKS}  # 25.99, 398.74
TRACK_TITLES = {"spiral_rt": "Spiral-RT", "los_rt": "LOS-RT"}
LOOP_NOTE = " (its firmware loop in the NMPC's model: `ttd3_jax.control.loop_model`)"
STEADY_FACTOR = 2.0  # the steady-state error's target: at most this times the NMPC's
OVERSHOOT_MAX = 10.0  # %, the step's overshoot target


# --------------------------------------------------------------------------- the targets


def verdict(values, limit: float, *, crashes=None, ref_crashes: float = 0, ref: float | None = None,
            ref_name: str = NMPC, unit: str = "", note: str = "") -> dict:  # fmt: skip
    """Whether each seed's ``values[i]`` meets a target of at most ``limit``, and how far the
    worst misses.  A seed meets it when its value is finite, not above ``limit`` (a non-finite
    limit, a reference that failed, bounds nothing) and it crashed no more often
    (``crashes[i]``) than the reference (``ref_crashes``).  With ``ref`` the miss is stated
    as the worst ratio ``value / ref`` ("2/3; worst 1.4× NMPC"), else as the worst value
    itself ("worst 14.2 % (limit 10 %)"); ``note`` is appended to a miss ("limit 2×")."""
    values = [float(v) for v in values]
    crashes = [0] * len(values) if crashes is None else list(crashes)
    bounded = math.isfinite(limit)
    met = [
        math.isfinite(v) and (not bounded or v <= limit) and c <= ref_crashes
        for v, c in zip(values, crashes, strict=True)
    ]
    crashed = sum(c > ref_crashes for c in crashes)
    out = dict(met=met, k=sum(met), n=len(values), limit=limit, ref=ref, ref_name=ref_name, crashed=crashed)
    if ref is not None:
        ratios = [v / ref if ref > 0 and math.isfinite(v) else math.inf for v in values]
        out["ratios"] = ratios
        out["worst_ratio"] = max(ratios, default=math.nan)
    out["worst"] = max((v if math.isfinite(v) else math.inf for v in values), default=math.nan)
    text = f"{out['k']}/{out['n']}"
    if out["k"] < out["n"]:
        if ref is not None:
            text += f"; worst {fmt_ratio(out['worst_ratio'])} {ref_name}"
        else:
            text += f"; worst {fmt_value(out['worst'])}{unit}"
        if note:
            text += f" ({note})"
        if crashed:
            often = f" more often than {ref_name}" if ref_crashes else ""
            text += f"; {crashed} seed{'s' * (crashed > 1)} crashed{often}"
    out["text"] = text
    return out


def fmt_ratio(r: float) -> str:
    return "∞×" if not math.isfinite(r) else (f"{r:.2f}×" if r < 10 else f"{r:.0f}×")


def fmt_value(v: float, spec: str = ".1f") -> str:
    return format(v, spec) if math.isfinite(v) else ("inf" if v > 0 else "nan")


# --------------------------------------------------------------------------- a saved NMPC file


def _first_difference(a, b, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                return f"{path}{k}"
            d = _first_difference(a[k], b[k], f"{path}{k}.")
            if d:
                return d
        return None
    return None if a == b else path.rstrip(".")


def nmpc_config(vehicle: str = "paper"):
    """The NMPC's nominal config: the paper preset (1 kHz) flying the named ``vehicle``."""
    cfg = make_config("paper")
    return cfg if vehicle == "paper" else with_vehicle(cfg, vehicle)


def run_vehicle(run: rundir.LoadedRun) -> str:
    """The named vehicle ``run`` flies (``paper`` for a custom one: the NMPC's default)."""
    return vehicle_of(run.env_config.vehicle.quad) or "paper"


def nmpc_file_mismatch(d, num_seeds: int, vehicle: str | None = "paper") -> str | None:
    """Why a saved ``evaluate --controller nmpc --robustness --json`` result ``d`` cannot
    stand for the NMPC here (one line), or ``None`` when it provably can: written by the
    default NMPC (no options) on the paper preset's nominal config (today's) flying ``vehicle``
    (``None``: the named vehicle ``d`` records), its conditions today's by name and
    description, each with Spiral-RT and LOS-RT seeds 1..``num_seeds``."""
    if not isinstance(d, dict) or "robustness" not in d:
        return "it holds no robustness results (write it with evaluate --controller nmpc --robustness --json)"
    if d.get("controller") != "nmpc":
        return f"it was written by controller {d.get('controller')!r}, not the NMPC"
    if d.get("options"):
        return f"its NMPC had options {d['options']}, not the defaults used here"
    if vehicle is None:
        vehicle = d.get("vehicle") or "paper"
        if vehicle not in VEHICLE_NAMES:
            return f"its vehicle {vehicle!r} is not one of {list(VEHICLE_NAMES)}"
    allowed = ("paper", None) if vehicle == "paper" else (vehicle,)
    if d.get("preset") != "paper" or d.get("vehicle") not in allowed or d.get("task_args"):
        return (f"it is for preset {d.get('preset')!r}, vehicle {d.get('vehicle')!r}, task flags "
                f"{d.get('task_args')}, not the paper preset's nominal {vehicle} vehicle")  # fmt: skip
    env = d.get("env_config")
    want = json.loads(json.dumps(json_safe(dataclasses.asdict(nmpc_config(vehicle)))))
    if not isinstance(env, dict):
        return "it does not record its env config"
    where = _first_difference(env, want)
    if where:
        named = "" if vehicle == "paper" else f" ({vehicle} vehicle)"
        return f"its env config differs from the paper preset's{named} in {where}"
    descriptions = d.get("robustness_conditions")
    if not isinstance(descriptions, dict) or set(descriptions) != set(rob.ROBUSTNESS_DESCRIPTIONS):
        have = sorted(descriptions) if isinstance(descriptions, dict) else descriptions
        return f"its conditions {have} are not today's {list(rob.ROBUSTNESS_CONDITIONS)}"
    changed = [c for c in rob.ROBUSTNESS_CONDITIONS if descriptions[c] != rob.ROBUSTNESS_DESCRIPTIONS[c]]
    if changed:
        return f"its condition(s) {changed} are described differently from today's (another perturbation)"
    results = d["robustness"]
    if not isinstance(results, dict) or list(results) != ["nmpc"]:
        have = list(results) if isinstance(results, dict) else results
        return f"its robustness results are for {have}, not nmpc alone"
    per = results["nmpc"]
    if not isinstance(per, dict) or set(per) != set(rob.ROBUSTNESS_CONDITIONS):
        have = sorted(per) if isinstance(per, dict) else per
        return f"its robustness results cover {have}, not every condition"
    want = list(range(1, num_seeds + 1))
    for c in rob.ROBUSTNESS_CONDITIONS:
        try:
            seeds = per[c]["los_rt"]["seeds"]
            per[c]["spiral_rt"]["tracking_error"], per[c]["los_rt"]["tracking_error"]["mean"]  # noqa: B018
        except (KeyError, TypeError):
            return f"its {c} row is incomplete"
        if seeds != want:
            span = f"{seeds[0]}..{seeds[-1]}" if isinstance(seeds, list) and seeds else repr(seeds)
            return f"its LOS-RT seeds are {span}, not 1..{num_seeds} (--robustness-seeds {num_seeds})"
    return None


def read_nmpc_file(path: str, num_seeds: int) -> tuple[dict | None, str | None]:
    """``(its robustness results and the vehicle it flew, None)``, or ``(None, why not)``."""
    try:
        with open(path) as fh:
            d = json.load(fh)
    except OSError as e:
        return None, f"cannot read it ({e.strerror})"
    except (ValueError, UnicodeDecodeError) as e:
        return None, f"it is not valid JSON ({e})"
    why = nmpc_file_mismatch(d, num_seeds, None)
    if why:
        return None, why
    return dict(rows=d["robustness"]["nmpc"], vehicle=d.get("vehicle") or "paper"), None


# --------------------------------------------------------------------------- arguments


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python experiments/robust_table.py", description=__doc__.split("\n\n")[0]
    )
    add = ap.add_argument
    add(
        "robust_run",
        metavar="ROBUST_RUN",
        help="the robust run's directory (python -m ttd3_jax.train --preset robust)",
    )
    add(
        "--fast-run", default=None, help="a fast run's directory: its seeds as columns beside the robust ones"
    )
    add("--nmpc-robustness", default=None, metavar="FILE", help="a saved NMPC robustness result "
        "(evaluate --controller nmpc --robustness --json FILE) instead of computing it "
        "(≈ 1 min per LOS seed)")  # fmt: skip
    add(
        "--robustness-seeds",
        type=int,
        default=20,
        help="LOS-RT seeds 1..N of the robustness rows (default 20)",
    )
    add("--last", action="store_true", help="each seed's last policy (the newest checkpoint) instead of "
        "the one selected on the validation tracks (best/)")  # fmt: skip
    add("--out", default="results/robust", help="output directory (default results/robust)")
    return ap


def reference_preset(spec: sp.RunSpec) -> str:
    """The preset ``spec`` is judged as: ``cf2`` for a firmware vehicle, else ``robust``."""
    return "cf2" if spec.task.vehicle.quad.rate_model == "firmware" else "robust"


def robust_differences(spec: sp.RunSpec) -> list[str]:
    """The fields of its reference preset's task (``spec.ROBUST_TASK``, ``spec.CF2_TASK``) and
    actor update that ``spec`` does not share, by name."""
    task = sp.CF2_TASK if reference_preset(spec) == "cf2" else sp.ROBUST_TASK
    out = [k for k, v in task.items() if spec.task.get(k) != v]
    if spec.train.model_horizon == 0:
        out.append("model_horizon")
    return out


def load(
    ap: argparse.ArgumentParser, flag: str, path: str, last: bool = False
) -> tuple[str, rundir.LoadedRun]:
    try:
        path, note = rundir.find_run(path)
        if note:
            print(note)
        return path, rundir.load_run(path, best=not last)
    except (FileNotFoundError, ValueError) as e:
        ap.error(f"{flag} {path!r}: {str(e).splitlines()[0]}")


def check_args(
    ap: argparse.ArgumentParser, args
) -> tuple[rundir.LoadedRun, rundir.LoadedRun | None, dict | None]:
    """Refuse bad input with one line (exit 2) before anything compiles; returns the runs and
    the saved NMPC robustness (or ``None``: to compute)."""
    if args.robustness_seeds < 1:
        ap.error(f"--robustness-seeds must be >= 1, got {args.robustness_seeds}")
    try:
        writable_dir("--out", args.out)
    except ValueError as e:
        ap.error(str(e))
    saved = None
    if args.nmpc_robustness is not None:
        saved, why = read_nmpc_file(args.nmpc_robustness, args.robustness_seeds)
        if why:
            ap.error(f"--nmpc-robustness {args.nmpc_robustness}: {why}")
    args.robust_run, robust = load(ap, "ROBUST_RUN", args.robust_run, args.last)
    if saved is not None:
        if saved["vehicle"] != run_vehicle(robust):
            ap.error(f"--nmpc-robustness {args.nmpc_robustness}: its NMPC flew the {saved['vehicle']} "
                     f"vehicle, ROBUST_RUN the {run_vehicle(robust)} vehicle")  # fmt: skip
        saved = saved["rows"]
    fast = None
    if args.fast_run is not None:
        args.fast_run, fast = load(ap, "--fast-run", args.fast_run, args.last)
    return robust, fast, saved


# --------------------------------------------------------------------------- evaluation


def evaluate_policies(label: str, run: rundir.LoadedRun, seeds: tuple) -> dict:
    """``{f"{label} seed {s}": {"paper", "suite", "robustness"}}`` for each seed of ``run``:
    one evaluator per config, shared by the seeds (their weights are an argument)."""
    cfg = run.env_config
    out = {f"{label} seed {s}": {"control_hz": 1 / cfg.control_dt} for s, _ in run.thetas}
    ev = Evaluator(TrackingEnv(cfg.for_eval("los_rt")), run.build)
    suite = gen.suite_tracks(SUITE, cfg.dt)
    for s, theta in run.thetas:
        name = f"{label} seed {s}"
        out[name]["paper"] = evaluate_controller(ev, theta, los_seed=0, timing=False)[0]
        out[name]["suite"] = evaluate_tracks(ev, theta, suite, timing=False)[0]
        print(f"{name}: " + ", ".join(f"{t} {m['tracking_error']:.1f}"
                                      for t, m in {**out[name]["paper"], **out[name]["suite"]}.items()),
              flush=True)  # fmt: skip
        out[name]["robustness"] = {}
    keys = rob.condition_keys(len(seeds))
    for c, ccfg in rob.robustness_conditions(cfg).items():
        ev_c = Evaluator(TrackingEnv(ccfg), run.build)
        for s, theta in run.thetas:
            name = f"{label} seed {s}"
            out[name]["robustness"][c] = r = los_statistics(ev_c, theta, seeds, keys)
            progress(name, c, r)
    return out


def progress(name: str, condition: str, r: dict) -> None:
    los = r["los_rt"]
    print(f"[{name}] {condition:>12}: Spiral-RT {r['spiral_rt']['tracking_error']:8.2f}, LOS-RT mean "
          f"{los['tracking_error']['mean']:9.2f} (crashed {los['crashed']}/{len(los['seeds'])})",
          flush=True)  # fmt: skip


def evaluate_nmpc(seeds: tuple, saved: dict | None, vehicle: str = "paper") -> dict:
    """The NMPC (paper preset, 1 kHz, sensed state, flying ``vehicle``): the test tracks and the
    suite, and the robustness rows (``saved``, or computed)."""
    cfg = nmpc_config(vehicle)
    nominal = cfg.for_eval("los_rt")
    build = controller_build("nmpc", nominal)
    ev = Evaluator(TrackingEnv(nominal), build)
    out = dict(control_hz=1 / cfg.control_dt)
    out["paper"] = evaluate_controller(ev, None, los_seed=0, timing=False)[0]
    out["suite"] = evaluate_tracks(ev, None, gen.suite_tracks(SUITE, cfg.dt), timing=False)[0]
    print(
        f"{NMPC}: "
        + ", ".join(f"{t} {m['tracking_error']:.1f}" for t, m in {**out["paper"], **out["suite"]}.items())
    )
    if saved is not None:
        out["robustness"] = saved
    else:
        print(f"{NMPC} robustness at 1 kHz, LOS-RT seeds 1..{len(seeds)} (≈ 1 min per seed on 2 CPU cores)")
        out["robustness"] = rob.evaluate_configs(build, None, rob.robustness_conditions(cfg), seeds,
                                                 progress=lambda c, r: progress(NMPC, c, r))  # fmt: skip
    return out


# --------------------------------------------------------------------------- the table


def rows(results: dict, judged: list[str]) -> list[dict]:
    """The table's rows: ``{"row", "values": {label: (value, crashes)}, "target": verdict}``;
    the seeds ``judged`` (the robust ones) are checked against each row's target."""
    nmpc, out = results[NMPC], []

    def add(row, get, make_verdict, fmt="{:.2f}", count=None):
        vals = {label: get(r) for label, r in results.items()}
        v = make_verdict([vals[j][0] for j in judged], [vals[j][1] for j in judged], vals[NMPC])
        out.append(dict(row=row, values=vals, target=v, fmt=fmt, count=count))

    def vs_nmpc(factor=1.0, note=""):
        return lambda v, c, ref: verdict(
            v, factor * ref[0], crashes=c, ref_crashes=ref[1], ref=ref[0], note=note
        )

    for t in tr.TEST_TRACKS:
        add(f"{TRACK_TITLES[t]} seed 0 Σ‖e‖ [m] (paper T-TD3 {PAPER_TTD3[t]:g})",
            lambda r, t=t: (r["paper"][t]["tracking_error"], r["paper"][t]["crashed"] > 0),
            lambda v, c, ref, t=t: verdict(v, PAPER_TTD3[t], crashes=c, ref=PAPER_TTD3[t],
                                           ref_name="paper"))  # fmt: skip
    for t in gen.DESCRIPTIONS:
        crash = lambda r, t=t: r["suite"][t]["crashed"] > 0  # noqa: E731
        add(
            f"{t} Σ‖e‖ [m]",
            lambda r, t=t, crash=crash: (r["suite"][t]["tracking_error"], crash(r)),
            vs_nmpc(),
        )
        add(f"{t} steady [mm]", lambda r, t=t, crash=crash: (1e3 * r["suite"][t]["steady_error"], crash(r)),
            vs_nmpc(STEADY_FACTOR, f"limit {STEADY_FACTOR:g}×"))  # fmt: skip
        if t == "step":
            add("step overshoot [%]", lambda r, crash=crash: (r["suite"]["step"]["overshoot"], crash(r)),
                lambda v, c, ref: verdict(v, OVERSHOOT_MAX, crashes=c, ref_crashes=ref[1], unit=" %",
                                          note=f"limit {OVERSHOOT_MAX:g} %"), fmt="{:.1f}")  # fmt: skip
    n = len(nmpc["robustness"]["nominal"]["los_rt"]["seeds"])
    for c in rob.ROBUSTNESS_CONDITIONS:
        sp_ = lambda r, c=c: (r["robustness"][c]["spiral_rt"]["tracking_error"],  # noqa: E731
                              r["robustness"][c]["spiral_rt"]["crashed"] > 0)  # fmt: skip
        los = lambda r, c=c: (r["robustness"][c]["los_rt"]["tracking_error"]["mean"],  # noqa: E731
                              r["robustness"][c]["los_rt"]["crashed"])  # fmt: skip
        add(f"{c}: Spiral-RT Σ‖e‖ [m]", sp_, vs_nmpc())
        add(f"{c}: LOS-RT 1..{n} mean Σ‖e‖ [m]", los, vs_nmpc(), count=n)
    return out


def cell(value: float, crashes, fmt: str, count: int | None) -> str:
    text = fmt.format(value) if math.isfinite(value) else fmt_value(value)
    if count is not None:
        return text + (f" ({crashes}/{count} crashed)" if crashes else "")
    return text + (" (crashed)" if crashes else "")


def table(table_rows: list[dict], labels: list[str]) -> list[str]:
    lines = ["| row | " + " | ".join(labels) + " | target |", "| --- |" + " ---: |" * len(labels) + " --- |"]
    for r in table_rows:
        cells = [cell(*r["values"][label], r["fmt"], r["count"]) for label in labels]
        lines.append(f"| {r['row']} | " + " | ".join(cells) + f" | {r['target']['text']} |")
    return lines


def run_note(flag: str, path: str, run: rundir.LoadedRun, robust: bool) -> str:
    name = os.path.basename(os.path.normpath(path))
    seeds = [s for s, _ in run.thetas]
    which = (f"epochs selected on the validation tracks {run.epoch}" if isinstance(run.epoch, dict)
             else f"the last epoch's policies (epoch {run.epoch})")  # fmt: skip
    text = f"{flag}: `{name}` ({run.spec.algo}, seeds {seeds}, {which}, {1 / run.env_config.control_dt:g} Hz)"
    if robust:
        diff = robust_differences(run.spec)
        name = reference_preset(run.spec)
        if diff:
            text += f". **Not the `{name}` preset**: its task differs from `{name}`'s in {', '.join(diff)}"
        if len(seeds) != sp.preset(name).num_seeds:
            text += f". It has {len(seeds)} seed(s), not the {sp.preset(name).num_seeds} the targets ask for"
    return text + "."


def shown_words(argv: list[str]) -> list[str]:
    """``argv`` with the run directories as ``ROBUST_RUN`` and ``FAST_RUN`` (the README's
    command line names no local path)."""
    words, flag = [], None  # flag: the option whose value comes next (every option takes one)
    for w in argv:
        if flag is not None:
            words.append("FAST_RUN" if flag == "--fast-run" else w)
            flag = None
        elif w.startswith("--fast-run="):
            words.append("--fast-run=FAST_RUN")
        elif w.startswith("--"):
            words.append(w)
            flag = None if "=" in w else w
        else:
            words.append("ROBUST_RUN")
    return words


def readme(title: str, command: str, device: str, elapsed: float, notes: list[str], vehicle: str,
           nmpc_source: str, table_rows: list[dict], labels: list[str],
           n_seeds: int) -> list[str]:  # fmt: skip
    """The README's lines: what ran where, the NMPC and the rows, the table, the descriptions."""
    k_all = sum(r["target"]["k"] == r["target"]["n"] for r in table_rows)
    return [
        f"# The {title} policy against its targets (issue 37)", "",
        f"`{command}` on {device}, {datetime.date.today()}, {elapsed / 60:.0f} min.", "",
        *(f"{n}" for n in notes), "",
        f"NMPC: the paper preset's, 1 kHz, sensed state, default options, flying the `{vehicle}` vehicle"
        f"{LOOP_NOTE if vehicle == 'cf2' else ''}; its robustness rows {nmpc_source}. "
        f"Policies at their run's rate. Paper tracks: Spiral-RT and LOS-RT seed 0, nominal. Suite "
        f"(`--suite {SUITE}`): 3 s from rest on p_d(0), steady = mean ‖e‖ after {gen.STEADY_AFTER_S:g} s, "
        "overshoot past the step's target in % of the step. Robustness rows (`ttd3_jax.control.robustness`): "
        "one fixed mismatch each, unknown to every controller, the same reference; Spiral-RT, and LOS-RT "
        f"seeds 1..{n_seeds} (mean). Crash: ‖e‖ > {EVAL_CRASH_M:g} m, one rule for all.", "",
        "Target column: on how many of the robust seeds the row's target is met (Σ‖e‖ ≤ the NMPC's, steady "
        f"≤ {STEADY_FACTOR:g}× the NMPC's, overshoot ≤ {OVERSHOOT_MAX:g} %, paper tracks below the paper's "
        "T-TD3; a seed crashing more often than the NMPC misses), and where missed by how much: the worst "
        f"seed's ratio to the NMPC (or the paper). {k_all} of {len(table_rows)} rows met on every seed.", "",
        *table(table_rows, labels), "",
        *(f"- {k}: {v}" for k, v in gen.DESCRIPTIONS.items()),
        *(f"- {k}: {v}" for k, v in rob.ROBUSTNESS_DESCRIPTIONS.items()),
    ]  # fmt: skip


def main(argv=None) -> int:
    ap = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    robust, fast, saved = check_args(ap, args)
    seeds = tuple(range(1, args.robustness_seeds + 1))
    notes = [run_note("ROBUST_RUN", args.robust_run, robust, True)]
    if fast is not None:
        notes.append(run_note("FAST_RUN", args.fast_run, fast, False))
    for n in notes:
        print(n)
    device = device_description()
    print(f"device={device}")
    t0 = time.perf_counter()
    results = evaluate_policies("robust", robust, seeds)
    judged = list(results)
    if fast is not None:
        results.update(evaluate_policies("fast", fast, seeds))
    vehicle = run_vehicle(robust)
    results[NMPC] = evaluate_nmpc(seeds, saved, vehicle)
    elapsed = time.perf_counter() - t0
    table_rows = rows(results, judged)
    labels = list(results)
    command = "python experiments/robust_table.py " + shlex.join(shown_words(argv))
    nmpc_source = (f"read from `{args.nmpc_robustness}` (checked: the default NMPC on the paper preset "
                   "and this vehicle, today's conditions and seeds)" if saved is not None
                   else "computed here")  # fmt: skip
    title = reference_preset(robust.spec)
    lines = readme(title, command, device, elapsed, notes, vehicle, nmpc_source, table_rows, labels,
                   len(seeds))  # fmt: skip
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "README.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    targets = {
        r["row"]: dict(r["target"], values={k: v[0] for k, v in r["values"].items()},
                       crashes={k: v[1] for k, v in r["values"].items()})
        for r in table_rows
    }  # fmt: skip
    meta = dict(command=command, device=device, date=str(datetime.date.today()), elapsed_s=elapsed,
                robust_run=os.path.basename(os.path.normpath(args.robust_run)), vehicle=vehicle,
                fast_run=os.path.basename(os.path.normpath(args.fast_run)) if args.fast_run else None,
                robust_differences=robust_differences(robust.spec), judged=judged, los_seeds=list(seeds),
                nmpc_robustness=args.nmpc_robustness, paper_ttd3=PAPER_TTD3, steady_factor=STEADY_FACTOR,
                overshoot_max=OVERSHOOT_MAX, crash_threshold_m=EVAL_CRASH_M, suite=gen.DESCRIPTIONS,
                robustness_conditions=rob.ROBUSTNESS_DESCRIPTIONS)  # fmt: skip
    with open(os.path.join(args.out, "robust_table.json"), "w") as fh:
        json.dump(json_safe(dict(meta, targets=targets, results=results)), fh, indent=2)
    print("\n".join(table(table_rows, labels)))
    print(f"wrote {args.out}/README.md and robust_table.json ({elapsed:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
