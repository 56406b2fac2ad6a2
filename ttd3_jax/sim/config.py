"""The tracking env's static configuration and presets.  :class:`EnvConfig` is validated on
construction, so a bad value fails before anything compiles; docs/paper-notes.md gives the
reading of the paper behind each default.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated

from tyro.conf import Suppress  # (a field the command line does not show)

from ttd3_jax import checks
from ttd3_jax.sim import track_families as tf
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.dynamics import QuadParams, validate_params
from ttd3_jax.sim.vehicles import MIXABLE_NAMES

TRACK_MODES = ("train", "validation", "spiral_rt", "los_rt")
ERR_REFS = ("current", "next")
ERR_COSTS = ("paper", "squared", "log")
OBS_FRAMES = ("world", "track")
PRESETS = ("paper", "practical")
PRIVILEGED_AHEAD_S = (0.5, 1.0)  # s after p_d,k+L of the critics' extra reference points (obs_privileged)
PREVIEW_MAX_S = 2.0  # s: the farthest reference point observation.preview_s may show the actor
CRASH_GAMMA = 0.99  # the discount the derived crash penalty is sized for (spec R4)
# the fields EnvConfig.for_eval sets, and the episode length it keeps (keep them together)
EVAL_PROTOCOL_FIELDS = ("track", "los_seed", "randomize_init", "terminate", "wind_sigma", "e_max",
                        "obs_noise_pos", "obs_noise_vel", "obs_noise_quat", "episode_steps",
                        "mass", "inertia", "thrust_max", "thrust_gain", "tau_rate", "rate_limit",
                        "rate_gains",
                        "drag", "latency", "obs_noise", "pos_bias", "wind_mean")  # fmt: skip
LATENCY_MAX_S = 0.05  # s: the largest actuation latency randomization.latency may draw
# the plant's ranges of RandomizationConfig (lo, hi) and their neutral value (the nominal plant)
PLANT_FACTORS = (
    "mass",
    "inertia",
    "thrust_max",
    "thrust_gain",
    "tau_rate",
    "rate_limit",
    "rate_gains",
    "drag",
)
FIRMWARE_FACTORS = ("rate_gains", "drag")  # ranges only the firmware rate model has a parameter for
PLANT_NEUTRAL = {**dict.fromkeys(PLANT_FACTORS, (1.0, 1.0)), "latency": (0.0, 0.0), "obs_noise": (1.0, 1.0),
                 "pos_bias": 0.0, "wind_mean": 0.0}  # fmt: skip
DT_MAX = 0.01  # s: the physics step the integrator is used with at most (the body-rate lag is 0.03 s)
EVAL_CRASH_M = 1.0  # m: every controller is judged crashed once its error exceeds this in evaluation


def _where(group: str, name: str) -> str:
    return f"EnvConfig.{group}.{name}"


@dataclasses.dataclass(frozen=True)
class VehicleConfig:
    """The vehicle, its integrator and the action map (D4, D5, D7, O2)."""

    quad: QuadParams = QuadParams()
    rk4_substeps: Annotated[int, Suppress] = 1
    renormalize: Annotated[bool, Suppress] = True
    hover_centered_thrust: bool = False  # a0 = 0 means hover thrust
    thrust_map_mass: Annotated[float | None, Suppress] = (
        None  # kg: mass whose hover thrust the action map assumes
    )
    #   under hover_centered_thrust (None = quad.mass); set to the nominal mass when quad.mass
    #   is changed, so that a mass error stays unknown to the action map (and the controller)

    def __post_init__(self):
        f = lambda name: _where("vehicle", name)  # noqa: E731
        checks.integer(f("rk4_substeps"), self.rk4_substeps, 1)
        for name in ("renormalize", "hover_centered_thrust"):
            checks.boolean(f(name), getattr(self, name))
        if self.thrust_map_mass is not None:
            checks.number(f("thrust_map_mass"), self.thrust_map_mass, 0, lo_open=True, unit=" or None")
        checks.instance(f("quad"), self.quad, QuadParams)
        validate_params(self.quad)


@dataclasses.dataclass(frozen=True)
class ObservationConfig:
    """What the policy observes (O1; the parts: ``sim.observation.layout``)."""

    canonical_q_obs: Annotated[bool, Suppress] = True  # observe q with qw >= 0
    err_ref: Annotated[str, Suppress] = "current"
    lookahead_k: int = 1  # physics steps ahead for the observed reference point
    obs_frame: Annotated[str, Suppress] = (
        "world"  # "track": positions relative to p_d,k (translation invariant)
    )
    # appended to the observation (not in the paper): the last applied action (4) and the
    # leaky integral ∫(p_d − p) dt (3, m·s, leak time constant memory_tau s)
    obs_memory: bool = False
    memory_tau: Annotated[float, Suppress] = 1.0  # s
    # appended last, for the critics only (the actor sees the observation without them):
    # the wind acceleration (3, m/s²) and p_d 0.5 s and 1 s after p_d,k+L, relative to it (6, m)
    obs_privileged: bool = False
    # the actor's preview of the reference: p_d these times (s) after p_d,k+L, relative to it (m)
    preview_s: tuple[float, ...] = ()
    # integral action around the policy (needs obs_memory; gain 0: off): every reference point
    # observed is shifted by s = clip(gain ∫ e dt, ±limit) per axis, e = p_d,k − p where
    # |e| < band, else 0 (no wind-up while far off the track)
    ref_integral_gain: float = 0.0  # 1/s
    ref_integral_band: Annotated[float, Suppress] = 0.005  # m
    ref_integral_limit: Annotated[float, Suppress] = 0.01  # m
    # leaky averages of the applied action, one per time constant (s): a short history of the
    # commands, from which the policy can tell what the rotors and rate loop are doing now
    action_history_s: Annotated[tuple[float, ...], Suppress] = ()

    def __post_init__(self):
        f = lambda name: _where("observation", name)  # noqa: E731
        t = self.preview_s
        ok = isinstance(t, tuple) and all(checks.is_number(x) and 0 < x <= PREVIEW_MAX_S for x in t)
        if not (ok and list(t) == sorted(set(t))):
            checks.fail(f("preview_s"), f"increasing times in (0, {PREVIEW_MAX_S:g}] s", t)
        checks.number(f("memory_tau"), self.memory_tau, 0, lo_open=True)
        h = self.action_history_s
        ok = isinstance(h, tuple) and all(checks.is_number(x) and 0 < x <= PREVIEW_MAX_S for x in h)
        if not (ok and list(h) == sorted(set(h))):
            checks.fail(f("action_history_s"), f"increasing time constants in (0, {PREVIEW_MAX_S:g}] s", h)
        if h and self.obs_memory is not True:
            checks.fail(f("action_history_s"), "() without obs_memory (which keeps the last action)", h)
        checks.number(f("ref_integral_gain"), self.ref_integral_gain, 0, 100, unit=" 1/s")
        for name in ("ref_integral_band", "ref_integral_limit"):
            checks.number(f(name), getattr(self, name), 0, 1, lo_open=True, unit=" m")
        if self.ref_integral_gain > 0 and self.obs_memory is not True:
            checks.fail(
                f("ref_integral_gain"),
                "0 without obs_memory (which keeps the integral)",
                self.ref_integral_gain,
            )
        checks.integer(f("lookahead_k"), self.lookahead_k, 1)
        checks.one_of(f("err_ref"), self.err_ref, ERR_REFS)
        checks.one_of(f("obs_frame"), self.obs_frame, OBS_FRAMES)
        for name in ("canonical_q_obs", "obs_memory", "obs_privileged"):
            checks.boolean(f(name), getattr(self, name))


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Reward and termination (R1-R4)."""

    err_cost: str = "paper"  # r_e: "paper" (e, or e² past 1 m), "squared", "log": ln(1 + e/err_scale)
    err_scale: Annotated[float, Suppress] = 0.02  # m, ε of err_cost="log"
    rho1: float = 1.0
    rho2: float = 0.01
    # not in the paper (0: off); set in Python (the cf2 preset's recipes: experiments/transfer_recipes.py)
    rho_rate: Annotated[float, Suppress] = 0.0  # ||a_k − a_k−1||² per physics step (needs obs_memory)
    rho_yaw: Annotated[float, Suppress] = 0.0  # heading cost ψ² (rad², the yaw of q) per physics step
    effort_weights: Annotated[tuple[float, float, float, float], Suppress] = (1.0, 1.0, 1.0, 1.0)  # diag Ω
    effort_hover_relative: Annotated[bool, Suppress] = False  # penalise (a - a_hover) instead of a
    terminate: Annotated[bool, Suppress] = True
    e_max: float = 2.0  # m
    # reward of a crash; None: rho1 r_e(e_max) action_repeat / (1 - 0.99), 400 for the paper
    crash_penalty: Annotated[float | None, Suppress] = None

    def __post_init__(self):
        f = lambda name: _where("reward", name)  # noqa: E731
        for name in ("e_max", "rho1", "err_scale"):
            checks.number(f(name), getattr(self, name), 0, lo_open=True)
        checks.number(f("rho2"), self.rho2, 0)
        checks.number(f("rho_rate"), self.rho_rate, 0)
        checks.number(f("rho_yaw"), self.rho_yaw, 0)
        if self.crash_penalty is not None:
            checks.number(f("crash_penalty"), self.crash_penalty, 0, unit=" or None")
        checks.one_of(f("err_cost"), self.err_cost, ERR_COSTS)
        for name in ("effort_hover_relative", "terminate"):
            checks.boolean(f(name), getattr(self, name))
        w = self.effort_weights
        if len(w) != 4 or not all(checks.is_number(x) and x >= 0 for x in w):
            checks.fail(f("effort_weights"), "4 finite numbers >= 0", w)


@dataclasses.dataclass(frozen=True)
class TracksConfig:
    """The tracks flown (T1-T8): which, the generators' settings, users' training tracks."""

    track: Annotated[str, Suppress] = "train"  # one of TRACK_MODES
    los_seed: Annotated[int, Suppress] = 0  # LOS-RT test instance when track == "los_rt"
    generator: Annotated[tr.TrackConfig, Suppress] = (
        tr.TrackConfig()
    )  # the Spiral, LOS and training-mixture generators
    # users' tracks in the training mixture (never the test or suite tracks)
    train_tracks: tuple[str, ...] = ()  # CSV files read by sim.custom_tracks.from_csv
    train_tracks_weight: float = 0.25  # probability that a training episode flies one of them
    # the wide training mixture (issue 37): one weight per family of sim.track_families.FAMILIES
    # (its WIDE_MIX is a default to start from); () = the paper's mixture (generator.train_mix).
    # Set, it also picks the validation tracks (track "validation", policy selection)
    wide_mix: tuple[float, ...] = ()

    def __post_init__(self):
        f = lambda name: _where("tracks", name)  # noqa: E731
        checks.one_of(f("track"), self.track, TRACK_MODES)
        checks.number(f("los_seed"), self.los_seed, 0)
        # (that each is a file is checked where a training env reads them, sim.env: a run whose
        # CSV has moved still loads for evaluation and export, which never read it)
        paths = self.train_tracks
        if not (isinstance(paths, tuple | list) and all(isinstance(p, str) and p for p in paths)):
            checks.fail(f("train_tracks"), "paths of CSV track files", paths)
        checks.number(f("train_tracks_weight"), self.train_tracks_weight, 0, 1, lo_open=True)
        checks.instance(f("generator"), self.generator, tr.TrackConfig)
        if not (isinstance(self.wide_mix, tuple | list) and len(self.wide_mix) == 0):
            tf.check_weights(f("wide_mix"), self.wide_mix)
            if self.generator.train_mix != tr.TrackConfig.train_mix:
                raise ValueError(
                    f"{f('wide_mix')} replaces generator.train_mix (the paper families' weights are its "
                    f"first three); allowed: one of them, got train_mix {self.generator.train_mix}"
                )


@dataclasses.dataclass(frozen=True)
class DisturbancesConfig:
    """What the controller does not command: wind, observation noise, latency (O3)."""

    wind_sigma: float = 0.0  # m/s^2, stationary std of the OU acceleration
    wind_tau: Annotated[float, Suppress] = 0.5  # s, OU correlation time
    obs_noise_pos: float = 0.0  # m, std
    obs_noise_vel: float = 0.0  # m/s, std
    obs_noise_quat: float = 0.0  # std on each quaternion component (then renormalised)
    action_delay: Annotated[int, Suppress] = 0  # control steps between an action and its application (0 or 1)

    def __post_init__(self):
        f = lambda name: _where("disturbances", name)  # noqa: E731
        checks.number(f("wind_tau"), self.wind_tau, 0, lo_open=True)
        for name in ("wind_sigma", "obs_noise_pos", "obs_noise_vel", "obs_noise_quat"):
            checks.number(f(name), getattr(self, name), 0)
        checks.one_of(f("action_delay"), self.action_delay, (0, 1))


@dataclasses.dataclass(frozen=True)
class RandomizationConfig:
    """What each training episode draws (R5): the initial state around the track's start, and
    the plant (domain randomisation, ``sim.randomization``).  A range ``(lo, hi)`` is drawn
    uniformly per episode; ``lo == hi`` fixes the value; the defaults are the nominal plant.
    Factors multiply the config's (or the given) vehicle's value; the action map stays the
    nominal vehicle's, so a controller does not learn of the draw through it."""

    randomize_init: bool = True
    init_pos: Annotated[float, Suppress] = 0.1  # m, ± per axis around p_d(0)
    init_vel: Annotated[float, Suppress] = 0.2  # m/s, ± per axis
    init_tilt_deg: Annotated[float, Suppress] = 10.0  # deg, max tilt about a random horizontal axis
    init_yaw_deg: Annotated[float, Suppress] = 15.0  # deg, ± yaw
    mass: tuple[float, float] = (1.0, 1.0)  # factor on quad.mass
    inertia: Annotated[tuple[float, float], Suppress] = (
        1.0,
        1.0,
    )  # factor on each axis of quad.inertia (drawn per axis)
    thrust_max: Annotated[tuple[float, float], Suppress] = (
        1.0,
        1.0,
    )  # factor on quad.thrust_max (the flown vehicle's limit)
    thrust_gain: tuple[float, float] = (1.0, 1.0)  # thrust produced / thrust commanded (thrust-map error)
    # an "instant" vehicle flies the first_order rate model when tau_rate is randomised (same observation)
    tau_rate: tuple[float, float] = (
        1.0,
        1.0,
    )  # factor on the rate lag: quad.tau_rate, or the rotors' (firmware)
    rate_gains: Annotated[tuple[float, float], Suppress] = (
        1.0,
        1.0,
    )  # factor on the firmware PID's kp, ki, kd
    drag: Annotated[tuple[float, float], Suppress] = (
        1.0,
        1.0,
    )  # factor on the firmware model's quad.loop.drag
    rate_limit: Annotated[tuple[float, float], Suppress] = (
        1.0,
        1.0,
    )  # factor on the body-rate limits rate_min, rate_max
    latency: tuple[float, float] = (0.0, 0.0)  # s, actuation latency, whole physics steps (round(x/dt))
    obs_noise: tuple[float, float] = (1.0, 1.0)  # factor on disturbances.obs_noise_* (the stds)
    pos_bias: float | tuple[float, float, float] = 0.0  # m, ± per axis: a constant bias of the observed
    #   position; a 3-tuple instead is that bias itself, the same every episode (robustness rows)
    wind_mean: float = 0.0  # m/s², ± per axis: a constant wind acceleration added to the OU wind
    # () = the config's vehicle; two of sim.vehicles.MIXABLE_NAMES: each episode flies one between them, known
    # to the policy (sim.vehicle_mix); quad then gives only rate_model, gravity, thrust_units. (a, a): a alone
    vehicles: tuple[str, ...] = ()

    def __post_init__(self):
        f = lambda name: _where("randomization", name)  # noqa: E731
        v = self.vehicles
        if not (isinstance(v, tuple | list) and len(v) in (0, 2) and all(n in MIXABLE_NAMES for n in v)):
            checks.fail(f("vehicles"), f"() or two names of {MIXABLE_NAMES} (a policy for both and every "
                        "vehicle between them)", v)  # fmt: skip
        object.__setattr__(self, "vehicles", tuple(v))
        checks.boolean(f("randomize_init"), self.randomize_init)
        for name in ("init_pos", "init_vel", "init_tilt_deg", "init_yaw_deg", "wind_mean"):
            checks.number(f(name), getattr(self, name), 0)
        if isinstance(self.pos_bias, tuple | list):
            if len(self.pos_bias) != 3 or not all(checks.is_number(x) for x in self.pos_bias):
                allowed = "a number >= 0 (± per axis) or a fixed bias (x, y, z) in m"
                checks.fail(f("pos_bias"), allowed, self.pos_bias)
            object.__setattr__(self, "pos_bias", tuple(float(x) for x in self.pos_bias))
        else:
            checks.number(f("pos_bias"), self.pos_bias, 0)
        for name in PLANT_FACTORS:
            _range(f(name), getattr(self, name), 0, None, lo_open=True)
        _range(f("obs_noise"), self.obs_noise, 0, None)
        _range(f("latency"), self.latency, 0, LATENCY_MAX_S, unit=" s (LATENCY_MAX_S)")


def _range(field: str, v, lo: float, hi: float | None, *, lo_open: bool = False, unit: str = "") -> None:
    """``v`` a range ``(lo, hi)``: 2 finite numbers within the bounds, the first <= the second."""
    bounds = checks.interval(lo, hi, lo_open, False)
    ok = isinstance(v, tuple | list) and len(v) == 2 and all(checks.is_number(x) for x in v)
    ok = ok and all((x > lo if lo_open else x >= lo) and (hi is None or x <= hi) for x in v)
    if not ok:
        checks.fail(field, f"a range (lo, hi) of 2 finite numbers {bounds}{unit}", v)
    if v[0] > v[1]:
        checks.fail(field, "a range (lo, hi) with lo <= hi", v)


GROUPS = {"vehicle": VehicleConfig, "observation": ObservationConfig, "reward": RewardConfig,
          "tracks": TracksConfig, "disturbances": DisturbancesConfig,
          "randomization": RandomizationConfig}  # fmt: skip
# every field of the groups, by name (the names are unique across groups) -> its group
FIELD_GROUP = {f.name: g for g, kind in GROUPS.items() for f in dataclasses.fields(kind)}


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static environment configuration: the clock, then one group per concern (units in
    comments).  Validated on construction; :meth:`replace` sets fields by name."""

    dt: float = 1e-3  # s, physics (RK4) step
    episode_steps: int = 3000  # physics steps per episode (3 s)
    action_repeat: int = 1  # physics steps per control step (T1, T9)
    vehicle: VehicleConfig = VehicleConfig()
    observation: ObservationConfig = ObservationConfig()
    reward: RewardConfig = RewardConfig()
    tracks: TracksConfig = TracksConfig()
    disturbances: DisturbancesConfig = DisturbancesConfig()
    randomization: RandomizationConfig = RandomizationConfig()

    def __post_init__(self):
        _validate(self)

    # derived quantities -------------------------------------------------------------
    @property
    def control_dt(self) -> float:
        """Seconds per env step."""
        return self.dt * self.action_repeat

    @property
    def action_history_keep(self) -> tuple[float, ...]:
        """exp(-control_dt / τ) for each τ of ``observation.action_history_s``: what each average
        of the action history keeps of itself per control step (the env's and the export's)."""
        return tuple(math.exp(-self.control_dt / t) for t in self.observation.action_history_s)

    @property
    def episode_length(self) -> int:
        """Env (control) steps per episode."""
        return self.episode_steps // self.action_repeat

    @property
    def horizon_steps(self) -> int:
        """Physics steps at which a reference point may be read."""
        o = self.observation
        ahead = (PRIVILEGED_AHEAD_S if o.obs_privileged else ()) + o.preview_s
        return self.episode_steps + o.lookahead_k + 2 + round(max(ahead, default=0) / self.dt)

    @property
    def crash_cost(self) -> float:
        """The reward a crash costs: ``crash_penalty``, or by default what staying at
        ``e_max`` would cost for ever, ρ₁ r_e(e_max) · action_repeat / (1 − 0.99)."""
        r = self.reward
        if r.crash_penalty is not None:
            return r.crash_penalty
        return r.rho1 * error_cost_value(self, r.e_max) * self.action_repeat / (1 - CRASH_GAMMA)

    def replace(self, **changes) -> EnvConfig:
        """This config with ``changes``: its own fields (the clock, whole groups) or any
        group's field by its name (``wind_sigma=0.5`` sets ``disturbances.wind_sigma``)."""
        return _replace(self, **changes)

    @staticmethod
    def path(name: str) -> str:
        """Where field ``name`` sits: ``group.name`` for a group's field, else ``name``."""
        return f"{FIELD_GROUP[name]}.{name}" if name in FIELD_GROUP and name not in GROUPS else name

    def get(self, name: str):
        """The value of field ``name``: its own, or any group's by its name (as :meth:`replace`)."""
        group, _, field = self.path(name).rpartition(".")
        return getattr(getattr(self, group) if group else self, field)

    def for_eval(self, track: str, los_seed: int = 0, wind_sigma: float = 0.0) -> EnvConfig:
        """The evaluation protocol (spec §2.5): fixed track, start on p_d(0) at rest and
        level, no early termination, no observation noise, optional wind, and one crash
        threshold for every controller (``e_max = EVAL_CRASH_M``), and the nominal plant (no
        domain randomisation: ``PLANT_NEUTRAL``).  It sets the fields in
        ``EVAL_PROTOCOL_FIELDS`` (``episode_steps`` stays: 3000, the paper's), and with
        ``randomization.vehicles`` flies the first of them (``vehicle_mix.pin_vehicle``: another)."""
        quiet = dict(randomize_init=False, terminate=False, e_max=EVAL_CRASH_M, obs_noise_pos=0.0,
                     obs_noise_vel=0.0, obs_noise_quat=0.0, **PLANT_NEUTRAL)  # fmt: skip
        return vm.pin_vehicle(self).replace(track=track, los_seed=los_seed, wind_sigma=wind_sigma, **quiet)


def _replace(cfg: EnvConfig, **changes) -> EnvConfig:
    own = {f.name for f in dataclasses.fields(EnvConfig)}
    unknown = sorted(set(changes) - own - set(FIELD_GROUP))
    if unknown:
        raise ValueError(f"unknown EnvConfig field(s) {unknown}; allowed: {sorted(own | set(FIELD_GROUP))}")
    top = {k: v for k, v in changes.items() if k in own}
    for group in GROUPS:
        mine = {k: v for k, v in changes.items() if FIELD_GROUP.get(k) == group and k not in own}
        if mine:
            top[group] = dataclasses.replace(top.get(group, getattr(cfg, group)), **mine)
    return dataclasses.replace(cfg, **top) if top else cfg


def error_cost_value(c: EnvConfig, e: float) -> float:
    """r_e(e) for a Python float ``e`` (m); ``sim.env.error_cost`` is the traced one."""
    if c.reward.err_cost == "squared":
        return e * e
    if c.reward.err_cost == "log":
        return math.log1p(e / c.reward.err_scale)
    return e if e * e <= 1 else e * e


def _validate(c: EnvConfig) -> None:
    """Raise ``ValueError`` naming the bad field, its value and what is allowed (each group
    checks its own fields; these are the clock and the checks across groups)."""
    checks.number("EnvConfig.dt", c.dt, 0, DT_MAX, lo_open=True,
                  unit=" s (the RK4 physics step; the paper's is 0.001 s, control steps are longer "
                       "through action_repeat)")  # fmt: skip
    for name in ("episode_steps", "action_repeat"):
        checks.integer(f"EnvConfig.{name}", getattr(c, name), 1)
    for group, kind in GROUPS.items():
        checks.instance(f"EnvConfig.{group}", getattr(c, group), kind)
    if c.observation.lookahead_k > c.episode_steps:
        checks.fail("EnvConfig.observation.lookahead_k", f"<= episode_steps ({c.episode_steps}: a reference "
                    "point past the episode's end)", c.observation.lookahead_k)  # fmt: skip
    if not c.tracks.train_tracks and c.tracks.train_tracks_weight != TracksConfig.train_tracks_weight:
        why = f"{TracksConfig.train_tracks_weight} without train_tracks (the share of episodes that fly them)"
        checks.fail("EnvConfig.tracks.train_tracks_weight", why, c.tracks.train_tracks_weight)
    if c.reward.rho_rate > 0 and not c.observation.obs_memory:
        checks.fail("EnvConfig.reward.rho_rate", "0 without observation.obs_memory (the policy must see the "
                    "last action its cost compares with)", c.reward.rho_rate)  # fmt: skip
    if c.observation.obs_memory and c.disturbances.action_delay:
        raise ValueError(
            "EnvConfig.observation.obs_memory needs disturbances.action_delay 0 (the delayed env keeps "
            "its own last action)"
        )
    _validate_plant(c)
    if c.episode_steps % c.action_repeat:
        raise ValueError(
            f"EnvConfig.episode_steps ({c.episode_steps}) must be a multiple of action_repeat "
            f"({c.action_repeat})"
        )


def plant_is_nominal(r: RandomizationConfig) -> bool:
    """True when every range of the plant is at its neutral value (no domain randomisation)."""
    same = lambda v, n: tuple(v) == n if isinstance(n, tuple) else v == n  # noqa: E731
    return all(same(getattr(r, k), n) for k, n in PLANT_NEUTRAL.items())


def _validate_plant(c: EnvConfig) -> None:
    """The checks of the randomised plant across groups: the flown vehicle must hover (each end of
    ``vehicles``: thrust-to-weight is geometric between them), in the shared units with ``vehicles``."""
    r, v = c.randomization, c.vehicle
    if r.vehicles:
        vm.check_units(c)
    for q in [vm.flown_as(n, v.quad) for n in dict.fromkeys(r.vehicles)] or [v.quad]:
        _validate_hover(c, q)


def _validate_hover(c: EnvConfig, q: QuadParams) -> None:
    r = c.randomization
    if tuple(r.tau_rate) != PLANT_NEUTRAL["tau_rate"] and q.rate_model == "torque":
        checks.fail("EnvConfig.randomization.tau_rate", "(1.0, 1.0) with rate_model 'torque' (which has no "
                    "time constant; randomise inertia)", r.tau_rate)  # fmt: skip
    for name in FIRMWARE_FACTORS:
        if tuple(getattr(r, name)) != PLANT_NEUTRAL[name] and q.rate_model != "firmware":
            checks.fail(f"EnvConfig.randomization.{name}", f"(1.0, 1.0) with rate_model {q.rate_model!r} "
                        "(only the 'firmware' model has a rate PID and drag)", getattr(r, name))  # fmt: skip
    # the most thrust the flown vehicle gives: the action map's maximum times the gain, up to
    # its own (randomised) limit; hover needs the heaviest draw's weight (newton units)
    most = q.thrust_max * min(r.thrust_gain[0], r.thrust_max[0])
    hover = q.hover_thrust * (r.mass[1] if q.thrust_units == "newton" else 1.0)
    if plant_is_nominal(r):
        return  # the vehicle's own check holds
    if most <= hover:
        raise ValueError(
            f"EnvConfig.randomization.mass, thrust_max, thrust_gain must let every drawn vehicle hover: "
            f"quad.thrust_max x min(thrust_gain lo, thrust_max lo) = {most:.3f} must be > hover thrust x "
            f"mass hi = {hover:.3f}, got mass={r.mass}, thrust_max={r.thrust_max}, "
            f"thrust_gain={r.thrust_gain}"
        )


def make_config(preset: str = "paper", **overrides) -> EnvConfig:
    """A named, documented configuration, with ``overrides`` (as :meth:`EnvConfig.replace` takes them) on top.

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
    return EnvConfig().replace(**{**base, **overrides})
