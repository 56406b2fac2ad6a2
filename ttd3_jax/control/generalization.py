"""The generalisation suite: tracks no policy is trained on, with precision figures that
separate the catch-up transient from the steady state.

Every suite episode lasts 3 s (its track runs 1.1 s longer, so that no controller's preview
sees the end) and starts with the vehicle at rest on p_d(0), as the test
tracks do (spec §2.5).  The random tracks are drawn with NumPy from fixed seeds, outside
the training mixture's ranges (faster, harder accelerations, longer LOS legs).
"""

from __future__ import annotations

import math

import numpy as np

from ttd3_jax.control.closed_loop import Rollout
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import trajectories as tr

SUITES = ("generalization",)
DURATION_S = 3.0  # s, an episode (3000 physics steps)
PREVIEW_S = 1.1  # s of reference past the episode's end: the NMPC's 1 s preview, the look-ahead
STEADY_AFTER_S = 1.0  # s: the steady-state error is the mean ||e|| after this time
STEP_TARGET = (0.5, 0.0, 0.0)  # m

DESCRIPTIONS = {
    "figure8": "figure-8, x = sin(ωt), y = ½ sin(2ωt) (±1 m × ±0.5 m), 1 m/s through the centre",
    "circle": "circle of radius 1 m at 1.5 m/s",
    "step": "0.5 m position step along x from hover (v = a = 0)",
    "spiral_fast": "Spiral-RT at 1.5× its speed (time scale 1.5)",
    "agile_1": (
        "random accelerations, |a| ≤ 6 m/s² per horizontal axis (paper mixture ≤ 3, wide ≤ 6), "
        "held 0.3 s, ≤ 4.5 m/s"
    ),
    "agile_2": "as agile_1, another seed",
    "los_fast": "LOS legs of 0.5 s at 3.5–4.5 m/s (paper mixture ≤ 3, wide ≤ 4.5), headings ±20°",
}


def _figure8(t):
    w = 1.0 / math.sqrt(2.0)  # rad/s: |v(0)| = √2 ω = 1 m/s
    return np.stack([np.sin(w * t), 0.5 * np.sin(2 * w * t), 0 * t], -1)


def _circle(t):
    w = 1.5  # rad/s, r = 1 m
    return np.stack([np.sin(w * t), 1.0 - np.cos(w * t), 0 * t], -1)


def _agile(seed: int, dt: float) -> ct.CustomTrack:
    """Piecewise-constant accelerations integrated exactly on the physics grid."""
    rng = np.random.default_rng(seed)
    hold, n = round(0.3 / dt), round((DURATION_S + PREVIEW_S) / dt) + 1
    acc = np.repeat(rng.uniform(-1, 1, (n // hold + 1, 3)) * (6.0, 6.0, 2.0), hold, 0)[:n]
    p, v = np.zeros((n, 3)), np.zeros((n, 3))
    for k in range(n - 1):
        a = acc[k]
        speed = np.linalg.norm(v[k] + a * dt)
        if speed > 4.5:
            a = ((v[k] + a * dt) * 4.5 / speed - v[k]) / dt
            acc[k] = a
        v[k + 1] = v[k] + a * dt
        p[k + 1] = p[k] + v[k] * dt + 0.5 * a * dt * dt
    return ct.CustomTrack(f"agile_{seed}", p, v, acc, dt=dt)


def _los_fast(dt: float) -> ct.CustomTrack:
    rng = np.random.default_rng(7)
    hold, n = round(0.5 / dt), round((DURATION_S + PREVIEW_S) / dt) + 1
    legs = n // hold + 1
    psi = rng.uniform(-math.pi / 9, math.pi / 9, legs)
    speed = rng.uniform(3.5, 4.5, legs)
    v = np.repeat(np.stack([speed * np.cos(psi), speed * np.sin(psi), 0 * psi], -1), hold, 0)[:n]
    p = np.concatenate([np.zeros((1, 3)), np.cumsum(v[:-1] * dt, 0)])
    return ct.CustomTrack("los_fast", p, v, np.zeros_like(v), dt=dt)


def suite_tracks(name: str, dt: float = 1e-3) -> dict[str, tr.Track]:
    """The suite's tracks by name, each a single :class:`~ttd3_jax.sim.trajectories.Track`."""
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; allowed: {SUITES}")
    custom = [
        ct.from_function(_figure8, DURATION_S + PREVIEW_S, dt=dt, name="figure8"),
        ct.from_function(_circle, DURATION_S + PREVIEW_S, dt=dt, name="circle"),
        ct.step(STEP_TARGET, DURATION_S + PREVIEW_S, dt=dt),
        _agile(1, dt),
        _agile(2, dt),
        _los_fast(dt),
    ]
    tracks = {c.name: c.track() for c in custom}
    tracks["spiral_fast"] = tr.spiral_rt(tr.TrackConfig(spiral_time_scale=1.5))
    return {k: tracks[k] for k in DESCRIPTIONS}


def precision(r: Rollout, control_dt: float, name: str) -> dict[str, float]:
    """Figures of one rollout (host arrays): ``steady_error`` (m), the mean ‖e‖ over control
    steps after :data:`STEADY_AFTER_S` (NaN for shorter episodes), and on the step track
    ``overshoot`` (%), how far the vehicle passes the target along the step, relative to
    the step's length (NaN elsewhere)."""
    pos, ref = np.asarray(r.pos), np.asarray(r.ref)
    t = control_dt * np.arange(1, pos.shape[0] + 1)
    e = np.linalg.norm(pos - ref, axis=-1)
    late = e[t > STEADY_AFTER_S]
    out = {"steady_error": float(np.mean(late)) if late.size else float("nan")}  # NaN: too short
    overshoot = float("nan")
    if name == "step":
        d = np.asarray(STEP_TARGET)
        along = pos @ d / np.dot(d, d)  # 1.0 at the target
        overshoot = 100.0 * max(0.0, float(np.max(along)) - 1.0)
    out["overshoot"] = overshoot
    return out
