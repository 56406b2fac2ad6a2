"""Quadrotor trajectory-tracking environment with the Brax ``Env`` API (spec §2.2).

One control step (``env.step``) applies a normalised action ``a ∈ [-1, 1]^4`` for
``action_repeat`` physics steps of ``dt`` seconds (one 1 ms RK4 step in the ``paper``
preset); the configuration is :class:`~ttd3_jax.sim.config.EnvConfig`.

Observation at physics step k (raw units, O1), the parts of :func:`ttd3_jax.sim.observation.layout`::

    [p_k (3, m), v_k (3, m/s), q_k (4, qw>=0), p_d,k+L (3, m), p_d,k+L - p_k (3, m),
     ||p_d,k' - p_k|| (1, m)]          (+ ω_k (3, rad/s) for the first_order/torque models)

with L = ``lookahead_k`` (1 in the paper) and k' = k (``err_ref="current"``) or k+1.
``obs_frame="track"`` moves the origin of the two absolute positions to p_d,k.
``obs_memory``, ``randomization.vehicles`` (the known vehicle) and ``obs_privileged`` append the
parts the layout names after these.
Reward per physics step, with e' = ||p_d,k+1 - p_k+1|| after the step (R1-R3)::

    r = -rho1 * r_e(e') - rho2 * aᵀ Ω a,   r_e(e) = e if e² <= 1 else e²

summed over the ``action_repeat`` physics steps (not in the paper, 0 by default: minus
``rho_rate`` ||a − a_prev||², the change from the last control step's action, and minus
``rho_yaw`` ψ'², the heading after the step).  An episode terminates (crash)
when e' > ``e_max`` or the state is not finite, with reward ``-crash_cost``,
and is truncated (``info["truncation"] = 1``) after ``episode_steps`` physics steps.
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp

from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import observation
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim import track_families as tf
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import PRIVILEGED_AHEAD_S, EnvConfig, make_config
from ttd3_jax.sim.dynamics import (
    QuadParams,
    QuadState,
    clip_control,
    model_state,
    quat_from_axis_angle,
    quat_mul,
    rk4_step,
    yaw_of,
)
from ttd3_jax.sim.env_api import Env, State
from ttd3_jax.sim.env_state import (
    DelayedTrackingState,
    HistoryMemoryState,
    HistoryRandomizedState,
    IntegralMemoryState,
    IntegralRandomizedState,
    MemoryTrackingState,
    RandomizedTrackingState,
    TrackingState,
    reference_shift,
)

# -- the action map: a normalised action <-> thrust and body rates of the nominal vehicle (O2)


def thrust_range(cfg: EnvConfig, quad: QuadParams | None = None):
    """``(min, max, hover)`` collective thrust of the action map (N, or the thrust units)."""
    if quad is not None:  # a nominal vehicle of randomization.vehicles (thrust_map_mass None)
        return quad.thrust_min, quad.thrust_max, quad.hover_thrust
    q = cfg.vehicle.quad
    hover = q.hover_thrust
    if cfg.vehicle.thrust_map_mass is not None and q.thrust_units == "newton":
        hover = q.gravity * cfg.vehicle.thrust_map_mass
    return q.thrust_min, q.thrust_max, hover


def action_to_control(cfg: EnvConfig, a: jax.Array, quad: QuadParams | None = None) -> jax.Array:
    """Normalised action (..., 4) in [-1, 1] -> physical control ``[thrust, ω_cmd]`` (O2).

    Default: thrust = f_min + (a0 + 1)/2 (f_max - f_min); rates affine onto
    [rate_min, rate_max].  ``hover_centered_thrust`` maps a0 = 0 to the hover thrust.
    """
    lo, hi, hover = thrust_range(cfg, quad)
    a0 = a[..., 0]
    if cfg.vehicle.hover_centered_thrust:
        f = jnp.where(a0 >= 0, hover + a0 * (hi - hover), hover + a0 * (hover - lo))
    else:
        f = lo + 0.5 * (a0 + 1.0) * (hi - lo)
    q = cfg.vehicle.quad if quad is None else quad
    rlo, rhi = q.rate_min, q.rate_max
    w = rlo + 0.5 * (a[..., 1:] + 1.0) * (rhi - rlo)
    return jnp.concatenate([f[..., None], w], -1)


def control_to_action(cfg: EnvConfig, u: jax.Array, quad: QuadParams | None = None) -> jax.Array:
    """Inverse of :func:`action_to_control` (for controllers with physical outputs)."""
    lo, hi, hover = thrust_range(cfg, quad)
    f = u[..., 0]
    if cfg.vehicle.hover_centered_thrust:
        a0 = jnp.where(f >= hover, (f - hover) / (hi - hover), (f - hover) / (hover - lo))
    else:
        a0 = 2.0 * (f - lo) / (hi - lo) - 1.0
    q = cfg.vehicle.quad if quad is None else quad
    rlo, rhi = q.rate_min, q.rate_max
    aw = 2.0 * (u[..., 1:] - rlo) / (rhi - rlo) - 1.0
    return jnp.concatenate([a0[..., None], aw], -1)


def hover_action(cfg: EnvConfig, quad: QuadParams | None = None) -> jax.Array:
    """Normalised action that holds hover (a0 = 0.4715 with the paper's numbers).  With
    ``thrust_map_mass`` set: the hover action of that (nominal) mass."""
    u = jnp.array([thrust_range(cfg, quad)[2], 0.0, 0.0, 0.0])
    return control_to_action(cfg, u, quad)


# -- the tracks a config trains and is selected on: the paper's mixture, or the wide one ---


def mixture_num_segments(cfg: EnvConfig) -> int:
    """Track-table size of the training mixture and the validation tracks of ``cfg``: the paper
    mixture's, or the wide mixture's when ``tracks.wide_mix`` is set (users' tracks may need more)."""
    if cfg.tracks.wide_mix:
        return tf.wide_num_segments(cfg.horizon_steps, cfg.dt)
    return tr.train_num_segments(cfg.horizon_steps, cfg.dt)


def validation_tracks(cfg: EnvConfig, num_segments: int | None = None) -> tr.Track:
    """The fixed validation tracks of ``cfg`` (batched; the only tracks a policy is selected
    on): the paper mixture's 10, or the wide mixture's (``track_families.wide_validation_tracks``,
    2 per family of positive weight) when ``tracks.wide_mix`` is set."""
    t, n = cfg.tracks, num_segments or mixture_num_segments(cfg)
    if t.wide_mix:
        return tf.wide_validation_tracks(t.wide_mix, cfg.dt, cfg.horizon_steps, n, cfg=t.generator)
    return tr.validation_tracks(t.generator, cfg.dt, cfg.horizon_steps, n)


def num_validation_tracks(cfg: EnvConfig) -> int:
    """How many tracks :func:`validation_tracks` holds."""
    if cfg.tracks.wide_mix:
        return len(tf.wide_validation_families(cfg.tracks.wide_mix))
    return tr.NUM_VALIDATION_TRACKS


# -- numerics: the OU wind step, non-finite masks (each written for XLA:CPU's fusion) ------


def ou_wind_step(c: EnvConfig, wind: jax.Array, key: jax.Array):
    """One physics step (``c.dt``) of the OU wind acceleration ``wind`` (3,) m/s², with
    stationary std ``c.disturbances.wind_sigma`` and correlation time ``c.disturbances.wind_tau``; returns
    ``(wind, key)`` (one split and 3 normals of ``jax.random``)."""
    key, sub = jax.random.split(key)
    phi = math.exp(-c.dt / c.disturbances.wind_tau)
    xi = jax.random.normal(sub, (3,), wind.dtype)
    return phi * wind + c.disturbances.wind_sigma * math.sqrt(1.0 - phi * phi) * xi, key


@jax.custom_jvp
def _zero_non_finite(x: jax.Array) -> jax.Array:
    """``x`` with its NaN and inf entries set to +0.0, as ``jnp.where(jnp.isfinite(x), x, 0)``
    (values and derivative), but testing the exponent bits so that ``x`` is read once: XLA:CPU
    then fuses the observation's concatenation into the mask instead of writing it out."""
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
    """True when every state entry is finite (a NaN or inf anywhere makes the sum non-finite);
    added one by one, since a ``jnp.sum`` reduction would end the step's fusion on XLA:CPU."""
    return jnp.isfinite(sum(leaf[..., i] for leaf in jax.tree.leaves(x) for i in range(leaf.shape[-1])))


# -- the env -------------------------------------------------------------------------------


_USER_TAG = 0x05E7  # folded into a reset's track key to pick users' training tracks


def error_cost(cfg: EnvConfig, e: jax.Array) -> jax.Array:
    """r_e(e) of eq. 3 (``err_cost="paper"``), e² (``"squared"``) or ln(1 + e/ε) (``"log"``); e in m."""
    if cfg.reward.err_cost == "log":
        return jnp.log1p(e / cfg.reward.err_scale)
    if cfg.reward.err_cost == "squared":
        return e * e
    return jnp.where(e * e <= 1.0, e, e * e)


LONG_TRACK = 100  # a training track may last this many times the reference an episode flies


def _training_track(c: EnvConfig, path: str) -> tr.Track:
    """A user's training track, refused when it lasts over :data:`LONG_TRACK` times the reference
    an episode flies: every env keeps the longest track's whole table, so the rest only costs
    memory and speed.  A path that is not a file is refused, naming it."""
    if not os.path.isfile(path):
        raise ValueError(f"task.tracks.train_tracks: {path!r} is not a file; allowed: CSV track files")
    track = ct.from_csv(path, dt=c.dt)
    flown = c.horizon_steps * c.dt
    if track.duration_s > LONG_TRACK * flown:
        raise ValueError(f"task.tracks.train_tracks: {path} lasts {track.duration_s:,.0f} s, but an episode "
                         f"flies {flown:.2f} s of reference and every training env keeps the whole track: "
                         f"cut it to at most {LONG_TRACK * flown:,.0f} s")  # fmt: skip
    return track.track()


class TrackingEnv(Env):
    """Quadrotor trajectory tracking; ``reset(rng) -> State``, ``step(state, a) -> State``.

    Works with Brax's ``VmapWrapper``, ``EpisodeWrapper`` and ``AutoResetWrapper``.
    (Brax's auto-reset replays each env's first reset state, hence its first track.)

    ``track_rows`` (with ``train_tracks``): build the training env of a run that is read, not
    trained (evaluation, export): users' CSV files are not read (they may have moved since),
    and the track tables take the size the run saved, ``track_rows``, at least the mixture's.
    Its shapes are the trained env's; its draws leave the users' tracks out.
    """

    def __init__(self, config: EnvConfig | None = None, *, track_rows: int | None = None, **overrides):
        config = config or make_config("paper")
        if overrides:
            config = config.replace(**overrides)
        self.config = config
        c = config
        if c.tracks.track in ("train", "validation"):
            self._n_seg = mixture_num_segments(c)
        else:
            self._n_seg = tr.num_segments_for(c.horizon_steps, c.tracks.generator.los_segment_steps)
        self._user = None  # users' training tracks, stacked, with the mixture's table size
        if c.tracks.track == "train" and c.tracks.train_tracks and track_rows is not None:
            self._n_seg = max(self._n_seg, track_rows)
        elif c.tracks.track == "train" and c.tracks.train_tracks:
            user = [_training_track(c, p) for p in c.tracks.train_tracks]
            self._mix_n, self._n_seg = self._n_seg, max(self._n_seg, *(t.num_segments for t in user))
            self._user = jax.tree.map(lambda *x: jnp.stack(x), *(ct.pad(t, self._n_seg, c.dt) for t in user))
        self._effort_w = tuple(float(w) for w in c.reward.effort_weights)
        self.layout = observation.layout(c)  # the named parts of the observation
        self._randomized = rz.active(c)  # static: domain randomisation (RandomizedTrackingState)

    # the Brax Env interface; dt is seconds per env step, num_segments the static track-table size
    actor_observation_size = property(lambda self: self.layout.actor_size)
    observation_size = property(lambda self: self.layout.size)
    action_size = property(lambda self: 4)
    backend = property(lambda self: "jax")
    dt = property(lambda self: self.config.control_dt)
    episode_length = property(lambda self: self.config.episode_length)
    num_segments = property(lambda self: self._n_seg)

    def reset(self, rng: jax.Array, vehicle: QuadParams | None = None) -> State:
        """New episode: a track drawn per ``config.tracks.track`` and an initial state (R5), flying
        ``vehicle`` (None: the config's ``quad``; see :meth:`reset_with_track`)."""
        k_track, k_rest = jax.random.split(rng)
        return self.reset_with_track(k_rest, self.sample_track(k_track), vehicle)

    def sample_track(self, rng: jax.Array) -> tr.Track:
        """The track an episode uses under ``config.tracks.track``."""
        c, n = self.config, self._n_seg
        if c.tracks.track == "train":  # the paper's mixture, or the wide one (sim.track_families)
            t, n_mix = c.tracks, n if self._user is None else self._mix_n
            if t.wide_mix:
                mix = tf.sample_wide_track(rng, t.wide_mix, c.dt, c.horizon_steps, n_mix, cfg=t.generator)
            else:
                mix = tr.sample_train_track(rng, t.generator, c.dt, c.horizon_steps, n_mix)
            if self._user is None:
                return mix
            mix = ct.pad(mix, n, c.dt)
            k_pick, k_use = jax.random.split(jax.random.fold_in(rng, _USER_TAG))
            user = jax.tree.map(
                lambda x: x[jax.random.randint(k_pick, (), 0, len(c.tracks.train_tracks))], self._user
            )
            use = jax.random.uniform(k_use) < c.tracks.train_tracks_weight
            return jax.tree.map(lambda a, b: jnp.where(use, a, b), user, mix)
        if c.tracks.track == "validation":
            bank = validation_tracks(c, n)
            i = jax.random.randint(rng, (), 0, num_validation_tracks(c))
            return jax.tree.map(lambda x: x[i], bank)
        if c.tracks.track == "spiral_rt":
            return tr.spiral_rt(c.tracks.generator, n)
        return tr.los_test_track(
            c.tracks.los_seed, c.tracks.generator, num_segments=n, dt=c.dt, horizon_steps=c.horizon_steps
        )

    def reset_with_track(self, rng: jax.Array, track: tr.Track, vehicle: QuadParams | None = None) -> State:
        """New episode on a given track (used by evaluation over many tracks), flying
        ``vehicle`` (``randomization.vehicle_arrays``; None: the config's ``quad``, as constants)."""
        c = self.config
        k_init, k_wind, k_next = jax.random.split(rng, 3)
        quad = self._initial_state(k_init, tr.position(track, 0, c.dt))
        f = quad.p.dtype
        wind = jnp.zeros(3, f)
        if c.disturbances.wind_sigma > 0:
            wind = c.disturbances.wind_sigma * jax.random.normal(k_wind, (3,), f)
        # the plant, drawn around ``vehicle`` (a key folded off rng's other draws)
        plant = rz.draw(c, rng, vehicle, f) if self._randomized else None
        flown = plant.quad if plant is not None else (c.vehicle.quad if vehicle is None else vehicle)
        fields = dict(  # (firmware: the rotors hold the flown vehicle's weight)
            quad=model_state(flown, quad), k=jnp.zeros((), jnp.int32), track=track, wind=wind, key=k_next
        )
        fields["ref_next"] = jnp.zeros(3, f)
        if self._randomized:
            hover = hover_action(c, rz.nominal_vehicle(plant)).astype(f)  # the known vehicle's map
            pending = jnp.broadcast_to(hover, (rz.pending_size(c), 4))
            ps = RandomizedTrackingState(**fields, plant=plant, pending=pending, last_action=jnp.zeros(4, f),
                                         err_int=jnp.zeros(3, f))  # fmt: skip
        elif c.disturbances.action_delay:
            ps = DelayedTrackingState(**fields, prev_action=hover_action(c).astype(f))
        elif c.observation.obs_memory:
            ps = MemoryTrackingState(**fields, last_action=jnp.zeros(4, f), err_int=jnp.zeros(3, f))
        else:
            ps = TrackingState(**fields)
        # (obs_memory: one of the two above; the history's state holds ref_int, unread at gain 0)
        if c.observation.ref_integral_gain > 0 or c.observation.action_history_s:
            kind = IntegralRandomizedState if self._randomized else IntegralMemoryState
            ps = kind(**vars(ps), ref_int=jnp.zeros(3, f))
        if c.observation.action_history_s:
            kind = HistoryRandomizedState if self._randomized else HistoryMemoryState
            ps = kind(**vars(ps), act_hist=jnp.zeros((len(c.observation.action_history_s), 4), f))
        obs, ps = self.observe(ps)
        zero = jnp.zeros((), f)
        metrics = {"tracking_error": zero, "energy": zero, "energy_sq": zero, "crashed": zero}
        info = {"truncation": zero, "terminated": zero}
        if vehicle is not None:  # only then: a nominal env keeps its state's layout (and checkpoints)
            info["vehicle"] = rz.vehicle_arrays(vehicle, f)
        return State(pipeline_state=ps, obs=obs, reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """Apply ``action`` (4,) in [-1, 1] for ``action_repeat`` physics steps (with
        ``action_delay = 1``: apply the previous step's action and keep this one)."""
        c = self.config
        ps = state.pipeline_state
        a = jnp.clip(action, -1.0, 1.0).astype(ps.quad.p.dtype)
        if self._randomized:
            return self._step_randomized(state, a)
        if c.disturbances.action_delay:
            a, ps = ps.prev_action, ps.replace(prev_action=a)
        u = action_to_control(c, a)  # the action map of the config's (nominal) vehicle
        effort = self._effort(a, ps)
        zero = jnp.zeros((), ps.quad.p.dtype)
        carry = (ps.quad, ps.k, ps.wind, ps.key, zero, zero, jnp.zeros((), bool))
        quad = state.info.get("vehicle", c.vehicle.quad)  # the vehicle flown
        if c.action_repeat == 1:
            carry, p_ref = self._substep(quad, ps.track, u, effort, carry, ps.ref_next)
        else:  # one compiled body, whatever the repeat count
            carry, p_refs = jax.lax.scan(
                lambda cr, _: self._substep(quad, ps.track, u, effort, cr), carry, None, c.action_repeat
            )
            p_ref = p_refs[-1]
        return self._finish(state, ps, a, carry, p_ref)

    def _step_randomized(self, state: State, a: jax.Array) -> State:
        """:meth:`step` of the randomised plant: the nominal action map (the drawn nominal
        vehicle's under ``vehicles``), then the plant's thrust gain and box, the latency's choice
        of command per physics step, its wind."""
        c = self.config
        ps = state.pipeline_state
        plant, m, known = ps.plant, rz.pending_size(c), rz.nominal_vehicle(ps.plant)
        if m:  # substep j applies the command given commanded_lags[j] control steps ago
            stack = jnp.concatenate([a[None], ps.pending])
            u = action_to_control(c, stack[rz.commanded_lags(c, plant.latency)], known)  # (R, 4)
            ps = ps.replace(pending=stack[:m])
        else:
            u = jnp.broadcast_to(action_to_control(c, a, known), (c.action_repeat, 4))
        u = clip_control(plant.quad, u.at[:, 0].multiply(plant.thrust_gain))
        effort = self._effort(a, ps)  # of the commanded action
        zero = jnp.zeros((), ps.quad.p.dtype)
        carry = (ps.quad, ps.k, ps.wind, ps.key, zero, zero, jnp.zeros((), bool))
        wind_mean = plant.wind_mean if c.randomization.wind_mean > 0 else None
        if c.action_repeat == 1:
            carry, p_ref = self._substep(plant.quad, ps.track, u[0], effort, carry, ps.ref_next, wind_mean)
        else:
            carry, p_refs = jax.lax.scan(
                lambda cr, uj: self._substep(plant.quad, ps.track, uj, effort, cr, None, wind_mean), carry, u
            )
            p_ref = p_refs[-1]
        return self._finish(state, ps, a, carry, p_ref)

    def _finish(self, state: State, ps: TrackingState, a: jax.Array, carry, p_ref) -> State:
        """The end of a step: termination, memory, observation, metrics (``a``: the action
        the step applied, the commanded one under randomisation)."""
        c = self.config
        quad, k, wind, key, reward, err_sum, crashed = carry
        terminated = crashed if c.reward.terminate else jnp.zeros((), bool)
        reward = reward - c.crash_cost * terminated
        truncated = (k >= c.episode_steps) & ~terminated
        ps = ps.replace(quad=quad, k=k, wind=wind, key=key)
        if self._randomized:
            ps = ps.replace(last_action=a)
        if c.observation.obs_memory:
            ps = ps.replace(last_action=a)
        if c.observation.action_history_s:
            keep = jnp.asarray(c.action_history_keep, a.dtype)[:, None]
            ps = ps.replace(act_hist=keep * ps.act_hist + (1.0 - keep) * a)
        obs, ps = self.observe(ps, p_ref, integrate=True)
        f = reward.dtype
        a_norm2 = jnp.sum(a * a)
        # Σ_k ||e_k|| (m) over the physics steps, Σ ||a||, Σ aᵀa; keeping keys that wrappers added
        metrics = {**state.metrics, "tracking_error": err_sum, "energy": c.action_repeat * jnp.sqrt(a_norm2),
                   "energy_sq": c.action_repeat * a_norm2, "crashed": crashed.astype(f)}  # fmt: skip
        info = {**state.info, "truncation": truncated.astype(f), "terminated": terminated.astype(f)}
        done = (terminated | truncated).astype(f)
        return state.replace(pipeline_state=ps, obs=obs, reward=reward, done=done, metrics=metrics, info=info)

    def _substep(self, params, track, u, effort, carry, p_ref=None, wind_mean=None):
        """One physics step of ``dt`` of vehicle ``params``: wind, RK4, tracking error, reward, crash flag.

        ``carry = (quad, k, wind, key, reward, err_sum, crashed)``; ``p_ref`` may pass
        p_d(k+1) when it is already known; ``wind_mean`` (3,) m/s² is added to the OU wind.
        Returns the new carry and p_d(k+1)."""
        c = self.config
        quad, k, wind, key, reward, err_sum, crashed = carry
        if c.disturbances.wind_sigma > 0:
            wind, key = ou_wind_step(c, wind, key)
        accel = wind if c.disturbances.wind_sigma > 0 else None
        if wind_mean is not None:
            accel = wind_mean if accel is None else accel + wind_mean
        quad = rk4_step(
            params,
            quad,
            u,
            c.dt,
            accel,
            substeps=c.vehicle.rk4_substeps,
            renormalize=c.vehicle.renormalize,
        )
        k = k + 1
        effort, change = effort
        step_r = -c.reward.rho2 * effort
        if change is not None:
            step_r = step_r - c.reward.rho_rate * change
        if p_ref is None:
            p_ref = tr.position(track, k, c.dt)
        e = jnp.linalg.norm(p_ref - quad.p)
        finite = jnp.isfinite(e) & _finite(quad)
        step_r = step_r - c.reward.rho1 * error_cost(c, e)
        if c.reward.rho_yaw > 0:  # hold the heading the tracks are flown at (ψ = 0)
            step_r = step_r - c.reward.rho_yaw * jnp.square(yaw_of(quad.q))
        reward = reward + jnp.where(~crashed & finite, step_r, 0.0)
        err_sum = err_sum + jnp.where(finite, e, jnp.inf)
        crashed = crashed | ~finite | (e > c.reward.e_max)
        return (quad, k, wind, key, reward, err_sum, crashed), p_ref

    def _effort(self, a: jax.Array, ps: TrackingState) -> tuple[jax.Array, jax.Array | None]:
        """``(aᵀΩa, ||a − a_prev||²)`` of the action (the second: with ``rho_rate`` > 0, against
        the action the last control step commanded, ``obs_memory``'s ``last_action``; else None)."""
        c = self.config
        change = a - ps.last_action if c.reward.rho_rate > 0 else None
        if c.reward.effort_hover_relative:
            a = a - hover_action(c).astype(a.dtype)
        w = jnp.asarray(self._effort_w, a.dtype)
        return jnp.sum(w * a * a), None if change is None else jnp.sum(change * change)

    def _initial_state(self, rng: jax.Array, p0: jax.Array) -> QuadState:
        c = self.config
        f = p0.dtype
        if not c.randomization.randomize_init:
            return QuadState.hover(p0, f)
        u = jax.random.uniform(rng, (9,), f, -1.0, 1.0)  # one draw, sliced
        p = p0 + c.randomization.init_pos * u[0:3]
        v = c.randomization.init_vel * u[3:6]
        ang = math.pi * u[6]
        axis = jnp.stack([jnp.cos(ang), jnp.sin(ang), jnp.zeros((), f)])
        tilt = 0.5 * (u[7] + 1.0) * math.radians(c.randomization.init_tilt_deg)
        yaw = u[8] * math.radians(c.randomization.init_yaw_deg)
        q = quat_mul(
            quat_from_axis_angle(jnp.array([0.0, 0.0, 1.0], f), yaw), quat_from_axis_angle(axis, tilt)
        )
        return QuadState(p=p, v=v, q=q, w=jnp.zeros(3, f))

    def _measured(self, ps: TrackingState):
        """``(p, v, q, ps)`` as measured: the observation noise (``ps``'s key advanced) and the
        position bias of a randomised plant added."""
        c = self.config
        p, v, q = ps.quad.p, ps.quad.v, ps.quad.q
        if (
            c.disturbances.obs_noise_pos > 0
            or c.disturbances.obs_noise_vel > 0
            or c.disturbances.obs_noise_quat > 0
        ):
            key, kp, kv, kq = jax.random.split(ps.key, 4)
            scale = ps.plant.noise_scale if self._randomized else 1.0  # (a Python 1.0: the same program)
            p = p + scale * c.disturbances.obs_noise_pos * jax.random.normal(kp, (3,), p.dtype)
            v = v + scale * c.disturbances.obs_noise_vel * jax.random.normal(kv, (3,), p.dtype)
            q = q + scale * c.disturbances.obs_noise_quat * jax.random.normal(kq, (4,), p.dtype)
            q = q / jnp.linalg.norm(q)
            ps = ps.replace(key=key)
        if self._randomized and rz.has_pos_bias(c):
            p = p + ps.plant.pos_bias  # the observed position's bias (before the track-frame shift)
        return p, v, q, ps

    def observe(self, ps: TrackingState, p_ref_now: jax.Array | None = None, integrate: bool = False):
        """Observation (O1), and the state with its noise key advanced and ``ref_next``
        refreshed.  ``p_ref_now`` may pass p_d(k) when the caller already has it.
        ``integrate`` (after a step, with ``obs_memory``): first add this control step to the
        leaky error integral, from the *observed* position (noise and bias included, as a
        vehicle would integrate it), never the true one."""
        c = self.config
        x = ps.quad
        p, v, q, ps = self._measured(ps)
        if integrate and c.observation.obs_memory:
            leak = math.exp(-c.control_dt / c.observation.memory_tau)
            p_now = tr.position(ps.track, ps.k, c.dt) if p_ref_now is None else p_ref_now
            e = _zero_non_finite(p_now - p)
            ps = ps.replace(err_int=leak * ps.err_int + c.control_dt * e)
            if c.observation.ref_integral_gain > 0:
                near = jnp.abs(e) < c.observation.ref_integral_band  # per axis: no wind-up far off
                ps = ps.replace(ref_int=ps.ref_int + c.control_dt * jnp.where(near, e, 0.0))
        if c.observation.ref_integral_gain > 0:
            p = p - reference_shift(c, ps)  # the vehicle against the shifted reference: p − s
        if c.observation.canonical_q_obs:
            q = jnp.where(q[0] < 0, -q, q)
        p_ahead = tr.position(ps.track, ps.k + c.observation.lookahead_k, c.dt)
        p_next = p_ahead if c.observation.lookahead_k == 1 else tr.position(ps.track, ps.k + 1, c.dt)
        ps = ps.replace(ref_next=p_next)
        if c.observation.err_ref == "next":
            p_err = p_next
        else:
            p_err = tr.position(ps.track, ps.k, c.dt) if p_ref_now is None else p_ref_now
        err = jnp.linalg.norm(p_err - p)
        if c.observation.obs_frame == "track":  # the same parts with the origin moved to p_d,k
            p_now = tr.position(ps.track, ps.k, c.dt) if p_ref_now is None else p_ref_now
            parts = dict(p=p - p_now, v=v, q=q, p_ahead=p_ahead - p_now)
        else:
            parts = dict(p=p, v=v, q=q, p_ahead=p_ahead)
        parts.update(p_ahead_error=p_ahead - p, error=err[None])
        if self.layout.has("omega"):
            parts["omega"] = x.w
        if c.observation.obs_memory:
            parts.update(last_action=ps.last_action, error_integral=ps.err_int)
        if c.observation.action_history_s:
            parts["action_history"] = ps.act_hist.reshape(-1)
        if self.layout.has("vehicle"):  # the known vehicle (randomization.vehicles)
            parts["vehicle"] = vm.descriptor(ps.plant.nominal)

        def ahead(t):  # p_d t s after p_d,k+L, relative to it (the preview, the critics' points)
            return tr.position(ps.track, ps.k + c.observation.lookahead_k + round(t / c.dt), c.dt) - p_ahead

        for t in c.observation.preview_s:  # the actor's preview of the reference
            parts[observation.preview_name(t)] = ahead(t)
        if c.observation.obs_privileged:
            wind_mean = self._randomized and c.randomization.wind_mean > 0
            parts["wind"] = ps.wind + ps.plant.wind_mean if wind_mean else ps.wind
            for t in PRIVILEGED_AHEAD_S:
                parts[f"p_ahead_{t:g}s"] = ahead(t)
        # non-finite entries (a diverged state) read as 0, in one read of the concatenation
        return _zero_non_finite(self.layout.build(parts, jnp.concatenate)), ps
