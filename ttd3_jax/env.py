"""Quadrotor trajectory-tracking environment with the Brax ``Env`` API (spec §2.2).

One control step (``env.step``) applies a normalised action ``a ∈ [-1, 1]^4`` for
``action_repeat`` physics steps of ``dt`` seconds each.  With the ``paper``
preset that is one 1 ms RK4 step.

Observation at physics step k (17-D, raw units, O1)::

    [p_k (3, m), v_k (3, m/s), q_k (4, qw>=0), p_d,k+L (3, m), p_d,k+L - p_k (3, m),
     ||p_d,k' - p_k|| (1, m)]          (+ ω_k (3, rad/s) for the first_order/torque models)

``obs_frame="track"`` moves the origin of the two absolute positions to p_d,k, so
they read p_k - p_d,k and p_d,k+L - p_d,k (the policy no longer sees where in space
the track is).  ``"heading"`` turns that by the vehicle's -yaw; ``"error"`` puts the
velocity error v_k - (p_d,k+L - p_d,k)/(L dt) in slot 2 and v_k in slot 5.

with L = ``lookahead_k`` (1 in the paper) and k' = k (``err_ref="current"``) or k+1.
Reward per physics step, with e' = ||p_d,k+1 - p_k+1|| after the step (R1-R3)::

    r = -rho1 * r_e(e') - rho2 * aᵀ Ω a,   r_e(e) = e if e² <= 1 else e²

summed over the ``action_repeat`` physics steps.  An episode terminates (crash)
when e' > ``e_max`` or the state is not finite, with reward ``-crash_penalty``,
and is truncated (``info["truncation"] = 1``) after ``episode_steps`` physics steps.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math

import jax
import jax.numpy as jnp
from flax import struct

# mujoco.mjx (imported by brax) prints "Failed to import warp" when the optional
# GPU package is absent; keep that out of our CLI output.
with contextlib.redirect_stdout(io.StringIO()):
    from brax.envs.base import Env, State

from ttd3_jax import rng
from ttd3_jax import trajectories as tr
from ttd3_jax.dynamics import QuadParams, QuadState, quat_from_axis_angle, quat_mul, rk4_step, validate_params

TRACK_MODES = ("train", "validation", "spiral_rt", "los_rt")
ERR_REFS = ("current", "next")
ERR_COSTS = ("paper", "squared")
OBS_FRAMES = ("world", "track", "heading", "error")
RATE_MAPS = ("linear", "cubic")
PRESETS = ("paper", "practical")
# the fields EnvConfig.for_eval sets (keep the two together)
EVAL_PROTOCOL_FIELDS = ("track", "los_seed", "randomize_init", "terminate", "wind_sigma",
                        "obs_noise_pos", "obs_noise_vel", "obs_noise_quat")  # fmt: skip


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static environment configuration (units in comments). Validated on construction.

    Build the documented presets with :func:`make_config`; change fields with
    ``dataclasses.replace``.  See docs/paper-notes.md for every reading of the paper.
    """

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
    obs_frame: str = "world"  # "track": positions relative to p_d,k (translation invariant);
    #   "heading": "track", then vectors and q in the vehicle's heading frame (yaw invariant)
    #   "error": [p - p_d,k, v - v̂_d, q, p_d,k+L - p_d,k, v, ||e||], v̂_d = (p_d,k+L - p_d,k)/(L dt)
    hover_centered_thrust: bool = False  # a0 = 0 means hover thrust
    rate_map: str = "linear"  # "cubic": a -> α a + (1 − α) a³ before the rate map (not in the paper)
    rate_map_slope: float = 0.1  # α, the cubic map's slope at a = 0 (1 = linear)
    # reward and termination (R1-R4)
    err_cost: str = "paper"
    rho1: float = 1.0
    rho2: float = 0.01
    effort_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)  # diag Ω
    effort_hover_relative: bool = False  # penalise (a - a_hover) instead of a
    rho_vel: float = 0.0  # 1/(m/s): extra cost rho_vel ||v - v_ref|| per physics step (not in the paper)
    precision_bonus: float = 0.0  # m: extra cost κ (1 − exp(−||e||/precision_scale)) per physics
    precision_scale: float = 0.02  # m, ε   step (not in the paper): slope 1 + κ/ε at e = 0
    terminate: bool = True
    e_max: float = 2.0  # m
    crash_penalty: float = 400.0  # = rho1 r_e(e_max) action_repeat / (1 - 0.99)
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
    thrust_map_mass: float | None = None  # kg: mass whose hover thrust the action map assumes
    #   under hover_centered_thrust (None = quad.mass); set to the nominal mass when quad.mass
    #   is changed, so that a mass error stays unknown to the action map (and the controller)

    def __post_init__(self):
        def positive(name, integer=False):
            v = getattr(self, name)
            if integer and (not isinstance(v, int) or isinstance(v, bool)):
                raise ValueError(f"EnvConfig.{name} must be an integer >= 1, got {v!r}")
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"EnvConfig.{name} must be > 0, got {v!r}")

        def non_negative(name):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"EnvConfig.{name} must be >= 0, got {v!r}")

        def one_of(name, allowed):
            if getattr(self, name) not in allowed:
                raise ValueError(f"EnvConfig.{name} must be one of {allowed}, got {getattr(self, name)!r}")

        for name in ("dt", "e_max", "wind_tau", "rho1", "precision_scale"):
            positive(name)
        for name in ("episode_steps", "action_repeat", "rk4_substeps", "lookahead_k"):
            positive(name, integer=True)
        for name in (
            "rho2",
            "rho_vel",
            "precision_bonus",
            "crash_penalty",
            "init_pos",
            "init_vel",
            "init_tilt_deg",
            "init_yaw_deg",
            "wind_sigma",
            "obs_noise_pos",
            "obs_noise_vel",
            "obs_noise_quat",
            "los_seed",
        ):
            non_negative(name)
        if isinstance(self.action_delay, bool) or self.action_delay not in (0, 1):
            raise ValueError(
                f"EnvConfig.action_delay must be 0 or 1 (control steps), got {self.action_delay!r}"
            )
        if self.thrust_map_mass is not None:
            positive("thrust_map_mass")
        one_of("err_ref", ERR_REFS)
        one_of("err_cost", ERR_COSTS)
        one_of("obs_frame", OBS_FRAMES)
        one_of("rate_map", RATE_MAPS)
        if not (isinstance(self.rate_map_slope, (int, float)) and 0 < self.rate_map_slope <= 1):
            raise ValueError(f"EnvConfig.rate_map_slope must be in (0, 1], got {self.rate_map_slope!r}")
        one_of("track", TRACK_MODES)
        if self.episode_steps % self.action_repeat:
            raise ValueError(
                f"EnvConfig.episode_steps ({self.episode_steps}) must be a multiple of "
                f"action_repeat ({self.action_repeat})"
            )
        if len(self.effort_weights) != 4 or any(w < 0 for w in self.effort_weights):
            raise ValueError(f"EnvConfig.effort_weights must be 4 values >= 0, got {self.effort_weights}")
        if not isinstance(self.quad, QuadParams):
            raise ValueError(f"EnvConfig.quad must be a QuadParams, got {type(self.quad).__name__}")
        validate_params(self.quad)
        if not isinstance(self.tracks, tr.TrackConfig):
            raise ValueError(f"EnvConfig.tracks must be a TrackConfig, got {type(self.tracks).__name__}")

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
        return self.episode_steps + self.lookahead_k + 2

    def for_eval(self, track: str, los_seed: int = 0, wind_sigma: float = 0.0) -> EnvConfig:
        """The evaluation protocol (spec §2.5): fixed track, start on p_d(0) at rest and
        level, no early termination, no observation noise, optional wind.  It sets exactly
        the fields in ``EVAL_PROTOCOL_FIELDS``."""
        return dataclasses.replace(
            self,
            track=track,
            los_seed=los_seed,
            randomize_init=False,
            terminate=False,
            wind_sigma=wind_sigma,
            obs_noise_pos=0.0,
            obs_noise_vel=0.0,
            obs_noise_quat=0.0,
        )


def error_cost(cfg: EnvConfig, e: jax.Array) -> jax.Array:
    """r_e(e) of eq. 3 (``err_cost="paper"``) or e² (``"squared"``); e in m."""
    if cfg.err_cost == "squared":
        return e * e
    return jnp.where(e * e <= 1.0, e, e * e)


def _like(default, x):
    """``x`` with JSON lists as tuples and integers as floats where ``default`` (the field's
    default value) has floats, recursively, so that ``e_max=1`` sets the float 1.0."""
    if isinstance(x, (list, tuple)):
        ref = default if isinstance(default, tuple) and len(default) == len(x) else (None,) * len(x)
        return tuple(_like(d, v) for d, v in zip(ref, x, strict=True))
    if isinstance(default, float) and isinstance(x, int) and not isinstance(x, bool):
        return float(x)
    return x


def config_value(name: str, value):
    """``value`` (as read from JSON or a command line) as the type of ``EnvConfig.name``:
    lists become tuples, and an object sets some fields of a nested config (``quad``:
    :class:`~ttd3_jax.dynamics.QuadParams`, ``tracks``: :class:`~ttd3_jax.trajectories.TrackConfig`)
    on top of their defaults.  Raises ``ValueError`` naming a field that does not exist."""
    fields = {f.name: f for f in dataclasses.fields(EnvConfig)}
    if name not in fields:
        raise ValueError(f"unknown env config field {name!r}; allowed: {sorted(fields)}")
    default = fields[name].default
    if not dataclasses.is_dataclass(default) or isinstance(value, type(default)):
        return _like(default, value)
    kind = type(default).__name__
    if not isinstance(value, dict):
        raise ValueError(f"{name} takes an object of {kind} fields, got {value!r}")
    allowed = {f.name for f in dataclasses.fields(default)}
    unknown = sorted(set(value) - allowed)
    if unknown:
        raise ValueError(f"{name}: unknown {kind} field(s) {unknown}; allowed: {sorted(allowed)}")
    merged = {k: getattr(default, k) for k in allowed}
    merged.update({k: _like(merged[k], v) for k, v in value.items()})
    return type(default).create(**merged) if hasattr(type(default), "create") else type(default)(**merged)


def parse_overrides(items, refused: dict[str, str] | None = None) -> dict:
    """Command-line overrides ``["name=value", ...]`` as ``{field: value}`` in the types of
    ``EnvConfig`` (:func:`config_value`).  ``value`` is read as JSON when it parses (numbers,
    ``true``, lists, objects for the nested ``quad`` / ``tracks``), else as a plain string.
    ``refused`` maps fields that may not be set here to the reason.  Raises ``ValueError``
    naming the bad entry."""
    refused = refused or {}
    out = {}
    for item in items:
        if not isinstance(item, str) or "=" not in item:
            raise ValueError(f"an env override is 'name=value', got {item!r}")
        name, text = (x.strip() for x in item.split("=", 1))
        if name in refused:
            raise ValueError(f"{name!r} cannot be overridden ({refused[name]})")
        if name in out:
            raise ValueError(f"{name!r} is overridden twice")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text  # a bare word: a string field such as obs_frame=heading
        out[name] = config_value(name, value)
    return out


def make_config(preset: str = "paper", **overrides) -> EnvConfig:
    """A named, documented configuration.

    ``paper``: 1 kHz control exactly as published (spec defaults), trained with an OU
    wind of 0.2 m/s^2.  ``practical``: 10 physics steps per action and a 50 ms
    look-ahead so that γ = 0.99 spans about 1 s (spec T9); positions observed
    relative to the current reference point (``obs_frame="track"``); episodes end
    1 m off the track, with the R4 penalty for that distance (1000).
    """
    if preset == "paper":
        base = dict(wind_sigma=0.2)
    elif preset == "practical":
        repeat, gamma = 10, 0.99
        base = dict(wind_sigma=0.2, action_repeat=repeat, lookahead_k=50, obs_frame="track", e_max=1.0)
        rho1, e_max = overrides.get("rho1", 1.0), overrides.get("e_max", base["e_max"])
        e_cost = e_max if e_max * e_max <= 1 else e_max * e_max
        base["crash_penalty"] = rho1 * e_cost * repeat / (1 - gamma)
    else:
        raise ValueError(f"unknown env preset {preset!r}; allowed: {PRESETS}")
    base.update(overrides)
    return EnvConfig(**base)


# --------------------------------------------------------------------------- action map


def _thrust_range(cfg: EnvConfig):
    q = cfg.quad
    hover = q.hover_thrust
    if cfg.thrust_map_mass is not None and q.thrust_units == "newton":
        hover = q.gravity * cfg.thrust_map_mass
    return q.thrust_min, q.thrust_max, hover


def action_to_control(cfg: EnvConfig, a: jax.Array) -> jax.Array:
    """Normalised action (..., 4) in [-1, 1] -> physical control ``[thrust, ω_cmd]`` (O2).

    Default: thrust = f_min + (a0 + 1)/2 (f_max - f_min); rates affine onto
    [rate_min, rate_max].  ``hover_centered_thrust`` maps a0 = 0 to the hover thrust.
    ``rate_map="cubic"`` first sends each rate action a to α a + (1 − α) a³ (odd, monotone,
    [-1, 1] onto itself): the same bounds with 1/α times finer resolution near a = 0.
    """
    lo, hi, hover = _thrust_range(cfg)
    a0 = a[..., 0]
    if cfg.hover_centered_thrust:
        f = jnp.where(a0 >= 0, hover + a0 * (hi - hover), hover + a0 * (hover - lo))
    else:
        f = lo + 0.5 * (a0 + 1.0) * (hi - lo)
    rlo, rhi = cfg.quad.rate_min, cfg.quad.rate_max
    w = rlo + 0.5 * (_shape_rates(cfg, a[..., 1:]) + 1.0) * (rhi - rlo)
    return jnp.concatenate([f[..., None], w], -1)


def _shape_rates(cfg: EnvConfig, a: jax.Array) -> jax.Array:
    if cfg.rate_map == "linear":
        return a
    k = cfg.rate_map_slope
    return k * a + (1.0 - k) * a * a * a


def _unshape_rates(cfg: EnvConfig, y: jax.Array) -> jax.Array:
    """Inverse of :func:`_shape_rates`: the real root of (1 − α) a³ + α a = y (Cardano)."""
    if cfg.rate_map == "linear" or cfg.rate_map_slope == 1.0:
        return y
    k = cfg.rate_map_slope
    p, q = k / (1.0 - k), -y / (1.0 - k)
    r = jnp.sqrt(q * q / 4.0 + p**3 / 27.0)
    return jnp.cbrt(-q / 2.0 + r) + jnp.cbrt(-q / 2.0 - r)


def control_to_action(cfg: EnvConfig, u: jax.Array) -> jax.Array:
    """Inverse of :func:`action_to_control` (for controllers with physical outputs)."""
    lo, hi, hover = _thrust_range(cfg)
    f = u[..., 0]
    if cfg.hover_centered_thrust:
        a0 = jnp.where(f >= hover, (f - hover) / (hi - hover), (f - hover) / (hover - lo))
    else:
        a0 = 2.0 * (f - lo) / (hi - lo) - 1.0
    rlo, rhi = cfg.quad.rate_min, cfg.quad.rate_max
    aw = _unshape_rates(cfg, 2.0 * (u[..., 1:] - rlo) / (rhi - rlo) - 1.0)
    return jnp.concatenate([a0[..., None], aw], -1)


def hover_action(cfg: EnvConfig) -> jax.Array:
    """Normalised action that holds hover (a0 = 0.4715 with the paper's numbers).  With
    ``thrust_map_mass`` set: the hover action of that (nominal) mass."""
    u = jnp.array([_thrust_range(cfg)[2], 0.0, 0.0, 0.0])
    return control_to_action(cfg, u)


# --------------------------------------------------------------------------- env


@struct.dataclass
class TrackingState:
    """What the simulator carries between steps (Brax ``State.pipeline_state``)."""

    quad: QuadState
    k: jax.Array  # int32, physics step index
    track: tr.Track
    wind: jax.Array  # (3,) m/s^2, OU acceleration disturbance
    key: jax.Array  # PRNG key for wind and observation noise
    ref_next: jax.Array  # (3,) m, p_d(k+1), cached by ``observe`` for the next reward


@struct.dataclass
class DelayedTrackingState(TrackingState):
    """The state of an env with ``action_delay = 1``.  A subclass, so that undelayed envs
    (and the checkpoints of their training runs) keep the layout of :class:`TrackingState`."""

    prev_action: jax.Array  # (4,) action the next step applies (the hover action at reset)


class TrackingEnv(Env):
    """Quadrotor trajectory tracking; ``reset(rng) -> State``, ``step(state, a) -> State``.

    Works with Brax's ``VmapWrapper``, ``EpisodeWrapper`` and ``AutoResetWrapper``.
    (Brax's auto-reset replays each env's first reset state, hence its first track.)
    """

    def __init__(self, config: EnvConfig | None = None, **overrides):
        config = config or make_config("paper")
        if overrides:
            config = dataclasses.replace(config, **overrides)
        self.config = config
        c = config
        if c.track in ("train", "validation"):
            self._n_seg = tr.train_num_segments(c.horizon_steps, c.dt)
        else:
            self._n_seg = tr.num_segments_for(c.horizon_steps, c.tracks.los_segment_steps)
        self._noisy = c.wind_sigma > 0 or c.obs_noise_pos > 0 or c.obs_noise_vel > 0 or c.obs_noise_quat > 0
        self._effort_w = tuple(float(w) for w in c.effort_weights)
        self._rates_in_obs = c.quad.rate_model != "instant"

    # Brax Env interface ----------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return 20 if self._rates_in_obs else 17

    @property
    def action_size(self) -> int:
        return 4

    @property
    def backend(self) -> str:
        return "jax"

    @property
    def dt(self) -> float:
        """Seconds per env step."""
        return self.config.control_dt

    @property
    def episode_length(self) -> int:
        return self.config.episode_length

    @property
    def num_segments(self) -> int:
        """Static segment-table size of this env's tracks."""
        return self._n_seg

    def reset(self, rng: jax.Array) -> State:
        """New episode: a track drawn per ``config.track`` and an initial state (R5)."""
        k_track, k_rest = jax.random.split(rng)
        return self.reset_with_track(k_rest, self.sample_track(k_track))

    def sample_track(self, rng: jax.Array) -> tr.Track:
        """The track an episode uses under ``config.track``."""
        c, n = self.config, self._n_seg
        if c.track == "train":
            return tr.sample_train_track(rng, c.tracks, c.dt, c.horizon_steps, n)
        if c.track == "validation":
            bank = tr.validation_tracks(c.tracks, c.dt, c.horizon_steps, n)
            i = jax.random.randint(rng, (), 0, tr.NUM_VALIDATION_TRACKS)
            return jax.tree.map(lambda x: x[i], bank)
        if c.track == "spiral_rt":
            return tr.spiral_rt(c.tracks, n)
        return tr.los_test_track(c.los_seed, c.tracks, num_segments=n, dt=c.dt, horizon_steps=c.horizon_steps)

    def reset_with_track(self, rng: jax.Array, track: tr.Track) -> State:
        """New episode on a given track (used by evaluation over many tracks)."""
        c = self.config
        k_init, k_wind, k_next = jax.random.split(rng, 3)
        quad = self._initial_state(k_init, tr.position(track, 0, c.dt))
        f = quad.p.dtype
        wind = jnp.zeros(3, f)
        if c.wind_sigma > 0:
            wind = c.wind_sigma * jax.random.normal(k_wind, (3,), f)
        fields = dict(quad=quad, k=jnp.zeros((), jnp.int32), track=track, wind=wind, key=k_next)
        fields["ref_next"] = jnp.zeros(3, f)
        if c.action_delay:
            ps = DelayedTrackingState(**fields, prev_action=hover_action(c).astype(f))
        else:
            ps = TrackingState(**fields)
        obs, ps = self.observe(ps)
        zero = jnp.zeros((), f)
        metrics = {"tracking_error": zero, "energy": zero, "energy_sq": zero, "crashed": zero}
        info = {"truncation": zero, "terminated": zero}
        return State(pipeline_state=ps, obs=obs, reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """Apply ``action`` (4,) in [-1, 1] for ``action_repeat`` physics steps (with
        ``action_delay = 1``: apply the previous step's action and keep this one)."""
        c = self.config
        ps = state.pipeline_state
        a = jnp.clip(action, -1.0, 1.0).astype(ps.quad.p.dtype)
        if c.action_delay:
            a, ps = ps.prev_action, ps.replace(prev_action=a)
        u = action_to_control(c, a)
        effort = self._effort(a)
        zero = jnp.zeros((), ps.quad.p.dtype)
        carry = (ps.quad, ps.k, ps.wind, ps.key, zero, zero, jnp.zeros((), bool))
        if c.action_repeat == 1:
            carry, p_ref = self._substep(ps.track, u, effort, carry, ps.ref_next)
        else:  # one compiled body, whatever the repeat count
            carry, p_refs = jax.lax.scan(
                lambda cr, _: self._substep(ps.track, u, effort, cr), carry, None, c.action_repeat
            )
            p_ref = p_refs[-1]
        quad, k, wind, key, reward, err_sum, crashed = carry
        terminated = crashed if c.terminate else jnp.zeros((), bool)
        reward = reward - c.crash_penalty * terminated
        truncated = (k >= c.episode_steps) & ~terminated
        ps = ps.replace(quad=quad, k=k, wind=wind, key=key)
        obs, ps = self.observe(ps, p_ref)
        f = reward.dtype
        a_norm2 = jnp.sum(a * a)
        metrics = dict(state.metrics)  # keep keys that wrappers added (e.g. EvalWrapper)
        metrics.update(
            {
                "tracking_error": err_sum,  # Σ_k ||e_k|| over the physics steps, m
                "energy": c.action_repeat * jnp.sqrt(a_norm2),  # Σ ||a||
                "energy_sq": c.action_repeat * a_norm2,  # Σ aᵀa
                "crashed": crashed.astype(f),
            }
        )
        info = dict(state.info)
        info.update(truncation=truncated.astype(f), terminated=terminated.astype(f))
        return state.replace(
            pipeline_state=ps,
            obs=obs,
            reward=reward,
            done=(terminated | truncated).astype(f),
            metrics=metrics,
            info=info,
        )

    # pieces ------------------------------------------------------------------------------
    def _substep(self, track, u, effort, carry, p_ref=None):
        """One physics step of ``dt``: wind, RK4, tracking error, reward, crash flag.

        ``carry = (quad, k, wind, key, reward, err_sum, crashed)``; ``p_ref`` may pass
        p_d(k+1) when it is already known.  Returns the new carry and p_d(k+1)."""
        c = self.config
        quad, k, wind, key, reward, err_sum, crashed = carry
        if c.wind_sigma > 0:
            wind, key = ou_wind_step(c, wind, key)
        quad = rk4_step(
            c.quad, quad, u, c.dt, wind if c.wind_sigma > 0 else None, c.rk4_substeps, c.renormalize
        )
        k = k + 1
        step_r = -c.rho2 * effort
        if c.rho_vel > 0:
            p_ref, v_ref, _ = tr.evaluate(track, k, c.dt)
            step_r = step_r - c.rho_vel * jnp.linalg.norm(v_ref - quad.v)
        elif p_ref is None:
            p_ref = tr.position(track, k, c.dt)
        e = jnp.linalg.norm(p_ref - quad.p)
        finite = jnp.isfinite(e) & _finite(quad)
        step_r = step_r - c.rho1 * error_cost(c, e)
        if c.precision_bonus > 0:
            step_r = step_r - c.rho1 * c.precision_bonus * (1.0 - jnp.exp(-e / c.precision_scale))
        reward = reward + jnp.where(~crashed & finite, step_r, 0.0)
        err_sum = err_sum + jnp.where(finite, e, jnp.inf)
        crashed = crashed | ~finite | (e > c.e_max)
        return (quad, k, wind, key, reward, err_sum, crashed), p_ref

    def _effort(self, a: jax.Array) -> jax.Array:
        c = self.config
        if c.effort_hover_relative:
            a = a - hover_action(c).astype(a.dtype)
        w = jnp.asarray(self._effort_w, a.dtype)
        return jnp.sum(w * a * a)

    def _initial_state(self, rng: jax.Array, p0: jax.Array) -> QuadState:
        c = self.config
        f = p0.dtype
        if not c.randomize_init:
            return QuadState.hover(p0, f)
        u = jax.random.uniform(rng, (9,), f, -1.0, 1.0)  # one draw, sliced
        p = p0 + c.init_pos * u[0:3]
        v = c.init_vel * u[3:6]
        ang = math.pi * u[6]
        axis = jnp.stack([jnp.cos(ang), jnp.sin(ang), jnp.zeros((), f)])
        tilt = 0.5 * (u[7] + 1.0) * math.radians(c.init_tilt_deg)
        yaw = u[8] * math.radians(c.init_yaw_deg)
        q = quat_mul(
            quat_from_axis_angle(jnp.array([0.0, 0.0, 1.0], f), yaw), quat_from_axis_angle(axis, tilt)
        )
        return QuadState(p=p, v=v, q=q, w=jnp.zeros(3, f))

    def observe(self, ps: TrackingState, p_ref_now: jax.Array | None = None):
        """Observation (O1), and the state with its noise key advanced and ``ref_next``
        refreshed.  ``p_ref_now`` may pass p_d(k) when the caller already has it."""
        c = self.config
        x = ps.quad
        p, v, q = x.p, x.v, x.q
        if c.obs_noise_pos > 0 or c.obs_noise_vel > 0 or c.obs_noise_quat > 0:
            # jax.random here, not ttd3_jax.rng: the same draws, but fused with this arithmetic
            # they change the last bit of a few observations (tests/test_rng.py), and this runs
            # once per env step (robustness evaluation), not once per physics step
            key, kp, kv, kq = jax.random.split(ps.key, 4)
            p = p + c.obs_noise_pos * jax.random.normal(kp, (3,), p.dtype)
            v = v + c.obs_noise_vel * jax.random.normal(kv, (3,), p.dtype)
            q = q + c.obs_noise_quat * jax.random.normal(kq, (4,), p.dtype)
            q = q / jnp.linalg.norm(q)
            ps = ps.replace(key=key)
        if c.canonical_q_obs:
            q = jnp.where(q[0] < 0, -q, q)
        p_ahead = tr.position(ps.track, ps.k + c.lookahead_k, c.dt)
        p_next = p_ahead if c.lookahead_k == 1 else tr.position(ps.track, ps.k + 1, c.dt)
        ps = ps.replace(ref_next=p_next)
        if c.err_ref == "next":
            p_err = p_next
        else:
            p_err = tr.position(ps.track, ps.k, c.dt) if p_ref_now is None else p_ref_now
        err = jnp.linalg.norm(p_err - p)
        if c.obs_frame != "world":  # the relative frames put the origin at p_d,k
            p_now = tr.position(ps.track, ps.k, c.dt) if p_ref_now is None else p_ref_now
        if c.obs_frame == "track":  # same 17 numbers with the origin moved to p_d,k
            parts = [p - p_now, v, q, p_ahead - p_now, p_ahead - p, err[None]]
        elif c.obs_frame == "error":  # "track" with the velocity error pre-computed
            v_ref = (p_ahead - p_now) / (c.lookahead_k * c.dt)  # mean reference velocity ahead
            parts = [p - p_now, v - v_ref, q, p_ahead - p_now, v, err[None]]
        elif c.obs_frame == "heading":  # "track", then turned by -yaw about z
            turn, q_h = _remove_yaw(q)
            q_h = jnp.where(q_h[0] < 0, -q_h, q_h) if c.canonical_q_obs else q_h
            vecs = (p - p_now, v, p_ahead - p_now, p_ahead - p)
            parts = [turn(vecs[0]), turn(vecs[1]), q_h, turn(vecs[2]), turn(vecs[3]), err[None]]
        else:
            parts = [p, v, q, p_ahead, p_ahead - p, err[None]]
        if self._rates_in_obs:
            parts.append(x.w)
        # non-finite entries (a diverged state) read as 0, in one read of the concatenation
        return _zero_non_finite(jnp.concatenate(parts)), ps


def ou_wind_step(c: EnvConfig, wind: jax.Array, key: jax.Array):
    """One physics step (``c.dt``) of the OU wind acceleration ``wind`` (3,) m/s², with
    stationary std ``c.wind_sigma`` and correlation time ``c.wind_tau``; returns
    ``(wind, key)`` (one split and 3 normals of ``ttd3_jax.rng``)."""
    key, sub = rng.split(key)
    phi = math.exp(-c.dt / c.wind_tau)
    xi = rng.normal(sub, (3,), wind.dtype)
    return phi * wind + c.wind_sigma * math.sqrt(1.0 - phi * phi) * xi, key


def yaw_of(q: jax.Array) -> jax.Array:
    """Yaw ψ (rad) of the scalar-first unit quaternion ``q`` (z-y-x Euler angles)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _remove_yaw(q: jax.Array):
    """``(turn, q_h)``: ``turn(x)`` rotates a world vector by −ψ about z (into the heading
    frame) and ``q_h = q_z(−ψ) ⊗ q`` is the attitude with its yaw removed (tilt only)."""
    psi = yaw_of(q)
    cs, sn = jnp.cos(psi), jnp.sin(psi)

    def turn(x):
        return jnp.stack([cs * x[0] + sn * x[1], -sn * x[0] + cs * x[1], x[2]])

    half = 0.5 * psi
    q_unyaw = jnp.stack([jnp.cos(half), jnp.zeros_like(half), jnp.zeros_like(half), -jnp.sin(half)])
    return turn, quat_mul(q_unyaw, q)


@jax.custom_jvp
def _zero_non_finite(x: jax.Array) -> jax.Array:
    """``x`` with its NaN and inf entries set to +0.0 (the same values as
    ``jnp.where(jnp.isfinite(x), x, 0.0)``, and the same derivative).

    The test reads the exponent bits, so that ``x`` is used once: XLA:CPU then fuses the
    observation's concatenation into the mask instead of writing it out first
    (benchmarks/env_throughput.py)."""
    return _mask_bits(x)


def _mask_bits(x: jax.Array) -> jax.Array:
    f = jnp.finfo(x.dtype)
    ints = jnp.dtype(f"int{f.bits}")
    exp = ((1 << f.nexp) - 1) << f.nmant  # all exponent bits set: inf or NaN
    bits = jax.lax.bitcast_convert_type(x, ints)
    mask = jnp.asarray(exp, ints)
    return jax.lax.bitcast_convert_type(jnp.where(bits & mask == mask, 0, bits), x.dtype)


@_zero_non_finite.defjvp
def _zero_non_finite_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return _mask_bits(x), jnp.where(jnp.isfinite(x), t, 0.0)


def _finite(x: QuadState) -> jax.Array:
    """True when every state entry is finite (a NaN or inf anywhere makes the sum non-finite).

    The entries are added one by one rather than with ``jnp.sum``: a reduction would end
    the step's fusion on XLA:CPU (benchmarks/env_throughput.py)."""
    return jnp.isfinite(sum(leaf[..., i] for leaf in jax.tree.leaves(x) for i in range(leaf.shape[-1])))
