"""The tracking env's static configuration and presets.  :class:`EnvConfig` is validated on
construction, so a bad value fails before anything compiles; docs/paper-notes.md gives the
reading of the paper behind each default.
"""

from __future__ import annotations

import dataclasses
import math
import os

from ttd3_jax import checks
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.dynamics import QuadParams, validate_params

TRACK_MODES = ("train", "validation", "spiral_rt", "los_rt")
ERR_REFS = ("current", "next")
ERR_COSTS = ("paper", "squared", "log")
OBS_FRAMES = ("world", "track")
PRESETS = ("paper", "practical")
PRIVILEGED_AHEAD_S = (0.5, 1.0)  # s after p_d,k+L of the critics' extra reference points (obs_privileged)
CRASH_GAMMA = 0.99  # the discount the derived crash penalty is sized for (spec R4)
# the fields EnvConfig.for_eval sets, and the episode length it keeps (keep them together)
EVAL_PROTOCOL_FIELDS = ("track", "los_seed", "randomize_init", "terminate", "wind_sigma", "e_max",
                        "obs_noise_pos", "obs_noise_vel", "obs_noise_quat", "episode_steps")  # fmt: skip
DT_MAX = 0.01  # s: the physics step the integrator is used with at most (the body-rate lag is 0.03 s)
EVAL_CRASH_M = 1.0  # m: every controller is judged crashed once its error exceeds this in evaluation


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static environment configuration (units in comments). Validated on construction."""

    # time
    dt: float = 1e-3  # s, physics (RK4) step
    episode_steps: int = 3000  # physics steps per episode (3 s)
    action_repeat: int = 1  # physics steps per control step (T1, T9)
    # vehicle and integrator (D4, D5, D7)
    quad: QuadParams = QuadParams()
    rk4_substeps: int = 1
    renormalize: bool = True
    canonical_q_obs: bool = True  # observe q with qw >= 0
    # observation and action (O1, O2)
    err_ref: str = "current"
    lookahead_k: int = 1  # physics steps ahead for the observed reference point
    obs_frame: str = "world"  # "track": positions relative to p_d,k (translation invariant)
    hover_centered_thrust: bool = False  # a0 = 0 means hover thrust
    # appended to the observation (not in the paper): the last applied action (4) and the
    # leaky integral ∫(p_d − p) dt (3, m·s, leak time constant memory_tau s)
    obs_memory: bool = False
    memory_tau: float = 1.0  # s
    # appended last, for the critics only (the actor sees the observation without them):
    # the wind acceleration (3, m/s²) and p_d 0.5 s and 1 s after p_d,k+L, relative to it (6, m)
    obs_privileged: bool = False
    # reward and termination (R1-R4)
    err_cost: str = "paper"  # r_e: "paper" (e, or e² past 1 m), "squared", "log": ln(1 + e/err_scale)
    err_scale: float = 0.02  # m, ε of err_cost="log"
    rho1: float = 1.0
    rho2: float = 0.01
    effort_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)  # diag Ω
    effort_hover_relative: bool = False  # penalise (a - a_hover) instead of a
    terminate: bool = True
    e_max: float = 2.0  # m
    # reward of a crash; None: rho1 r_e(e_max) action_repeat / (1 - 0.99), 400 for the paper
    crash_penalty: float | None = None
    # tracks and initial state (T1-T8, R5)
    track: str = "train"  # one of TRACK_MODES
    los_seed: int = 0  # LOS-RT test instance when track == "los_rt"
    tracks: tr.TrackConfig = tr.TrackConfig()
    randomize_init: bool = True
    init_pos: float = 0.1  # m, ± per axis around p_d(0)
    init_vel: float = 0.2  # m/s, ± per axis
    init_tilt_deg: float = 10.0  # deg, max tilt about a random horizontal axis
    init_yaw_deg: float = 15.0  # deg, ± yaw
    # disturbances (O3)
    wind_sigma: float = 0.0  # m/s^2, stationary std of the OU acceleration
    wind_tau: float = 0.5  # s, OU correlation time
    obs_noise_pos: float = 0.0  # m, std
    obs_noise_vel: float = 0.0  # m/s, std
    obs_noise_quat: float = 0.0  # std on each quaternion component (then renormalised)
    # robustness evaluation (not in the paper)
    action_delay: int = 0  # control steps between an action and its application (0 or 1)
    # users' tracks in the training mixture (never the test or suite tracks)
    train_tracks: tuple[str, ...] = ()  # CSV files read by sim.custom_tracks.from_csv
    train_tracks_weight: float = 0.25  # probability that a training episode flies one of them
    thrust_map_mass: float | None = None  # kg: mass whose hover thrust the action map assumes
    #   under hover_centered_thrust (None = quad.mass); set to the nominal mass when quad.mass
    #   is changed, so that a mass error stays unknown to the action map (and the controller)

    def __post_init__(self):
        _validate(self)

    # derived quantities -------------------------------------------------------------
    @property
    def control_dt(self) -> float:
        """Seconds per env step."""
        return self.dt * self.action_repeat

    @property
    def episode_length(self) -> int:
        """Env (control) steps per episode."""
        return self.episode_steps // self.action_repeat

    @property
    def horizon_steps(self) -> int:
        """Physics steps at which a reference point may be read."""
        extra = round(max(PRIVILEGED_AHEAD_S) / self.dt) if self.obs_privileged else 0
        return self.episode_steps + self.lookahead_k + 2 + extra

    @property
    def crash_cost(self) -> float:
        """The reward a crash costs: ``crash_penalty``, or by default what staying at
        ``e_max`` would cost for ever, ρ₁ r_e(e_max) · action_repeat / (1 − 0.99)."""
        if self.crash_penalty is not None:
            return self.crash_penalty
        return self.rho1 * error_cost_value(self, self.e_max) * self.action_repeat / (1 - CRASH_GAMMA)

    def for_eval(self, track: str, los_seed: int = 0, wind_sigma: float = 0.0) -> EnvConfig:
        """The evaluation protocol (spec §2.5): fixed track, start on p_d(0) at rest and
        level, no early termination, no observation noise, optional wind, and one crash
        threshold for every controller (``e_max = EVAL_CRASH_M``).  It sets the fields in
        ``EVAL_PROTOCOL_FIELDS`` (``episode_steps`` stays: 3000, the paper's)."""
        quiet = dict(randomize_init=False, terminate=False, e_max=EVAL_CRASH_M, obs_noise_pos=0.0,
                     obs_noise_vel=0.0, obs_noise_quat=0.0)  # fmt: skip
        return dataclasses.replace(self, track=track, los_seed=los_seed, wind_sigma=wind_sigma, **quiet)


def error_cost_value(c: EnvConfig, e: float) -> float:
    """r_e(e) for a Python float ``e`` (m); ``sim.env.error_cost`` is the traced one."""
    if c.err_cost == "squared":
        return e * e
    if c.err_cost == "log":
        return math.log1p(e / c.err_scale)
    return e if e * e <= 1 else e * e


def _validate(c: EnvConfig) -> None:
    """Raise ``ValueError`` naming the bad field, its value and what is allowed."""
    f = lambda name: f"EnvConfig.{name}"  # noqa: E731
    for name in ("e_max", "wind_tau", "rho1", "err_scale", "memory_tau"):
        checks.number(f(name), getattr(c, name), 0, lo_open=True)
    checks.number(f("dt"), c.dt, 0, DT_MAX, lo_open=True,
                  unit=" s (the RK4 physics step; the paper's is 0.001 s, control steps are longer "
                       "through action_repeat)")  # fmt: skip
    for name in ("episode_steps", "action_repeat", "rk4_substeps", "lookahead_k"):
        checks.integer(f(name), getattr(c, name), 1)
    for name in ("rho2", "init_pos", "init_vel", "init_tilt_deg", "init_yaw_deg", "wind_sigma",
                 "obs_noise_pos", "obs_noise_vel", "obs_noise_quat", "los_seed"):  # fmt: skip
        checks.number(f(name), getattr(c, name), 0)
    if c.crash_penalty is not None:
        checks.number(f("crash_penalty"), c.crash_penalty, 0, unit=" or None")
    if c.thrust_map_mass is not None:
        checks.number(f("thrust_map_mass"), c.thrust_map_mass, 0, lo_open=True, unit=" or None")
    checks.one_of(f("action_delay"), c.action_delay, (0, 1))
    for name, allowed in (("err_ref", ERR_REFS), ("err_cost", ERR_COSTS), ("obs_frame", OBS_FRAMES),
                          ("track", TRACK_MODES)):  # fmt: skip
        checks.one_of(f(name), getattr(c, name), allowed)
    for name in ("renormalize", "canonical_q_obs", "hover_centered_thrust", "effort_hover_relative",
                 "terminate", "randomize_init", "obs_memory", "obs_privileged"):  # fmt: skip
        checks.boolean(f(name), getattr(c, name))
    if c.obs_memory and c.action_delay:
        raise ValueError(
            "EnvConfig.obs_memory needs action_delay 0 (the delayed env keeps its own last action)"
        )
    if c.episode_steps % c.action_repeat:
        raise ValueError(
            f"EnvConfig.episode_steps ({c.episode_steps}) must be a multiple of action_repeat "
            f"({c.action_repeat})"
        )
    w = c.effort_weights
    if len(w) != 4 or not all(checks.is_number(x) and x >= 0 for x in w):
        checks.fail("EnvConfig.effort_weights", "4 finite numbers >= 0", w)
    checks.instance("EnvConfig.quad", c.quad, QuadParams)
    validate_params(c.quad)
    if not all(isinstance(p, str) and os.path.isfile(p) for p in c.train_tracks):
        bad = next(p for p in c.train_tracks if not (isinstance(p, str) and os.path.isfile(p)))
        raise ValueError(f"EnvConfig.train_tracks: {bad!r} is not a file; allowed: CSV track files")
    checks.number("EnvConfig.train_tracks_weight", c.train_tracks_weight, 0, 1, lo_open=True)
    checks.instance("EnvConfig.tracks", c.tracks, tr.TrackConfig)


def make_config(preset: str = "paper", **overrides) -> EnvConfig:
    """A named, documented configuration, with ``overrides`` (EnvConfig fields) on top.

    ``paper``: 1 kHz control exactly as published (spec defaults), trained with an OU
    wind of 0.2 m/s^2.  ``practical``: 10 physics steps per action and a 50 ms
    look-ahead so that γ = 0.99 spans about 1 s (spec T9); positions observed
    relative to the current reference point (``obs_frame="track"``); episodes end
    1 m off the track, with the R4 penalty for that distance (1000).
    """
    if preset == "paper":
        base = dict(wind_sigma=0.2)
    elif preset == "practical":
        base = dict(wind_sigma=0.2, action_repeat=10, lookahead_k=50, obs_frame="track", e_max=1.0)
    else:
        raise ValueError(f"unknown env preset {preset!r}; allowed: {PRESETS}")
    return EnvConfig(**{**base, **overrides})
