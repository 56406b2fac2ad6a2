"""The ``paper`` preset at the paper's budget (issue 35 item 2): T-TD3 as published (1 kHz
control, 256-256 networks, 20 envs, UTD 1), 3 seeds to 1e6 transitions and seed 0 on to 3e6,
evaluated every 100k transitions on Spiral-RT, LOS-RT and the validation tracks.

The runs are the CLI's own (``python -m ttd3_jax.train --preset paper ...``, resumable with
``--resume``; ``results/paper_budget/commands.txt`` holds the exact commands).  This script
only reads their run directories and writes ``results/paper_budget/``: ``table.md`` (each
seed's last evaluation and its validation-selected policy against the paper's T-TD3 and our
NMPC, with transitions, wall time and machine), ``curves.csv`` and ``curves.png`` (Σ‖e‖
against transitions).  A run without ``eval.json`` is reported "unfinished at N transitions".

    python experiments/paper_budget.py RUN_DIR [RUN_DIR ...] [--out results/paper_budget]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

import numpy as np

from ttd3_jax.control.paper import PAPER_TTD3
from ttd3_jax.run import rundir

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "results", "paper_budget")
NMPC_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "results", "paper_tables.json")
KEYS = ("spiral_tracking_error", "los_tracking_error", "val_tracking_error")


def nmpc_row() -> dict:
    """Our NMPC on the two test tracks, from results/paper_tables.json (experiments/paper_tables.py)."""
    with open(NMPC_SOURCE) as fh:
        tracks = json.load(fh)["results"]["NMPC"]["tracks"]
    return {"spiral_tracking_error": tracks["spiral_rt"]["tracking_error"],
            "los_tracking_error": tracks["los_rt"]["tracking_error"]}  # fmt: skip


def selected_epochs(run_dir: str, metrics: list[dict]) -> dict[int, dict]:
    """Per seed, the policy selected on the validation tracks: a finished run's ``eval.json``
    records it; for an unfinished one (whose ``best/`` is not committed) it is the trainer's
    rule applied to metrics.csv: the lowest finite validation error, the earlier epoch on a tie."""
    path = os.path.join(run_dir, "eval.json")
    if os.path.exists(path):
        with open(path) as fh:
            recorded = json.load(fh).get("selected")
        if recorded:
            return {int(s["seed"]): s for s in recorded}
    out = {}
    for r in metrics:  # in epoch order, as the trainer met them
        if rundir.improves_selection(out, int(r["seed"]), r["val_tracking_error"]):
            out[int(r["seed"])] = dict(r, epoch=int(r["epoch"]))
    return out


def episode_lengths(rows: list[dict], warmup: int) -> list[float]:
    """Mean training-episode length (env steps) per epoch: the epoch's transitions (after the
    ``warmup`` random ones) over the episodes that ended in it (crash or truncation): how long
    the policy survives on the training tracks."""
    steps = np.diff([float(warmup)] + [float(r["env_steps"]) for r in rows])
    return [
        s / e if (e := float(r["episodes"])) > 0 else float("nan") for s, r in zip(steps, rows, strict=True)
    ]


def run_rows(run_dir: str) -> list[dict]:
    """One row per seed: its curve, last evaluation, selected policy, budget and state."""
    spec = rundir.load_spec(run_dir)
    metrics = rundir.read_metrics(run_dir)
    finished = os.path.exists(os.path.join(run_dir, "eval.json"))
    selected = selected_epochs(run_dir, metrics)
    out = []
    for seed in range(spec.seed, spec.seed + spec.num_seeds):
        rows = [r for r in metrics if int(r["seed"]) == seed]
        if not rows:
            continue
        last = rows[-1]
        out.append(dict(
            run=os.path.basename(os.path.normpath(run_dir)), seed=seed, budget=spec.train.total_transitions,
            transitions=int(last["env_steps"]), wall_s=float(sum(r["wall_s"] for r in rows)),
            finished=finished, last={k: last[k] for k in KEYS},
            curve=[(int(r["env_steps"]), *(r[k] for k in KEYS)) for r in rows],
            mean_episode=episode_lengths(rows, spec.train.warmup_steps * spec.train.num_envs),
            selected=selected.get(seed),
        ))  # fmt: skip
    return out


def fmt(x: float) -> str:
    return f"{x:.2f}" if np.isfinite(x) else "nan"


def table(rows: list[dict], nmpc: dict, machine: str) -> str:
    lines = [
        "# `paper` preset at the paper's budget (T-TD3 as published)",
        "",
        f"Machine: {machine}. Written by `python experiments/paper_budget.py` from the run directories; "
        "commands in `commands.txt`. Σ‖e‖ (m, summed over 3000 physics steps); lower is better. "
        "Training episode: the mean length of the training episodes that ended in an epoch (the env's "
        "`episode_steps` at most; shorter ones crashed).",
        "",
        "| run | seed | state | transitions | wall h | Spiral-RT (last) | LOS-RT (last) | val (last) "
        "| selected epoch | Spiral-RT (selected) | LOS-RT (selected) "
        "| training episode, first → last epoch |",
        "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        state = "finished" if r["finished"] else f"unfinished at {r['transitions']:,} of {r['budget']:,}"
        sel = r["selected"] or {}
        lines.append(
            f"| {r['run']} | {r['seed']} | {state} | {r['transitions']:,} | {r['wall_s'] / 3600:.2f} "
            f"| {fmt(r['last']['spiral_tracking_error'])} | {fmt(r['last']['los_tracking_error'])} "
            f"| {fmt(r['last']['val_tracking_error'])} | {sel.get('epoch', '-')} "
            f"| {fmt(sel.get('spiral_tracking_error', np.nan))} "
            f"| {fmt(sel.get('los_tracking_error', np.nan))} "
            f"| {r['mean_episode'][0]:.0f} → {r['mean_episode'][-1]:.0f} steps |"
        )
    lines += [
        f"| paper's T-TD3 | | | 3,000,000 (spec A8) | | {PAPER_TTD3['spiral_tracking_error']} "
        f"| {PAPER_TTD3['los_tracking_error']} | | | | | |",
        f"| our NMPC | | | | | {fmt(nmpc['spiral_tracking_error'])} "
        f"| {fmt(nmpc['los_tracking_error'])} | | | | | |",
        "",
    ]
    return "\n".join(lines)


def write_curves(rows: list[dict], nmpc: dict, out: str) -> None:
    with open(os.path.join(out, "curves.csv"), "w") as fh:
        fh.write("run,seed,transitions," + ",".join(KEYS) + ",training_episode_steps\n")
        for r in rows:
            for c, n in zip(r["curve"], r["mean_episode"], strict=True):
                fh.write(f"{r['run']},{r['seed']},{c[0]}," + ",".join(f"{v:.6g}" for v in (*c[1:], n)) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4), constrained_layout=True)
    for ax, i, name, key in ((axes[0], 1, "Spiral-RT", KEYS[0]), (axes[1], 2, "LOS-RT", KEYS[1])):
        for r in rows:
            xs = [c[0] for c in r["curve"]]
            ax.plot(xs, [c[i] for c in r["curve"]], marker=".", label=f"seed {r['seed']} ({r['run'][-15:]})")
        ax.axhline(PAPER_TTD3[key], color="k", ls="--", label="paper's T-TD3")
        ax.axhline(nmpc[key], color="g", ls=":", label="our NMPC")
        ax.set(yscale="log", xlabel="transitions per seed", ylabel="Σ‖e‖ (m)", title=name)
        ax.grid(alpha=0.3)
    for r in rows:
        axes[2].plot([c[0] for c in r["curve"]], r["mean_episode"], marker=".")
    axes[2].set(
        xlabel="transitions per seed",
        ylabel="env steps (an episode ends at the latest at 3000)",
        title="mean training episode (crash or end)",
    )
    axes[2].grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.savefig(os.path.join(out, "curves.png"), dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python experiments/paper_budget.py", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("run_dirs", nargs="+", help="paper-preset run directories")
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--machine", default=f"{platform.machine()} CPU, {os.cpu_count()} cores")
    a = ap.parse_args(argv)
    missing = [d for d in a.run_dirs if not os.path.isfile(os.path.join(d, "config.json"))]
    if missing:
        print(f"error: not a run directory (no config.json): {missing[0]}", file=sys.stderr)
        return 2
    rows = [r for d in a.run_dirs for r in run_rows(d)]
    os.makedirs(a.out, exist_ok=True)
    nmpc = nmpc_row()
    with open(os.path.join(a.out, "table.md"), "w") as fh:
        fh.write(table(rows, nmpc, a.machine))
    write_curves(rows, nmpc, a.out)
    print(table(rows, nmpc, a.machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())
