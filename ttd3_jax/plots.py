"""Plots of closed-loop evaluation traces (:class:`ttd3_jax.evaluate.Trace`).

:func:`plot_traces` writes, per test track, PNG files of the reference and flown 3-D paths
(m), the tracking error ‖p_d − p‖ (m, log scale) against time (s), and the four applied
normalised actions with ‖a‖ against time.  matplotlib is imported on first use, with the
non-interactive ``Agg`` backend.
"""

from __future__ import annotations

import os

import numpy as np

from ttd3_jax import trajectories as tr
from ttd3_jax.evaluate import TRACK_TITLES, Trace


def plot_traces(
    traces: dict[str, dict[str, Trace]],
    out_dir: str,
    title: str = "",
    los_seed: int = 0,
    prefix: str = "",
    e_show: float = 2.0,
    action_note: str = "",
) -> list[str]:
    """Per track: ``{prefix}{track}_3d.png`` (reference and flown paths),
    ``{prefix}{track}_error.png`` (‖e‖ vs time) and ``{prefix}{track}_actions.png`` (the four
    applied normalised actions and ‖a‖ vs time).  ``traces`` maps a label (controller, seed)
    to ``{track: Trace}``.  The 3-D plot shows each flown path until its error first
    exceeds ``e_show`` m; ``action_note`` is appended to the action plot's title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    tracks = [t for t in tr.TEST_TRACKS if any(t in v for v in traces.values())]
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
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.set_title(f"{name}: reference vs flown{suffix}")
        ax.legend(fontsize=8)
        paths.append(_save(fig, os.path.join(out_dir, f"{prefix}{track}_3d.png")))

        fig, ax = plt.subplots(figsize=(7, 3.5))
        for label, x in runs.items():
            ax.plot(x.t, x.error, lw=1.2, label=label)
        ax.set_yscale("log")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("‖p_d − p‖ [m]")
        ax.set_title(f"{name}: tracking error{suffix}")
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


def _save(fig, path: str) -> str:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
