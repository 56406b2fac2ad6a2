"""What people read and look at: result tables, trace CSVs and plots (matplotlib, imported
on first use with the ``Agg`` backend).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading

import jax
import numpy as np

from ttd3_jax.control.evaluator import Trace
from ttd3_jax.control.paper import PAPER, PAPER_TTD3
from ttd3_jax.sim.dynamics import yaw_of

TRACK_TITLES = {"spiral_rt": "Spiral-RT", "los_rt": "LOS-RT"}


def track_names(traces: dict[str, dict]) -> list[str]:
    """The tracks of ``{label: {track: ...}}`` in order of first appearance."""
    return list(dict.fromkeys(t for v in traces.values() for t in v))


def plot_traces(traces: dict[str, dict[str, Trace]], out_dir: str, *, title: str = "", los_seed: int = 0,
                prefix: str = "", e_show: float = 2.0, action_note: str = "") -> list[str]:  # fmt: skip
    """Per track: ``{prefix}{track}_3d.png`` (reference and flown paths),
    ``{prefix}{track}_error.png`` (‖e‖ vs time) and ``{prefix}{track}_actions.png`` (the four
    applied normalised actions and ‖a‖ vs time).  ``traces`` maps a label (controller, seed)
    to ``{track: Trace}``.  The 3-D plot shows each flown path until its error first
    exceeds ``e_show`` m; ``action_note`` is appended to the action plot's title."""
    plt = _pyplot()
    os.makedirs(out_dir, exist_ok=True)
    tracks = track_names(traces)
    paths = []
    for track in tracks:
        runs = {label: v[track] for label, v in traces.items() if track in v}
        name = TRACK_TITLES.get(track, track) + (f" seed {los_seed}" if track == "los_rt" else "")
        finest = max(runs.values(), key=lambda x: x.t.size)
        suffix = f" ({title})" if title else ""

        fig = plt.figure(figsize=(7, 6))
        ax = fig.add_subplot(projection="3d")
        ax.plot(*finest.ref.T, "k--", lw=1.5, label="reference")
        for label, x in runs.items():
            # the flown path until the error first exceeds e_show (a path that flies off would
            # set the axes' scale for everyone)
            off = np.flatnonzero(~(x.error <= e_show))
            n = off[0] if off.size else x.t.size
            if off.size:
                label = f"{label} (> {e_show:g} m off at {x.t[n]:.2f} s)"
            ax.plot(*x.pos[:n].T, lw=1.2, label=label)
        ax.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]", title=f"{name}: reference vs flown{suffix}")
        ax.legend(fontsize=8)
        paths.append(_save(fig, os.path.join(out_dir, f"{prefix}{track}_3d.png")))

        fig, ax = plt.subplots(figsize=(7, 3.5))
        for label, x in runs.items():
            ax.plot(x.t, x.error, lw=1.2, label=label)
        ax.set(yscale="log", xlabel="t [s]", ylabel="‖p_d − p‖ [m]", title=f"{name}: tracking error{suffix}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        paths.append(_save(fig, os.path.join(out_dir, f"{prefix}{track}_error.png")))

        fig, axes = plt.subplots(5, 1, figsize=(7, 9), sharex=True)
        names = ("a0 (thrust)", "a1 (ω_x)", "a2 (ω_y)", "a3 (ω_z)", "‖a‖")
        for label, x in runs.items():
            for j in range(4):
                axes[j].plot(x.t, x.action[:, j], lw=1.0, label=label)
            axes[4].plot(x.t, np.linalg.norm(x.action, axis=-1), lw=1.0, label=label)
        for ax, ylabel in zip(axes, names, strict=True):
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
        axes[0].set_title(f"{name}: applied normalised actions{action_note}{suffix}")
        axes[0].legend(fontsize=8)
        axes[-1].set_xlabel("t [s]")
        paths.append(_save(fig, os.path.join(out_dir, f"{prefix}{track}_actions.png")))
    return paths


def import_pyplot_in_background() -> threading.Thread:
    """Import matplotlib's pyplot on a daemon thread (about a second of Python, which the
    run's learning curve needs only at its end), so that the import overlaps the compiled
    epochs, which hold no Python lock."""
    thread = threading.Thread(target=_pyplot, name="import-pyplot", daemon=True)
    thread.start()
    return thread


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str) -> str:
    plt = _pyplot()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_learning_curve(run_dir: str, rows: list[dict], title: str) -> str:
    """``run_dir/learning_curve.png`` from a run's metrics rows: Spiral-RT and LOS-RT Σ‖e‖
    (quadrotor, with the paper's T-TD3 for reference) or the evaluation return, per seed,
    against env transitions."""
    plt = _pyplot()
    seeds = sorted({int(r["seed"]) for r in rows})
    keys = [k for k in PAPER_TTD3 if k in rows[0]] or ["eval_return"]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 4), squeeze=False)
    for ax, key in zip(axes[0], keys, strict=True):
        for s in seeds:
            rs = [r for r in rows if int(r["seed"]) == s]
            ax.plot([r["env_steps"] for r in rs], [r[key] for r in rs], marker="o", ms=3, label=f"seed {s}")
        if key in PAPER_TTD3:
            ax.axhline(PAPER_TTD3[key], color="k", ls="--", lw=1, label="paper T-TD3")
            ax.set_yscale("log")
        ax.set(xlabel="env transitions", ylabel=key.replace("_", " ") + (" [m]" if "error" in key else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, os.path.join(run_dir, "learning_curve.png"))


TRACE_COLUMNS = (
    "label,t_s,x_m,y_m,z_m,x_ref_m,y_ref_m,z_ref_m,error_m,a0_thrust,a1_wx,a2_wy,a3_wz,"
    "vx_mps,vy_mps,vz_mps,qw,qx,qy,qz,yaw_rad"
)


def write_traces(traces: dict[str, dict[str, Trace]], out_dir: str, prefix: str = "") -> list[str]:
    """Per track, ``{prefix}{track}_trace.csv``: one row per control step and label
    (controller or seed), with the time (s), the flown and reference positions (m), the
    error ‖p_d − p‖ (m), the applied normalised action, the velocity (m/s), the attitude
    quaternion and its yaw (rad, z-y-x) (columns ``TRACE_COLUMNS``).  The plots of
    :func:`plot_traces` draw from the same data."""
    os.makedirs(out_dir, exist_ok=True)
    tracks = track_names(traces)
    paths = []
    for track in tracks:
        path = os.path.join(out_dir, f"{prefix}{track}_trace.csv")
        with open(path, "w") as fh:
            fh.write(TRACE_COLUMNS + "\n")
            for label, v in traces.items():
                if track not in v:
                    continue
                x = v[track]
                yaw = np.asarray(yaw_of(x.quat.T))
                cols = np.column_stack([x.t, x.pos, x.ref, x.error, x.action, x.vel, x.quat, yaw])
                name = str(label).replace(",", ";")
                for row in cols:
                    fh.write(name + "," + ",".join(f"{c:.9g}" for c in row) + "\n")
        paths.append(path)
    return paths


def fmt(x: float, spec: str) -> str:
    """``format(x, spec)``, with "inf" / "nan" (padded to the width) for non-finite values."""
    width = int(spec.split(".")[0].rstrip("dfe") or 0)
    return format(x, spec) if math.isfinite(x) else f"{'inf' if x > 0 else 'nan':>{width}}"


def json_safe(x):
    """JSON-ready copy: non-finite floats become None (strict JSON has no inf/nan)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


# the evaluation table's columns: (title, metric, format); the timing ones need --timing
_COLUMNS = (("Σ||e|| [m]", "tracking_error", "11.2f"), ("RMSE [m]", "rmse", "9.4f"),
            ("max [m]", "max_error", "8.4f"), ("crash", "crashed", "5.0f"), ("Σ||a||", "energy", "8.1f"),
            ("Σaᵀa", "energy_sq", "8.1f"))  # fmt: skip
_RATE = (("Hz", "control_hz", "5.0f"),)
_PRECISION = (("steady [m]", "steady_error", "10.4f"), ("overshoot %", "overshoot", "11.1f"))
_TIMING = (("steps", "control_steps", "5d"), ("compile s", "compile_scan_s", "9.2f"),
           ("loop s", "loop_s", "7.3f"), ("scan s", "scan_s", "7.3f"),
           ("act ms", "act_ms", "7.3f"))  # fmt: skip


def format_results(results: dict[str, dict[str, dict]], timing: bool) -> str:
    """The evaluation table: one row per (label, track); the precision columns where the
    results have them (:func:`~ttd3_jax.control.evaluator.evaluate_tracks`)."""
    any_m = next(iter(next(iter(results.values())).values()))
    cols = _COLUMNS + _RATE + (_PRECISION if "steady_error" in any_m else ()) + (_TIMING if timing else ())
    width = max(10, *(len(n) for per in results.values() for n in per))
    head = f"{'':<14} {'track':<{width}} " + " ".join(
        f"{t:>{int(f.split('.')[0].rstrip('d'))}}" for t, _, f in cols
    )

    def cell(m, k, f):  # overshoot is defined for a step only
        return f"{'-':>{len(fmt(0.0, f))}}" if k == "overshoot" and not math.isfinite(m[k]) else fmt(m[k], f)

    rows = [f"{label:<14} {name:<{width}} " + " ".join(cell(m, k, f) for _, k, f in cols)
            for label, per_track in results.items() for name, m in per_track.items()]  # fmt: skip
    return "\n".join([head, *rows])


def format_paper() -> str:
    """The paper's figures in one line, for comparison under a table."""
    parts = []
    for who in ("T-TD3", "MPC"):
        tracks = [f"{TRACK_TITLES[t]} {p['tracking_error']} / {p['energy']:.1f} / {p['run_s']:.2f}"
                  for t, p in PAPER[who].items()]  # fmt: skip
        parts.append(f"{who} " + ", ".join(tracks))
    return "paper Σ||e|| / Σ√(uᵀu) / run s: " + "; ".join(parts)


def format_robustness(label: str, rob: dict) -> str:
    """Robustness table of one controller (:func:`ttd3_jax.control.robustness.evaluate_robustness`)."""
    seeds = next(iter(rob.values()))["los_rt"]["seeds"]
    w = max(10, *(len(name) for name in rob))
    lines = [
        f"robustness of {label}: Spiral-RT, and LOS-RT seeds {seeds[0]}..{seeds[-1]} (mean ± std over "
        f"{len(seeds)})",
        f"{'condition':<{w}} {'Spiral Σ||e||':>13} {'LOS Σ||e|| mean ± std':>24} {'LOS crashes':>11} "
        f"{'LOS Σ||a|| mean ± std':>22}",
    ]
    for name, r in rob.items():
        los = r["los_rt"]
        e, a = los["tracking_error"], los["energy"]
        lines.append(
            f"{name:<{w}} {fmt(r['spiral_rt']['tracking_error'], '13.2f')} "
            f"{fmt(e['mean'], '13.2f')} ± {fmt(e['std'], '8.2f')} "
            f"{los['crashed']:>5}/{len(los['seeds']):<5} "
            f"{fmt(a['mean'], '12.1f')} ± {fmt(a['std'], '7.1f')}"
        )
    return "\n".join(lines)


def tensorboard(run_dir: str):
    """A TensorBoard writer for ``run_dir/tb`` when tensorboardX is installed, else ``None``;
    the runner logs every seed's metrics under ``seed<N>/``."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(os.path.join(run_dir, "tb"))


def device_description() -> str:
    """The default JAX device in words, e.g. ``"cpu (cpu), AMD EPYC, 2 core(s) usable"``."""
    dev = jax.devices()[0]
    text = f"{dev.platform} ({dev.device_kind})"
    if dev.platform == "cpu":
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count()
        model = ""
        with contextlib.suppress(OSError):
            with open("/proc/cpuinfo") as fh:
                model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
        text += f", {model + ', ' if model else ''}{cores} core(s) usable"
    return text
