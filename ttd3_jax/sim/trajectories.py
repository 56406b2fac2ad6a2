"""Reference trajectories: Spiral-RT, LOS-RT and the random training mixture (spec §2.3).

Every track is a :class:`Track`, a small pytree of parameters from which the reference
position, velocity and acceleration at any step ``k`` are evaluated in O(1)
(:func:`evaluate`).  Two families cover everything:

* ``kind == SPIRAL``: ``p(τ) = (a τ cos(Ωτ+φ), a τ sin(Ωτ+φ), c τ)`` with
  ``τ = s · k · dt`` (s = ``time_scale``).  The paper's Spiral-RT is
  a = 0.1 m/s, Ω = π/20 rad/s, c = 0.1 m/s, φ = 0, s = 1.
* ``kind == PIECEWISE``: segments of ``seg_steps`` control steps with constant
  acceleration; segment j holds ``(P_j, V_j, A_j)`` and
  ``p = P_j + V_j τ + ½ A_j τ²`` with ``τ = (k − j·seg_steps)·dt``.  Steps before
  ``first_step`` sit at the origin (the LOS-RT literal start, spec T7).
  LOS-RT (A = 0) and the "dynamics-generated" training tracks use it.

A track never stores the dense 3000-point table (:func:`reference` makes one), so an env
state stays small.  All generators are pure functions of a PRNG key; ``vmap`` them.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from flax import struct

SPIRAL, PIECEWISE = 0, 1
LOS_HEADINGS = ("absolute", "cumulative")
MAX_COORD = 1e4  # m: any reference coordinate (float32 keeps mm resolution up to about 1e4 m)
MAX_SPEED = 100.0  # m/s: any reference speed set by a TrackConfig field

# The exact test instances (LOS-RT seed 0 and 1..20, Spiral-RT) come from
# ``jax.random.PRNGKey(seed)``.  The training mixture and the validation set fold
# these tags into their keys and draw with a different structure, so they never
# produce a test instance (see docs/paper-notes.md, T8).
_TRAIN_TAG = 0x7EA1
_VALIDATION_TAG = 0x5A11
NUM_VALIDATION_TRACKS = 10

# Training-mixture ranges (spec §2.3).
_ACC_HOLD_S = (0.2, 0.6)  # s, hold time of each random acceleration
_ACC_MAX = (3.0, 3.0, 1.0)  # m/s^2, |a| per axis
_SPEED_CAP_H, _SPEED_CAP_Z = 3.0, 0.5  # m/s
_SPIRAL_GAIN = (0.05, 0.5)  # m/s
_SPIRAL_RATE = (math.pi / 40, math.pi / 2)  # rad/s, sign random
_SPIRAL_CLIMB = 0.2  # m/s, climb ~ U(-0.2, 0.2)
_LOS_SPEED = (0.5, 3.0)  # m/s
_LOS_THETA_MAX = math.pi / 6  # rad, per-track bound ~ U(0, π/6)
_LOS_SEG_STEPS = (50, 500)  # control steps
_LOS_CLIMB = 0.2  # m/s, climb ~ U(-0.2, 0.2)


def _float():
    """Default float dtype: float32, or float64 when x64 is enabled."""
    return jnp.zeros(()).dtype


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """How the test tracks are read from the paper, and the training-mixture weights.

    Units: seconds, metres, radians.  Defaults follow the spec's default reading.
    """

    spiral_time_scale: float = 1.0  # s in τ = s·t (T2); t in seconds
    los_speed: tuple[float, float] = (1.5, 2.5)  # p ~ U(lo, hi): m/s, or m/step if not p_is_speed
    los_theta_max: float = math.pi / 120  # rad, θ ~ U(-θmax, θmax)
    los_segment_steps: int = 100  # control steps between redraws of θ, p (T6)
    los_p_is_speed: bool = True  # T4: p·dt per step (True) or p per step (literal)
    los_heading: str = "absolute"  # T5: "absolute" (ψ = θ) or "cumulative" (ψ += θ)
    los_literal_init: bool = True  # T7: p_d(1) = los_init_point
    los_init_point: tuple[float, float, float] = (0.1, 0.1, 0.1)  # m
    los_climb_rate: float = 0.1  # m/s (1e-4 m per 1 ms step)
    train_mix: tuple[float, float, float] = (0.5, 0.25, 0.25)  # (dynamics, spiral, LOS) weights

    def __post_init__(self):
        if not (math.isfinite(self.spiral_time_scale) and self.spiral_time_scale > 0):
            raise ValueError(f"spiral_time_scale must be finite and > 0, got {self.spiral_time_scale}")
        if len(self.los_speed) != 2 or not all(map(math.isfinite, self.los_speed)):
            raise ValueError(f"los_speed must be two finite numbers (min, max), got {self.los_speed}")
        lo, hi = self.los_speed
        if not 0 <= lo <= hi:
            raise ValueError(f"los_speed must satisfy 0 <= min <= max, got {self.los_speed}")
        if not (math.isfinite(self.los_theta_max) and self.los_theta_max >= 0):
            raise ValueError(f"los_theta_max must be >= 0 rad, got {self.los_theta_max}")
        if int(self.los_segment_steps) != self.los_segment_steps or self.los_segment_steps < 1:
            raise ValueError(f"los_segment_steps must be an integer >= 1, got {self.los_segment_steps}")
        if self.los_heading not in LOS_HEADINGS:
            raise ValueError(f"los_heading must be one of {LOS_HEADINGS}, got {self.los_heading!r}")
        if not (math.isfinite(self.los_climb_rate) and abs(self.los_climb_rate) <= MAX_SPEED):
            raise ValueError(f"los_climb_rate must be a finite number in [-{MAX_SPEED:g}, {MAX_SPEED:g}] "
                             f"m/s, got {self.los_climb_rate}")  # fmt: skip
        p = self.los_init_point
        if len(p) != 3 or not all(math.isfinite(x) and abs(x) <= MAX_COORD for x in p):
            raise ValueError(f"los_init_point must be 3 finite numbers in [-{MAX_COORD:g}, {MAX_COORD:g}] m, "
                             f"got {p}")  # fmt: skip
        if self.los_speed[1] > MAX_SPEED:
            raise ValueError(f"los_speed must be at most {MAX_SPEED:g}, got {self.los_speed}")
        w = self.train_mix
        if len(w) != 3 or not all(map(math.isfinite, w)) or any(x < 0 for x in w) or sum(w) <= 0:
            raise ValueError(
                f"train_mix must be 3 non-negative weights (dynamics, spiral, los) with a "
                f"positive sum, got {w}"
            )


@struct.dataclass
class Track:
    """Parameters of one reference track (see module docstring). Scalars are 0-d arrays."""

    kind: jax.Array  # int32, SPIRAL or PIECEWISE
    gain: jax.Array  # m/s, spiral radius growth a
    rate: jax.Array  # rad/s, spiral angular rate Ω
    climb: jax.Array  # m/s, spiral vertical speed c
    phase: jax.Array  # rad, spiral phase φ
    time_scale: jax.Array  # spiral time scale s
    seg_steps: jax.Array  # int32, control steps per segment
    first_step: jax.Array  # int32, steps before it are at the origin
    seg: jax.Array  # (n_seg, 3, 3): rows P_j (m), V_j (m/s), A_j (m/s^2); one gather per lookup

    # (..., n_seg, 3): segment start positions P_j (m), start velocities V_j (m/s), accelerations A_j
    seg_p = property(lambda self: self.seg[..., 0, :])
    seg_v = property(lambda self: self.seg[..., 1, :])
    seg_a = property(lambda self: self.seg[..., 2, :])
    num_segments = property(lambda self: self.seg.shape[-3])


@struct.dataclass
class Reference:
    """Dense reference on the control grid: each field (num_points, 3) at t_k = k·dt."""

    pos: jax.Array  # m
    vel: jax.Array  # m/s
    acc: jax.Array  # m/s^2


def num_segments_for(horizon_steps: int, min_seg_steps: int) -> int:
    """Static segment-table size that covers ``horizon_steps`` control steps."""
    return int(math.ceil(horizon_steps / min_seg_steps)) + 1


def _segments(requested: int | None, needed: int, horizon_steps: int) -> int:
    """Segment-table size: ``needed`` by default; a smaller request would leave the
    last segment extrapolating past its end, so it is refused."""
    if requested is None:
        return needed
    if int(requested) != requested or requested < needed:
        raise ValueError(
            f"num_segments={requested!r} cannot cover {horizon_steps} steps; allowed: an integer >= {needed}"
        )
    return int(requested)


_SPIRAL_DEFAULTS = {"gain": 0.0, "rate": 0.0, "climb": 0.0, "phase": 0.0, "time_scale": 1.0}


def _make(kind, *, n_seg, seg_steps=1, first_step=0, seg_p=None, seg_v=None, seg_a=None, **spiral) -> Track:
    """A :class:`Track` of ``kind``; ``spiral`` sets the spiral fields (else 0, time scale 1)."""
    f = jnp.zeros(()).dtype  # the default float (float64 under x64), as _float
    fields = dict(_SPIRAL_DEFAULTS, **spiral)
    for name in _SPIRAL_DEFAULTS:
        fields[name] = jnp.asarray(fields[name], f)
    tables = []
    for x in (seg_p, seg_v, seg_a):
        tables.append(jnp.zeros((n_seg, 3), f) if x is None else jnp.asarray(x, f))
    return Track(kind=jnp.asarray(kind, jnp.int32), **fields, seg_steps=jnp.asarray(seg_steps, jnp.int32),
                 first_step=jnp.asarray(first_step, jnp.int32), seg=jnp.stack(tables, -2))  # fmt: skip


def table(pos, vel, acc, seg_steps: int = 1) -> Track:
    """A piecewise track from tables (n, 3) of segment start positions (m), velocities
    (m/s) and accelerations (m/s^2), one segment every ``seg_steps`` control steps; after
    the last segment it extrapolates that segment's motion (hold a point with v = a = 0)."""
    return _make(PIECEWISE, n_seg=len(pos), seg_steps=seg_steps, seg_p=pos, seg_v=vel, seg_a=acc)


def _spiral(track: Track, t: jax.Array):
    s = track.time_scale
    tau = s * t
    ang = track.rate * tau + track.phase
    c, sn = jnp.cos(ang), jnp.sin(ang)
    a, om = track.gain, track.rate
    zero = jnp.zeros_like(tau)
    pos = jnp.stack([a * tau * c, a * tau * sn, track.climb * tau], -1)
    dpos = jnp.stack([a * (c - om * tau * sn), a * (sn + om * tau * c), track.climb + zero], -1)
    ddpos = jnp.stack([a * om * (-2.0 * sn - om * tau * c), a * om * (2.0 * c - om * tau * sn), zero], -1)
    return pos, s * dpos, s * s * ddpos


def _piecewise(track: Track, k: jax.Array, dt: float):
    # Segment index in floating point: exact for k < 2**23 and about 3x faster on CPU
    # than integer floor division (benchmarks/env_throughput.py).
    f = track.seg.dtype
    kf, S = k.astype(f), track.seg_steps.astype(f)
    jf = jnp.minimum(jnp.floor((kf + 0.5) / S), track.seg.shape[-3] - 1)  # the last segment
    tau = ((kf - jf * S) * dt)[..., None]
    row = track.seg[jf.astype(jnp.int32)]  # (..., 3, 3)
    P, V, A = row[..., 0, :], row[..., 1, :], row[..., 2, :]
    pos = P + V * tau + 0.5 * A * tau * tau
    pos = jnp.where((k < track.first_step)[..., None], jnp.zeros_like(pos), pos)
    return pos, V + A * tau, A


def evaluate(track: Track, k: jax.Array, dt: float, derivatives: bool = True):
    """Reference at integer control step(s) ``k`` (any shape ``...``).

    Returns ``(pos, vel, acc)`` each (..., 3) in m, m/s, m/s^2, or only ``pos`` when
    ``derivatives=False``.  Both families are evaluated and selected by ``kind``,
    which keeps it branch-free under ``vmap``.
    """
    k = jnp.asarray(k, jnp.int32)
    t = k.astype(track.seg.dtype) * dt
    sp = _spiral(track, t)
    pw = _piecewise(track, k, dt)
    is_spiral = track.kind == SPIRAL
    out = tuple(jnp.where(is_spiral, a, b) for a, b in zip(sp, pw, strict=True))
    return out if derivatives else out[0]


# position(track, k, dt): the reference position (..., 3) m at control step(s) ``k``
position = functools.partial(evaluate, derivatives=False)


def reference(track: Track, dt: float, num_points: int) -> Reference:
    """Dense reference for k = 0 … num_points−1 (the env uses episode_steps + 2 points)."""
    pos, vel, acc = evaluate(track, jnp.arange(num_points), dt)
    return Reference(pos=pos, vel=vel, acc=acc)


def spiral_rt(cfg: TrackConfig = TrackConfig(), num_segments: int = 1) -> Track:
    """The paper's Spiral-RT (eq. 6) with t in seconds scaled by ``spiral_time_scale``."""
    return _make(
        SPIRAL, n_seg=num_segments, gain=0.1, rate=math.pi / 20, climb=0.1, time_scale=cfg.spiral_time_scale
    )


def _los_tables(thetas, speeds, dt, seg_steps, *, heading_cumulative, p_is_speed, climb_rate, init_point,
                literal_init):  # fmt: skip
    """Segment start positions/velocities for LOS tracks (zero acceleration): headings θ
    (absolute or cumulative), speeds (m/s, or m per step unless ``p_is_speed``), climb m/s."""
    psi = jnp.where(heading_cumulative, jnp.cumsum(thetas), thetas)
    speed = jnp.where(p_is_speed, speeds, speeds / dt)  # m/s
    vz = jnp.full_like(speed, climb_rate)
    vel = jnp.stack([speed * jnp.cos(psi), speed * jnp.sin(psi), vz], -1)  # (n_seg, 3)
    seg_len = seg_steps.astype(vel.dtype) * dt
    # p_d(1) = init_point under the literal start, so P_0 = init_point - V_0 dt.
    p0 = jnp.where(literal_init, jnp.asarray(init_point, vel.dtype) - vel[0] * dt, 0.0)
    starts = p0 + jnp.concatenate([jnp.zeros_like(vel[:1]), jnp.cumsum(vel[:-1] * seg_len, 0)], 0)
    return starts, vel


LOS_BASE_DRAWS = 31  # segments of a 3000-step LOS-RT track (S = 100)


def _prefix_uniform(key: jax.Array, n: int, dtype, lo, hi) -> jax.Array:
    """n uniform draws whose first values do not depend on n: the first
    ``LOS_BASE_DRAWS`` come from ``key``, any further ones from ``fold_in(key, 1)``.
    A test instance is then the same track whatever horizon it is built for."""
    base = jax.random.uniform(key, (LOS_BASE_DRAWS,), dtype, lo, hi)
    if n <= LOS_BASE_DRAWS:
        return base[:n]
    extra = jax.random.uniform(jax.random.fold_in(key, 1), (n - LOS_BASE_DRAWS,), dtype, lo, hi)
    return jnp.concatenate([base, extra])


def los_rt(key: jax.Array, cfg: TrackConfig = TrackConfig(), num_segments: int | None = None,
           dt: float = 1e-3, horizon_steps: int = 3002) -> Track:  # fmt: skip
    """LOS-RT (eq. 7) drawn from ``key``: θ ~ U(±θmax), p ~ U(speed range) every S steps.

    ``p_d(k+1) = p_d(k) + (p cosψ·dt, p sinψ·dt, climb·dt)``, ``p_d(0) = 0`` and, under
    the literal start, ``p_d(1) = los_init_point``.  ``num_segments`` (static) defaults
    to enough segments for ``horizon_steps``.
    """
    S = int(cfg.los_segment_steps)
    n = _segments(num_segments, num_segments_for(horizon_steps, S), horizon_steps)
    k_theta, k_speed = jax.random.split(key)
    f = _float()
    thetas = _prefix_uniform(k_theta, n, f, -cfg.los_theta_max, cfg.los_theta_max)
    speeds = _prefix_uniform(k_speed, n, f, cfg.los_speed[0], cfg.los_speed[1])
    cumulative = cfg.los_heading == "cumulative"
    starts, vel = _los_tables(thetas, speeds, dt, jnp.asarray(S), heading_cumulative=cumulative,
                              p_is_speed=cfg.los_p_is_speed, climb_rate=cfg.los_climb_rate,
                              init_point=cfg.los_init_point, literal_init=cfg.los_literal_init)  # fmt: skip
    return _make(
        PIECEWISE, n_seg=n, seg_steps=S, first_step=int(cfg.los_literal_init), seg_p=starts, seg_v=vel
    )


def los_test_track(seed: int, cfg: TrackConfig = TrackConfig(), **kw) -> Track:
    """The fixed LOS-RT test instance ``seed`` (0 is the headline, 1..20 give mean ± std)."""
    if int(seed) != seed or seed < 0:
        raise ValueError(f"LOS-RT test seed must be a non-negative integer, got {seed!r}")
    return los_rt(jax.random.PRNGKey(int(seed)), cfg, **kw)


def _uniform(u: jax.Array, lo, hi) -> jax.Array:
    """Map U(0, 1) samples onto U(lo, hi)."""
    return lo + (hi - lo) * u


def _randint(u: jax.Array, lo: int, hi: int) -> jax.Array:
    """Map U(0, 1) samples onto integers in [lo, hi]."""
    return jnp.clip(jnp.floor(lo + (hi - lo + 1) * u).astype(jnp.int32), lo, hi)


# The mixture draws one block of U(0, 1) numbers per track and slices it: one threefry call
# instead of a dozen keeps the compiled reset small and fast to build.  Sizes per family:
_dynamics_uniforms = lambda n_seg: 1 + 3 * n_seg  # noqa: E731
_los_uniforms = lambda n_seg: 6 + 2 * n_seg  # noqa: E731
_SPIRAL_UNIFORMS = 5


def _train_dynamics(u: jax.Array, n_seg: int, dt: float, hold_s=_ACC_HOLD_S, acc_max=_ACC_MAX,
                    speed_max=(_SPEED_CAP_H, _SPEED_CAP_Z)) -> Track:  # fmt: skip
    """Piecewise-constant random acceleration, speed-capped, starting at rest at 0: one hold
    time ~ U(``hold_s``) s for all segments, accelerations ~ U(±``acc_max``) m/s² per axis,
    speed capped at ``speed_max`` = (horizontal, vertical) m/s.  The defaults are the paper
    mixture's; the wide mixture's agile family passes its own."""
    lo, hi = (max(1, int(round(x / dt))) for x in hold_s)
    hold = _randint(u[0], lo, hi)
    seg_t = hold.astype(u.dtype) * dt
    acc = _uniform(u[1:].reshape(n_seg, 3), -1.0, 1.0) * jnp.asarray(acc_max, u.dtype)
    cap_h, cap_z = speed_max

    def seg(carry, a):
        p, v = carry
        v_new = v + a * seg_t
        h = jnp.linalg.norm(v_new[:2])
        v_new = v_new.at[:2].multiply(jnp.minimum(1.0, cap_h / jnp.maximum(h, 1e-9)))
        v_new = v_new.at[2].set(jnp.clip(v_new[2], -cap_z, cap_z))
        a_eff = (v_new - v) / seg_t  # the cap lowers the acceleration, it never breaks continuity
        p_new = p + v * seg_t + 0.5 * a_eff * seg_t * seg_t
        return (p_new, v_new), (p, v, a_eff)

    zero = jnp.zeros(3, u.dtype)
    _, (P, V, A) = jax.lax.scan(seg, (zero, zero), acc)
    return _make(PIECEWISE, n_seg=n_seg, seg_steps=hold, seg_p=P, seg_v=V, seg_a=A)


def _train_spiral(u: jax.Array, n_seg: int) -> Track:
    gain = _uniform(u[0], *_SPIRAL_GAIN)
    rate = _uniform(u[1], *_SPIRAL_RATE) * jnp.where(u[2] < 0.5, 1.0, -1.0)
    climb = _uniform(u[3], -_SPIRAL_CLIMB, _SPIRAL_CLIMB)
    phase = _uniform(u[4], 0.0, 2 * math.pi)
    return _make(SPIRAL, n_seg=n_seg, gain=gain, rate=rate, climb=climb, phase=phase)


def _train_los(u: jax.Array, n_seg: int, dt: float, cfg: TrackConfig) -> Track:
    seg_steps = _randint(u[0], *_LOS_SEG_STEPS)
    theta_max = _uniform(u[1], 0.0, _LOS_THETA_MAX)
    cumulative, literal = u[2] < 0.5, u[3] < 0.5
    climb = _uniform(u[4], -_LOS_CLIMB, _LOS_CLIMB)
    thetas = _uniform(u[6 : 6 + n_seg], -1.0, 1.0) * theta_max
    speeds = _uniform(u[6 + n_seg : 6 + 2 * n_seg], *_LOS_SPEED)
    starts, vel = _los_tables(thetas, speeds, dt, seg_steps, heading_cumulative=cumulative, p_is_speed=True,
                              climb_rate=climb, init_point=cfg.los_init_point,
                              literal_init=literal)  # fmt: skip
    first = literal.astype(jnp.int32)
    return _make(PIECEWISE, n_seg=n_seg, seg_steps=seg_steps, first_step=first, seg_p=starts, seg_v=vel)


def train_num_segments(horizon_steps: int, dt: float) -> int:
    """Segment-table size used by :func:`sample_train_track` for ``horizon_steps``."""
    min_seg = min(_LOS_SEG_STEPS[0], int(round(_ACC_HOLD_S[0] / dt)))
    return num_segments_for(horizon_steps, max(1, min_seg))


def sample_train_track(key: jax.Array, cfg: TrackConfig = TrackConfig(), dt: float = 1e-3,
                       horizon_steps: int = 3002, num_segments: int | None = None) -> Track:  # fmt: skip
    """One track of the training mixture (dynamics / random spiral / random LOS, weights
    ``cfg.train_mix``).  Starts at the origin.  Never yields a test instance."""
    n = _segments(num_segments, train_num_segments(horizon_steps, dt), horizon_steps)
    sizes = (1, _dynamics_uniforms(n), _SPIRAL_UNIFORMS, _los_uniforms(n))
    u = jax.random.uniform(jax.random.fold_in(key, _TRAIN_TAG), (sum(sizes),), _float())
    u_cat, u_dyn, u_sp, u_los = jnp.split(u, [sum(sizes[:i]) for i in range(1, 4)])
    w = jnp.cumsum(jnp.asarray(cfg.train_mix, u.dtype))
    cat = jnp.sum(u_cat[0] * w[-1] >= w[:2])  # 0, 1 or 2 with probabilities ∝ train_mix
    candidates = (_train_dynamics(u_dyn, n, dt), _train_spiral(u_sp, n), _train_los(u_los, n, dt, cfg))
    return jax.tree.map(lambda a, b, c: jnp.select([cat == 0, cat == 1], [a, b], c), *candidates)


def validation_tracks(cfg: TrackConfig = TrackConfig(), dt: float = 1e-3, horizon_steps: int = 3002,
                      num_segments: int | None = None) -> Track:  # fmt: skip
    """The 10 fixed validation tracks (a batched :class:`Track`, leading axis 10) drawn
    from the training mixture; used for model selection and NMPC tuning."""
    base = jax.random.PRNGKey(_VALIDATION_TAG)
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(NUM_VALIDATION_TRACKS))
    return jax.vmap(lambda k: sample_train_track(k, cfg, dt, horizon_steps, num_segments))(keys)


TEST_TRACKS = ("spiral_rt", "los_rt")
