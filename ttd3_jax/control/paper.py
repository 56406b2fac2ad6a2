"""The paper's reported figures, in one place (its Tables 3-5, quadrotor).

"MPC" is the paper's own, unspecified MPC.  Σ‖e‖ in m, energy Σ√(uᵀu) (spec M2: the LOS
values exceed the bound of 2 per step), run time in s (a Python loop of 3000 controller
outputs, mean of 3 runs, hardware not stated).
"""

from __future__ import annotations

PAPER = {
    "T-TD3": {
        "spiral_rt": {"tracking_error": 25.99, "energy": 2759.582772, "run_s": 4.879404},
        "los_rt": {"tracking_error": 398.74, "energy": 7156.452883, "run_s": 4.754059},
    },
    "MPC": {
        "spiral_rt": {"tracking_error": 78.47, "energy": 2762.378835, "run_s": 19.360494},
        "los_rt": {"tracking_error": 542.92, "energy": 7467.541158, "run_s": 16.305317},
    },
}

# the targets of a training run: the paper's T-TD3 tracking errors, keyed as a run's metrics
PAPER_TTD3 = {
    "spiral_tracking_error": PAPER["T-TD3"]["spiral_rt"]["tracking_error"],
    "los_tracking_error": PAPER["T-TD3"]["los_rt"]["tracking_error"],
}


def beats_paper(m: dict) -> bool:
    """Whether a run's evaluation ``m`` (``spiral_*`` / ``los_*`` metrics) tracks both test
    tracks at least as well as the paper's T-TD3, without a crash."""
    return bool(
        m["spiral_tracking_error"] <= PAPER_TTD3["spiral_tracking_error"]
        and m["los_tracking_error"] <= PAPER_TTD3["los_tracking_error"]
        and m["spiral_crashed"] == 0
        and m["los_crashed"] == 0
    )
