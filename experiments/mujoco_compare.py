"""T-TD3 vs TD3 on the Brax/MJX MuJoCo tasks (spec §2.7): the paper's second figure.

For each task and algorithm one run trains all seeds side by side (``vmap``: one compiled
program per task and algorithm) and evaluates every ``--eval-every`` env steps over
``--eval-episodes`` deterministic episodes.  Writes to ``--out`` (default
``results/mujoco``):

* ``runs/<task>-<algo>/...``  the run directories (config, metrics.csv, checkpoints);
* ``evals.csv``   task, algo, seed, step, eval_return: one row per evaluation and seed;
* ``summary.csv`` / ``summary.md``  final return (mean ± std over seeds), area under the
  curve (mean return over the evaluations) and steps to 80 % of TD3's final return;
* ``curves.png``  2×2 learning curves, mean ± ½ std over seeds, as in the paper;
* ``README.md``   the command, budget, device and whether this is the paper's protocol.

Resumable per task: a finished task/algorithm (its ``eval.json`` exists) is skipped, an
interrupted one continues from its last checkpoint.

    python experiments/mujoco_compare.py                      # the protocol: 1M steps, 3 seeds
    python experiments/mujoco_compare.py --steps 100000 --tasks hopper inverted_double_pendulum
    python experiments/mujoco_compare.py --parallel 8         # one process per task x algo (GPU)

The protocol (spec §2.7) is 1 env and 1 update per env step; ``--num-envs K`` steps K
envs per vector step with K updates each (the same update-to-data ratio, fewer
sequential steps).  Anything other than 1M steps with 1 env is labelled a reduced run.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import glob
import math
import os
import shlex
import subprocess
import sys
import time

import numpy as np

TASKS = ("ant", "walker2d", "inverted_double_pendulum", "hopper")  # the paper figure's order
ALGOS = ("ttd3", "td3")
LABEL = {"ttd3": "T-TD3", "td3": "TD3"}
PROTOCOL_STEPS = 1_000_000
# the paper's reading of its figure (spec §2.7): T-TD3 converges faster on these three,
# and is slightly worse on Hopper
PAPER_CLAIM = {
    "ant": "T-TD3 faster",
    "walker2d": "T-TD3 faster",
    "inverted_double_pendulum": "T-TD3 faster",
    "hopper": "T-TD3 slightly worse",
}


# --------------------------------------------------------------------------- configs


def task_config(task: str, algo: str, a: argparse.Namespace):
    """The RunSpec of one task and algorithm (the ``mujoco`` preset, resized)."""
    import dataclasses

    from ttd3_jax.run import spec as sp

    if a.eval_every % a.num_envs:
        raise ValueError(f"--eval-every ({a.eval_every}) must be a multiple of --num-envs ({a.num_envs})")
    epochs = (a.steps - a.warmup) // a.eval_every
    if epochs < 1:
        raise ValueError(
            f"--steps ({a.steps}) must leave at least one evaluation interval (--eval-every "
            f"{a.eval_every}) after the warm-up (--warmup {a.warmup})"
        )
    s = sp.preset(
        "mujoco",
        env=task,
        algo=algo,
        num_envs=a.num_envs,
        updates_per_step=a.updates_per_step or a.num_envs,
        total_transitions=a.warmup + epochs * a.eval_every,
        warmup_transitions=a.warmup,
        buffer_size=min(1_000_000, a.warmup + epochs * a.eval_every),
        epochs=epochs,
        seed=a.seed,
        num_seeds=a.seeds,
    )
    return sp.replace(s, brax=dataclasses.replace(s.brax, backend=a.backend, eval_episodes=a.eval_episodes))


def run_dir_of(out: str, task: str, algo: str) -> str | None:
    found = sorted(glob.glob(os.path.join(out, "runs", f"{task}-{algo}", "*", "config.json")))
    return os.path.dirname(found[-1]) if found else None


def run_one(task: str, algo: str, a: argparse.Namespace) -> None:
    """Train one task/algorithm (all seeds in one program), resuming if it was interrupted."""
    from ttd3_jax.cli.console import show_messages
    from ttd3_jax.run.loop import run

    show_messages()  # the runner's log, as plain lines
    c = task_config(task, algo, a)
    d = run_dir_of(a.out, task, algo)
    if d is not None and os.path.exists(os.path.join(d, "eval.json")):
        print(f"[{task} {algo}] done already: {d}", flush=True)
        return
    t0 = time.perf_counter()
    if (
        d is not None
        and os.path.isdir(os.path.join(d, "checkpoints"))
        and os.listdir(os.path.join(d, "checkpoints"))
    ):
        print(f"[{task} {algo}] resuming {d}", flush=True)
        res = run(resume=d, checkpoint_every=a.checkpoint_every)
    else:
        res = run(c, out=os.path.join(a.out, "runs", f"{task}-{algo}"), checkpoint_every=a.checkpoint_every)
    print(f"[{task} {algo}] finished in {time.perf_counter() - t0:.0f} s: {res['run_dir']}", flush=True)


# --------------------------------------------------------------------------- results


def collect_evals(out: str) -> list[dict]:
    """Rows (task, algo, seed, step, eval_return) from every run directory under ``out``."""
    from ttd3_jax.run.rundir import read_metrics

    rows = []
    for task in TASKS:
        for algo in ALGOS:
            d = run_dir_of(out, task, algo)
            if d is None or not os.path.exists(os.path.join(d, "metrics.csv")):
                continue
            for r in read_metrics(d):
                rows.append(
                    dict(
                        task=task,
                        algo=algo,
                        seed=int(float(r["seed"])),
                        step=int(float(r["env_steps"])),
                        eval_return=float(r["eval_return"]),
                    )
                )
    return rows


def write_evals(rows: list[dict], out: str) -> str:
    path = os.path.join(out, "evals.csv")
    tmp = f"{path}.{os.getpid()}.tmp"  # one per process: two workers once raced on one name
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["task", "algo", "seed", "step", "eval_return"])
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)  # atomic: parallel workers may rewrite it
    return path


def load_evals(out: str) -> list[dict]:
    """Read ``<out>/evals.csv`` back into rows with typed values."""
    with open(os.path.join(out, "evals.csv"), newline="") as fh:
        return [
            dict(
                task=r["task"],
                algo=r["algo"],
                seed=int(r["seed"]),
                step=int(r["step"]),
                eval_return=float(r["eval_return"]),
            )
            for r in csv.DictReader(fh)
        ]


def curve(rows: list[dict], task: str, algo: str) -> tuple[np.ndarray, np.ndarray]:
    """``(steps (E,), returns (S, E))``: the evaluations common to all seeds of a task/algo."""
    sel = [r for r in rows if r["task"] == task and r["algo"] == algo]
    seeds = sorted({r["seed"] for r in sel})
    by_seed = {s: {r["step"]: r["eval_return"] for r in sel if r["seed"] == s} for s in seeds}
    steps = sorted(set.intersection(*(set(v) for v in by_seed.values()))) if seeds else []
    return np.array(steps, dtype=np.int64), np.array([[by_seed[s][t] for t in steps] for s in seeds])


def steps_to(steps: np.ndarray, mean: np.ndarray, level: float) -> float:
    """First evaluation step at which the seed-mean return reaches ``level`` (nan: never)."""
    hit = np.nonzero(mean >= level)[0]
    return float(steps[hit[0]]) if hit.size else math.nan


def auc(steps: np.ndarray, mean: np.ndarray) -> float:
    """Area under the seed-mean curve per env step (trapezoids), i.e. its average height."""
    if len(steps) < 2:
        return float(mean[0])
    area = np.sum((mean[1:] + mean[:-1]) / 2 * np.diff(steps))
    return float(area / (steps[-1] - steps[0]))


def level_80(td3_final: float) -> float:
    """80 % of TD3's final mean return, the level "steps to" is read at (nan unless > 0)."""
    return 0.8 * td3_final if td3_final > 0 else math.nan


def paired(rows: list[dict], task: str) -> dict | None:
    """T-TD3 against TD3, seed by seed (seed i of both starts from the same key), on the
    evaluations both have: final return, AUC and the steps each seed's curve takes to reach
    80 % of TD3's final mean return (nan: never), each with the mean difference T-TD3 − TD3,
    the number of seeds where T-TD3 is better (higher return, fewer steps) and a two-sided
    paired t-test's p (nan below 2 seeds or where a seed never reached the level)."""
    from scipy import stats

    (st, rt), (sd, rd) = curve(rows, task, "ttd3"), curve(rows, task, "td3")
    common = np.intersect1d(st, sd)
    n = min(rt.shape[0], rd.shape[0]) if rt.size and rd.size else 0
    if n == 0 or common.size == 0:
        return None
    rt, rd = rt[:n, np.isin(st, common)], rd[:n, np.isin(sd, common)]
    level = level_80(float(np.mean(rd[:, -1])))
    res = {"seeds": n, "step": int(common[-1]), "level": level}
    for name, a, b, sign in (
        ("final", rt[:, -1], rd[:, -1], 1),
        ("auc", [auc(common, x) for x in rt], [auc(common, x) for x in rd], 1),
        ("steps80", [steps_to(common, x, level) for x in rt], [steps_to(common, x, level) for x in rd], -1),
    ):
        a, b = np.asarray(a, float), np.asarray(b, float)
        ok = np.all(np.isfinite(a) & np.isfinite(b))
        p = float(stats.ttest_rel(a, b).pvalue) if n >= 2 and ok and np.any(a != b) else math.nan
        diff = float(np.mean(a - b)) if ok else math.nan
        res.update({f"{name}_diff": diff, f"{name}_wins": int(np.sum(sign * (a - b) > 0)), f"{name}_p": p})
    return res


def summarize(rows: list[dict]) -> list[dict]:
    """Per task and algorithm: final return (mean, std over seeds), AUC (the mean return over
    all evaluations, i.e. the area under the curve per step) and the first step at which
    the seed-mean curve reaches 80 % of TD3's final mean return."""
    out = []
    for task in TASKS:
        curves = {algo: curve(rows, task, algo) for algo in ALGOS}
        td3_steps, td3_ret = curves["td3"]
        td3_final = float(np.mean(td3_ret[:, -1])) if td3_ret.size else math.nan
        level = level_80(td3_final)
        for algo in ALGOS:
            steps, ret = curves[algo]
            if not steps.size:
                continue
            mean = ret.mean(axis=0)
            out.append(
                dict(
                    task=task,
                    algo=algo,
                    seeds=ret.shape[0],
                    last_step=int(steps[-1]),
                    evals=len(steps),
                    final_mean=float(mean[-1]),
                    final_std=float(ret[:, -1].std()),
                    auc=auc(steps, mean),
                    steps_to_80pct_td3=steps_to(steps, mean, level) if not math.isnan(level) else math.nan,
                )
            )
    return out


def write_summary(summary: list[dict], out: str) -> None:
    if not summary:
        return
    with open(os.path.join(out, "summary.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(summary[0]))
        w.writeheader()
        w.writerows(summary)
    with open(os.path.join(out, "summary.md"), "w") as fh:
        fh.write(summary_markdown(summary))


def summary_markdown(summary: list[dict]) -> str:
    def f(x, fmt="{:.1f}"):
        return "–" if isinstance(x, float) and math.isnan(x) else fmt.format(x)

    lines = [
        "| task | algo | seeds | steps | final return (mean ± std) | AUC (mean return) "
        "| steps to 80 % of TD3 final |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for s in summary:
        lines.append(
            f"| {s['task']} | {LABEL[s['algo']]} | {s['seeds']} | {s['last_step']} | "
            f"{f(s['final_mean'])} ± {f(s['final_std'])} | {f(s['auc'])} | "
            f"{f(s['steps_to_80pct_td3'], '{:.0f}')} |"
        )
    return "\n".join(lines) + "\n"


def plot_curves(rows: list[dict], path: str, title: str | None = None) -> str:
    """The 2×2 figure: eval return vs env steps, mean ± ½ std over seeds per algorithm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for ax, task in zip(axes.flat, TASKS, strict=True):
        for algo, color in (("ttd3", "tab:red"), ("td3", "tab:blue")):
            steps, ret = curve(rows, task, algo)
            if not steps.size:
                continue
            m, sd = ret.mean(axis=0), ret.std(axis=0)
            ax.plot(steps, m, color=color, label=f"{LABEL[algo]} ({ret.shape[0]} seeds)")
            ax.fill_between(steps, m - sd / 2, m + sd / 2, color=color, alpha=0.2)
        ax.set_title(task)
        ax.set_xlabel("env steps")
        ax.set_ylabel("eval return")
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def reading(summary: list[dict], rows: list[dict] | None = None) -> list[str]:
    """One line per task: which algorithm is ahead (with ``rows``, the evaluations: a paired
    test over seeds), beside the paper's claim."""
    lines = []
    for task in TASKS:
        s = {r["algo"]: r for r in summary if r["task"] == task}
        if set(s) != set(ALGOS):
            continue
        t, d = s["ttd3"], s["td3"]
        pooled = math.sqrt((t["final_std"] ** 2 + d["final_std"] ** 2) / 2) or 1.0
        gap = (t["final_mean"] - d["final_mean"]) / pooled
        ahead = "T-TD3" if t["auc"] > d["auc"] else "TD3"
        pr = paired(rows, task) if rows is not None else None
        test = ""
        if pr:
            n = pr["seeds"]
            sooner = (
                "not reached by every seed"
                if math.isnan(pr["steps80_diff"])
                else f"{pr['steps80_diff']:+.0f} (T-TD3 sooner in {pr['steps80_wins']}/{n}, "
                f"p = {pr['steps80_p']:.2f})"
            )
            test = (
                f" Paired over {n} seeds: final {pr['final_diff']:+.1f} (T-TD3 ahead in "
                f"{pr['final_wins']}/{n}, p = {pr['final_p']:.2f}), AUC {pr['auc_diff']:+.1f} "
                f"({pr['auc_wins']}/{n}, p = {pr['auc_p']:.2f}), steps to 80 % of TD3's final {sooner}."
            )
        lines.append(
            f"- {task}: AUC T-TD3 {t['auc']:.1f} vs TD3 {d['auc']:.1f} ({ahead} ahead over the run); final "
            f"{t['final_mean']:.1f} vs {d['final_mean']:.1f} ({gap:+.1f} pooled std).{test} "
            f"Paper: {PAPER_CLAIM[task]}."
        )
    return lines


def budgets(out: str) -> list[dict]:
    """Per task and algorithm, the budget its run was trained with (from its config.json),
    and whether that is the paper's protocol (spec §2.7: 1M steps, 1 env, 1 update per
    step, 25k warm-up, evaluation every 5000 steps over 10 episodes, 3 seeds)."""
    from ttd3_jax.run.rundir import load_spec

    rows = []
    for task in TASKS:
        for algo in ALGOS:
            d = run_dir_of(out, task, algo)
            if d is None:
                continue
            s = load_spec(d)
            c = s.train
            b = dict(
                task=task,
                algo=algo,
                steps=c.transitions_run,
                seeds=s.num_seeds,
                num_envs=c.num_envs,
                updates_per_step=c.updates_per_step,
                warmup=c.warmup_transitions,
                eval_every=c.steps_per_epoch * c.num_envs,
                eval_episodes=s.brax.eval_episodes,
                backend=s.brax.backend,
                finished=os.path.exists(os.path.join(d, "eval.json")),
            )
            b["protocol"] = b["steps"] >= PROTOCOL_STEPS and protocol_settings(b)
            rows.append(b)
    return rows


def protocol_settings(b: dict) -> bool:
    """Whether a budget row has the protocol's settings apart from its steps: 1 env, 1
    update per step, a 25k warm-up, an evaluation every 5000 steps over 10 episodes, 3+ seeds."""
    return (
        b["num_envs"] == 1 and b["updates_per_step"] == 1 and b["warmup"] == 25_000
        and b["eval_every"] == 5000 and b["eval_episodes"] == 10 and b["seeds"] >= 3
    )  # fmt: skip


def protocol_label(b: dict) -> str:
    """``yes``; ``**no: 30 % of its steps**`` when only the steps fall short; else
    ``**no: reduced**``."""
    if b["protocol"]:
        return "yes"
    if protocol_settings(b):
        return f"**no: {100 * b['steps'] / PROTOCOL_STEPS:.0f} % of its steps**"
    return "**no: reduced**"


def budget_markdown(rows: list[dict]) -> str:
    lines = [
        "| task | algo | env steps per seed | seeds | envs x updates per vector step | warm-up "
        "| eval every (episodes) | backend | finished | paper's protocol |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | --- | --- |",
    ]
    for b in rows:
        lines.append(
            f"| {b['task']} | {LABEL[b['algo']]} | {b['steps']} | {b['seeds']} | "
            f"{b['num_envs']} x {b['updates_per_step']} | {b['warmup']} | {b['eval_every']} "
            f"({b['eval_episodes']}) | {b['backend']} | {'yes' if b['finished'] else 'no'} | "
            f"{protocol_label(b)} |"
        )
    return "\n".join(lines) + "\n"


def write_readme(a: argparse.Namespace, summary: list[dict], wall_s: float, rows_e: list[dict]) -> None:
    """README.md of ``a.out``: each task's budget (read from its run, so invocations with
    different budgets into one folder are described correctly), the device, the last
    command, the summary and a generated reading."""
    rows = budgets(a.out)
    reduced = not rows or not all(b["protocol"] for b in rows)
    readme = os.path.join(a.out, "README.md")
    log = os.path.join(a.out, "commands.txt")
    if not a.report_only:
        with open(log, "a") as fh:  # every invocation that trained, in order
            fh.write(f"{datetime.date.today().isoformat()}  {a.command}\n")
    commands = open(log).read().strip().splitlines() if os.path.exists(log) else [a.command]
    with open(readme, "w") as fh:
        fh.write("# T-TD3 vs TD3 on Brax/MJX MuJoCo tasks\n\n")
        fh.write(
            "**Reduced runs, not the paper's protocol.** "
            if reduced
            else "All runs follow the paper's protocol. "
        )
        fh.write(
            "The protocol (spec §2.7) is 1M env steps per seed, 1 env, 1 update per step, a 25k "
            "warm-up and an evaluation every 5000 steps over 10 deterministic episodes. "
            "Each run's own budget:\n\n"
        )
        fh.write(budget_markdown(rows) + "\n")
        note = f" ({a.device_note})" if a.device_note else ""
        fh.write(f"- device: {jax_device()}{note}\n")
        fh.write("- commands (each trains the tasks it names; finished tasks are skipped):\n")
        notes = [line for line in commands if line.lstrip().startswith("#")]
        for line in commands:
            if line.strip() and line not in notes:
                date, _, cmd = line.partition("  ")
                fh.write(f"  - {date}: `{cmd.strip()}`\n")
        if notes:
            lines = f"{len(notes)} line" + ("s" if len(notes) != 1 else "")
            fh.write(f"- [commands.txt](commands.txt) also holds {lines} of notes (`#`): where the runs "
                     "ran and how they were resumed\n")  # fmt: skip
        if not a.report_only:
            fh.write(f"- wall time of the last invocation: {wall_s:.0f} s\n")
        fh.write("\n")
        fh.write("Curves: `curves.png` (mean ± ½ std over seeds). Every evaluation: `evals.csv`.\n\n")
        fh.write(summary_markdown(summary))
        fh.write("\nReading (generated; AUC is the mean return over all evaluations):\n\n")
        fh.write("\n".join(reading(summary, rows_e)) + "\n")


def jax_device() -> str:
    import jax

    d = jax.devices()[0]  # "cpu", or e.g. "gpu NVIDIA H100 80GB HBM3"
    return d.platform if d.device_kind == d.platform else f"{d.platform} {d.device_kind}"


def report(a: argparse.Namespace, wall_s: float) -> list[dict]:
    rows = collect_evals(a.out)
    if not rows:
        print("no evaluations yet")
        return []
    write_evals(rows, a.out)
    summary = summarize(rows)
    write_summary(summary, a.out)
    budget = budgets(a.out)
    protocol = bool(budget) and all(b["protocol"] for b in budget)
    seeds = sorted({b["seeds"] for b in budget})
    title = (
        f"{'paper protocol' if protocol else 'reduced budget (README.md)'}, "
        f"{'/'.join(map(str, seeds))} seeds, {a.backend}, {jax_device()}"
    )
    plot_curves(rows, os.path.join(a.out, "curves.png"), title=title)
    write_readme(a, summary, wall_s, rows)
    print(summary_markdown(summary))
    print("\n".join(reading(summary, rows)))
    return summary


# --------------------------------------------------------------------------- CLI


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    p.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    p.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    p.add_argument("--seeds", type=int, default=3, help="seeds per task and algorithm, vmapped (default 3)")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--steps", type=int, default=PROTOCOL_STEPS, help="env steps per seed (default 1e6)")
    p.add_argument("--warmup", type=int, default=25_000, help="random-action steps first (default 25000)")
    p.add_argument("--eval-every", type=int, default=5000, help="env steps between evaluations")
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--num-envs", type=int, default=1, help="parallel envs per seed (protocol: 1)")
    p.add_argument(
        "--updates-per-step", type=int, default=None, help="default: --num-envs (1 update per env step)"
    )
    p.add_argument("--backend", default="mjx")
    p.add_argument("--checkpoint-every", type=int, default=20, help="evaluations between checkpoints")
    p.add_argument("--parallel", type=int, default=1, help="processes at once, one per task x algo")
    p.add_argument("--device-note", default="", help="free text about the machine, for README.md")
    p.add_argument("--out", default="results/mujoco")
    p.add_argument("--report-only", action="store_true", help="only rebuild evals.csv, summary, figure")
    p.add_argument(
        "--compile-cache",
        default=None,
        help="XLA compilation cache directory, or 'none' (default ~/.cache/ttd3_jax/xla): a resume "
        "loads the compiled programs instead of compiling them again",
    )
    a = p.parse_args(argv)
    for name in ("seeds", "steps", "eval_every", "eval_episodes", "num_envs", "checkpoint_every", "parallel"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if a.warmup < 256:
        p.error(f"--warmup must be >= 256 (the batch size), got {a.warmup}")
    a.command = "python experiments/mujoco_compare.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    return a


def main(argv: list[str] | None = None) -> int:
    a = parse(argv)
    t0 = time.perf_counter()
    jobs = [(t, al) for t in a.tasks for al in a.algos]
    if not a.report_only:
        for t, al in jobs:  # every config error before anything is compiled
            task_config(t, al, a)
        os.makedirs(a.out, exist_ok=True)
        from ttd3_jax.run.cache import use_compile_cache

        use_compile_cache(a.compile_cache)
        if a.parallel > 1 and len(jobs) > 1:
            run_parallel(jobs, a, argv)
        else:
            for t, al in jobs:
                run_one(t, al, a)
    report(a, time.perf_counter() - t0)
    return 0


def run_parallel(jobs, a: argparse.Namespace, argv) -> None:
    """One subprocess per task x algo, ``--parallel`` at a time, sharing the device(s)."""
    base = list(sys.argv[1:] if argv is None else argv)
    drop = {"--tasks", "--algos", "--parallel"}
    kept, skip = [], False
    for x in base:
        if x in drop:
            skip = True
            continue
        if skip and x.startswith("--"):
            skip = False
        if not skip:
            kept.append(x)
    env = dict(os.environ)
    env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{0.9 / min(a.parallel, len(jobs)):.3f}")
    pending, live = list(jobs), []
    os.makedirs(os.path.join(a.out, "logs"), exist_ok=True)
    while pending or live:
        while pending and len(live) < a.parallel:
            t, al = pending.pop(0)
            log = open(os.path.join(a.out, "logs", f"{t}-{al}.log"), "a")
            cmd = [
                sys.executable,
                os.path.abspath(__file__),
                *kept,
                "--tasks",
                t,
                "--algos",
                al,
                "--parallel",
                "1",
            ]
            live.append(((t, al), subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log))
            print(f"started {t} {al}", flush=True)
        time.sleep(2.0)
        for item in list(live):
            (t, al), proc, log = item
            if proc.poll() is not None:
                log.close()
                live.remove(item)
                print(f"{t} {al}: exit {proc.returncode} (log {a.out}/logs/{t}-{al}.log)", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    raise SystemExit(main())
