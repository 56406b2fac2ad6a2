"""A wider training-track distribution (issue 37): the paper's three families plus six more.

Every family maps the first numbers of one block of U(0, 1) draws onto a PIECEWISE or SPIRAL
:class:`~ttd3_jax.sim.trajectories.Track` with the same table size, so that
:func:`sample_wide_track` evaluates them all and picks one (branch-free under ``vmap``,
like :func:`~ttd3_jax.sim.trajectories.sample_train_track`).  Every track starts at the
origin.  Ranges are the constants below (units in their comments):

==========  ================================================================================
family      what it draws
==========  ================================================================================
dynamics    the paper's: random accelerations ±(3, 3, 1) m/s² held 0.2–0.6 s, ≤ 3 / 0.5 m/s
spiral      the paper's: random spiral
los         the paper's: random LOS, 0.5–3 m/s
step        hover at the origin for 0.5–1.5 s, then steps of 0.2–1 m (elevation ≤ 30°), each
            held 0.5–1.5 s; v = a = 0 (the only family whose position jumps)
circle      radius 0.5–3 m, speed 0.5–4.5 m/s lowered to keep v²/r ≤ 4.5 m/s², in a plane
            through a random start heading tilted up to ±45°, either direction
figure8     p = a sin θ e1 + b sin 2θ e2, a 0.5–3 m, b/a 0.25–0.75, peak speed 0.5–4.5 m/s
            lowered to keep θ'²|p''| ≤ 4.5 m/s²; plane and direction as circles
agile       random accelerations ±(6, 6, 2) m/s² held 0.2–0.5 s, capped at 4.5 m/s
            horizontally and 1.5 m/s vertically (both configurable), from rest; the cap
            shortens a segment's acceleration (one axis can pass its bound a little:
            6.14 m/s² seen in 4096 draws)
los_fast    LOS legs of 0.3–1 s at 1–4.5 m/s, headings within ±(0–45°) of a random base
            heading, climb ±0.5 m/s; starts at speed, as the paper's LOS does
vertical    climbs/descents up to ±1.5 m/s with a horizontal drift ≤ 1 m/s (ramped from rest
            at ≤ 2 m/s²), bobbing z = ±A(1 − cos ωt) with A 0.1–1 m, Aω ≤ 2 m/s,
            Aω² ≤ 4 m/s², or both; from rest
==========  ================================================================================

Circles and figure-8s start at speed (as the suite's do) or, with probability 1/2, spin up
from hover along a smoothstep speed profile whose tangential acceleration peaks at
1.5–3 m/s²; with the 4.5 m/s² cap this keeps ‖a‖ ≤ 5.6 m/s².  They, and the vertical family,
are tabulated with segments of at most 50 ms, each the quadratic through the curve at its
start, middle and end: continuous in position, within 0.03 mm and 6 mm/s of the curve
(measured; the tests bound 0.1 mm and 1 cm/s).

Seeds: training draws fold :data:`_WIDE_TAG` into the env's key and the validation set
starts from ``PRNGKey(_WIDE_VALIDATION_TAG)``, tags distinct from the paper mixture's and
validation's and from the test tracks' ``PRNGKey(seed)``; the generalisation suite is
built with NumPy from its own seeds and formulas.  No suite or test-track instance is
trained on; ``tests/test_track_families.py`` checks the distances numerically.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ttd3_jax import checks
from ttd3_jax.sim import trajectories as tr

FAMILIES = ("dynamics", "spiral", "los", "step", "circle", "figure8", "agile", "los_fast", "vertical")
WIDE_MIX = (0.15, 0.1, 0.1, 0.1, 0.1, 0.1, 0.15, 0.1, 0.1)  # default weights, in FAMILIES order
PAPER_ONLY = (0.5, 0.25, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # the paper's mixture's weights

_WIDE_TAG = 0x31DE  # folded into a training key (tr._TRAIN_TAG: 0x7EA1, tr._VALIDATION_TAG: 0x5A11)
_WIDE_VALIDATION_TAG = 0x31DF  # PRNGKey of the wide validation set
VALIDATION_PER_FAMILY = 2  # wide validation tracks per family of positive weight

# step from hover
STEP_HOLD_S = (0.5, 1.5)  # s, time at each set point (the first: the hover at the origin)
STEP_SIZE = (0.2, 1.0)  # m, length of each step
STEP_ELEVATION = math.pi / 6  # rad, |elevation| of a step's direction
# circles and figure-8s
CURVE_SEG_S = 0.05  # s, longest table segment of a tabulated curve
CURVE_SPEED = (0.5, 4.5)  # m/s, cruise (circle) or peak (figure-8) speed before the cap
CURVE_ACC = 4.5  # m/s^2, cap on the curvature acceleration at cruise speed
CURVE_RAMP_ACC = (1.5, 3.0)  # m/s^2, peak tangential acceleration of a spin-up
CURVE_RAMP_P = 0.5  # probability of a spin-up from hover (else the curve starts at speed)
CURVE_TILT = math.pi / 4  # rad, |tilt| of the plane about the start heading
CIRCLE_RADIUS = (0.5, 3.0)  # m
FIGURE8_SIZE = (0.5, 3.0)  # m, a in p = a sin θ e1 + b sin 2θ e2
FIGURE8_ASPECT = (0.25, 0.75)  # b / a
# random accelerations
AGILE_HOLD_S = (0.2, 0.5)  # s, hold time of each acceleration
AGILE_ACC_MAX = (6.0, 6.0, 2.0)  # m/s^2, |a| per axis
AGILE_SPEED_MAX = (4.5, 1.5)  # m/s, horizontal (radial scaling) and vertical (clip) caps
# LOS legs
LOS_FAST_SPEED = (1.0, 4.5)  # m/s
LOS_FAST_LEG_S = (0.3, 1.0)  # s, one leg (all legs of a track are as long)
LOS_FAST_THETA_MAX = math.pi / 4  # rad, per-track bound ~ U(0, ·) on |heading - base heading|
LOS_FAST_CLIMB = 0.5  # m/s, climb ~ U(±·)
# vertical manoeuvres
VERT_CLIMB = 1.5  # m/s, climb rate ~ U(±·)
VERT_DRIFT = 1.0  # m/s, horizontal drift speed ~ U(0, ·)
VERT_RAMP_S = (0.3, 1.5)  # s, shortest ramp to the climb and drift (longer if VERT_RAMP_ACC needs)
VERT_RAMP_ACC = 2.0  # m/s^2, peak acceleration of that ramp
VERT_BOB_AMPLITUDE = (0.1, 1.0)  # m
VERT_BOB_SPEED = 2.0  # m/s, bound on A ω
VERT_BOB_ACC = 4.0  # m/s^2, bound on A ω²

_CURVE_UNIFORMS, _VERTICAL_UNIFORMS = 8, 8
_PAPER_TRACKS = tr.TrackConfig()  # the paper's LOS family reads its literal start point


def _u(u, lo, hi):
    """U(0, 1) samples mapped onto U(lo, hi)."""
    return lo + (hi - lo) * u


def _steps(u, seconds: tuple[float, float], dt: float):
    """U(0, 1) samples mapped onto integer step counts for durations in ``seconds``."""
    lo, hi = (max(1, int(round(s / dt))) for s in seconds)
    return jnp.clip(jnp.floor(lo + (hi - lo + 1) * u).astype(jnp.int32), lo, hi)


def check_weights(field: str, weights) -> tuple[float, ...]:
    """``weights`` as a tuple of one non-negative weight per family with a positive sum."""
    ok = isinstance(weights, tuple | list) and len(weights) == len(FAMILIES)
    ok = ok and all(checks.is_number(w) and w >= 0 for w in weights) and sum(weights) > 0
    if not ok:
        allowed = f"{len(FAMILIES)} non-negative weights with a positive sum for {FAMILIES}"
        checks.fail(field, allowed, weights)
    return tuple(float(w) for w in weights)


def check_agile(acc_max, speed_max) -> None:
    """The agile family's per-axis acceleration bounds (m/s^2) and speed caps (m/s)."""
    for field, v, size, hi in (("agile_acc_max", acc_max, 3, math.inf), ("agile_speed_max", speed_max, 2,
                                                                        tr.MAX_SPEED)):  # fmt: skip
        ok = isinstance(v, tuple | list) and len(v) == size
        if not (ok and all(checks.is_number(x) and 0 < x <= hi for x in v)):
            checks.fail(field, f"{size} finite numbers in (0, {hi:g}]", v)


def wide_num_segments(horizon_steps: int, dt: float) -> int:
    """Segment-table size of :func:`sample_wide_track` for ``horizon_steps``: enough for the
    paper's families and for curve segments of at most :data:`CURVE_SEG_S`."""
    shortest = min(CURVE_SEG_S, STEP_HOLD_S[0], AGILE_HOLD_S[0], LOS_FAST_LEG_S[0])
    own = tr.num_segments_for(horizon_steps, max(1, int(round(shortest / dt))))
    return max(own, tr.train_num_segments(horizon_steps, dt))


def _step(u, n: int, dt: float) -> tr.Track:
    """Hover at the origin, then steps of random length and direction (v = a = 0)."""
    hold = _steps(u[0], STEP_HOLD_S, dt)
    size = _u(u[1 : 1 + n], *STEP_SIZE)
    az = _u(u[1 + n : 1 + 2 * n], 0.0, 2 * math.pi)
    el = _u(u[1 + 2 * n : 1 + 3 * n], -STEP_ELEVATION, STEP_ELEVATION)
    d = size[:, None] * jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az), jnp.sin(el)], -1)
    pos = jnp.cumsum(d.at[0].set(0.0), 0)  # segment 0 is the hover at the origin
    zero = jnp.zeros_like(pos)
    return tr.table(pos, zero, zero, hold)


class Curve(NamedTuple):
    """A smooth track: ``p(t) = a1 sin φ + a2 (1 − cos φ) + a3 sin 2φ + R(t, drift_s)·drift`` with
    ``φ = omega·R(t, ramp_s)`` (R: :func:`_ramp`).  Circles, figure-8s and vertical manoeuvres
    are all of this form, so one tabulation (one sin and cos per knot) serves all three."""

    omega: jax.Array  # rad/s
    ramp_s: jax.Array  # s, spin-up of φ (0: at speed from the start)
    a1: jax.Array  # (3,) m
    a2: jax.Array  # (3,) m
    a3: jax.Array  # (3,) m
    drift: jax.Array  # (3,) m/s, velocity reached after drift_s
    drift_s: jax.Array  # s


def curve_position(c: Curve, t) -> jax.Array:
    """Positions (m, 3) m of curve ``c`` at times ``t`` (m,) s."""
    phi = c.omega * _ramp(t, c.ramp_s)
    s, co = jnp.sin(phi)[:, None], jnp.cos(phi)[:, None]
    return s * c.a1 + (1.0 - co) * c.a2 + (2.0 * s * co) * c.a3 + _ramp(t, c.drift_s)[:, None] * c.drift


def _curve_table(c: Curve, n: int, seg_steps: int, dt: float, dtype) -> tr.Track:
    """Curve ``c`` as n quadratic segments of ``seg_steps`` steps, each through the curve at
    its start, middle and end (continuous in position)."""
    h = seg_steps * dt
    knots = curve_position(c, jnp.arange(2 * n + 1, dtype=dtype) * (0.5 * h))  # starts and middles
    p, m, e = knots[:-1:2], knots[1::2], knots[2::2]
    acc = 4.0 * (e - 2.0 * m + p) / (h * h)
    vel = (4.0 * m - 3.0 * p - e) / h
    return tr.table(p, vel, acc, seg_steps)


def _ramp(t, duration):
    """Distance (s) along a unit-speed motion that starts at rest and reaches speed 1 at
    ``duration`` along a smoothstep speed profile (peak acceleration 1.5 / duration)."""
    d = jnp.maximum(duration, 1e-6)
    x = jnp.clip(t / d, 0.0, 1.0)
    return d * (x**3 - 0.5 * x**4) + jnp.maximum(t - d, 0.0)


def _plane(psi, tilt):
    """Unit vectors e1 (the horizontal start heading psi) and e2 (⊥ e1, tilted by ``tilt``)."""
    e1 = jnp.stack([jnp.cos(psi), jnp.sin(psi), jnp.zeros_like(psi)])
    e2 = jnp.stack([-jnp.sin(psi) * jnp.cos(tilt), jnp.cos(psi) * jnp.cos(tilt), jnp.sin(tilt)])
    return e1, e2


def _curve_common(u):
    """Speed, plane, direction and spin-up draws shared by circles and figure-8s."""
    speed = _u(u[2], *CURVE_SPEED)
    e1, e2 = _plane(_u(u[3], 0.0, 2 * math.pi), _u(u[4], -CURVE_TILT, CURVE_TILT))
    e2 = e2 * jnp.where(u[5] < 0.5, 1.0, -1.0)
    ramp_acc = jnp.where(u[6] < CURVE_RAMP_P, _u(u[7], *CURVE_RAMP_ACC), jnp.inf)
    return speed, e1, e2, ramp_acc


def circle_curve(u) -> Curve:
    """The circle a block ``u`` (:data:`_CURVE_UNIFORMS`) draws."""
    r = _u(u[0], *CIRCLE_RADIUS)
    speed, e1, e2, ramp_acc = _curve_common(u)
    speed = jnp.minimum(speed, jnp.sqrt(CURVE_ACC * r))
    zero = jnp.zeros_like(e1)
    return Curve(speed / r, 1.5 * speed / ramp_acc, r * e1, r * e2, zero, zero, jnp.zeros_like(r))


def figure8_curve(u) -> Curve:
    """The figure-8 ``a sin φ e1 + b sin 2φ e2`` a block ``u`` (:data:`_CURVE_UNIFORMS`) draws."""
    a = _u(u[0], *FIGURE8_SIZE)
    b = a * _u(u[1], *FIGURE8_ASPECT)
    speed, e1, e2, ramp_acc = _curve_common(u)
    # |p'(φ)| <= sqrt(a² + 4b²) (at φ = 0) and |p''(φ)| <= sqrt(a² + 16b²)
    d1, d2 = jnp.sqrt(a * a + 4 * b * b), jnp.sqrt(a * a + 16 * b * b)
    omega = jnp.minimum(speed / d1, jnp.sqrt(CURVE_ACC / d2))
    zero = jnp.zeros_like(e1)
    return Curve(omega, 1.5 * omega * d1 / ramp_acc, a * e1, zero, b * e2, zero, jnp.zeros_like(a))


def vertical_curve(u) -> Curve:
    """The vertical manoeuvre a block ``u`` (:data:`_VERTICAL_UNIFORMS`) draws: a climb or
    descent with drift, a bob ``±A(1 − cos ωt)``, or both (u[0] picks)."""
    mode = jnp.floor(3.0 * u[0])  # 0: climb, 1: bob, 2: both
    climb = _u(u[1], -VERT_CLIMB, VERT_CLIMB) * (mode != 1)
    drift, psi = _u(u[2], 0.0, VERT_DRIFT), _u(u[3], 0.0, 2 * math.pi)
    cruise = jnp.stack([drift * jnp.cos(psi), drift * jnp.sin(psi), climb])
    drift_s = jnp.maximum(_u(u[4], *VERT_RAMP_S), 1.5 * jnp.linalg.norm(cruise) / VERT_RAMP_ACC)
    amp = _u(u[5], *VERT_BOB_AMPLITUDE) * (mode != 0)
    safe = jnp.maximum(amp, 1e-6)
    omega = _u(u[6], 0.5, 1.0) * jnp.minimum(VERT_BOB_SPEED / safe, jnp.sqrt(VERT_BOB_ACC / safe))
    bob = jnp.where(u[7] < 0.5, 1.0, -1.0) * amp * jnp.asarray([0.0, 0.0, 1.0], u.dtype)
    zero = jnp.zeros_like(bob)
    return Curve(omega, jnp.zeros_like(omega), zero, bob, zero, cruise, drift_s)


def _agile(u, n: int, dt: float, acc_max, speed_max) -> tr.Track:
    """Piecewise-constant random accelerations from rest at the origin, speed-capped (the cap
    lowers a segment's acceleration, never breaks continuity: |a| never grows): the paper's
    dynamics family with the agile bounds."""
    return tr._train_dynamics(u, n, dt, AGILE_HOLD_S, acc_max, speed_max)


def _los_fast(u, n: int, dt: float) -> tr.Track:
    """Straight legs of constant velocity (position continuous, velocity jumps at legs)."""
    leg = _steps(u[0], LOS_FAST_LEG_S, dt)
    psi = _u(u[2], 0.0, 2 * math.pi) + _u(u[4 : 4 + n], -1.0, 1.0) * _u(u[1], 0.0, LOS_FAST_THETA_MAX)
    speed = _u(u[4 + n : 4 + 2 * n], *LOS_FAST_SPEED)
    climb = jnp.full_like(speed, _u(u[3], -LOS_FAST_CLIMB, LOS_FAST_CLIMB))
    vel = jnp.stack([speed * jnp.cos(psi), speed * jnp.sin(psi), climb], -1)
    legs = vel[:-1] * (leg.astype(u.dtype) * dt)
    pos = jnp.concatenate([jnp.zeros_like(vel[:1]), jnp.cumsum(legs, 0)])
    return tr.table(pos, vel, jnp.zeros_like(vel), leg)


def _block(n: int) -> int:
    """Uniforms a track draws: the most any family reads.  Only one candidate is kept, so the
    families read the same numbers (a quarter of the threefry work of disjoint slices)."""
    return max(1 + 3 * n, 5, 6 + 2 * n, _CURVE_UNIFORMS, 4 + 2 * n, _VERTICAL_UNIFORMS)


_CURVES = (FAMILIES.index("circle"), FAMILIES.index("figure8"), FAMILIES.index("vertical"))
# candidate of each family: the three curve families share one (their Curve is picked first)
_CANDIDATE = tuple(min(i, _CURVES[0]) if i in _CURVES else i - sum(c < i for c in _CURVES[1:]) for i in
                   range(len(FAMILIES)))  # fmt: skip


def _candidates(u, family, n: int, dt: float, horizon_steps: int, cfg, acc_max, speed_max):
    """One track of every family from the start of the block ``u`` (:func:`_block` uniforms), the
    three curve families as one tabulated :class:`Curve` (``family``'s, when it is one)."""
    curves = (circle_curve(u), figure8_curve(u), vertical_curve(u))
    which = sum(jnp.where(family == f, i, 0) for i, f in enumerate(_CURVES))
    curve = jax.tree.map(lambda *x: jnp.stack(x)[which], *curves)
    curve_steps = max(1, -(-horizon_steps // n))  # ceil: n segments cover the horizon
    return (
        tr._train_dynamics(u[: 1 + 3 * n], n, dt),  # the paper's families, as sample_train_track draws them
        tr._train_spiral(u[:5], n),
        tr._train_los(u[: 6 + 2 * n], n, dt, cfg),
        _step(u[: 1 + 3 * n], n, dt),
        _curve_table(curve, n, curve_steps, dt, u.dtype),
        _agile(u[: 1 + 3 * n], n, dt, acc_max, speed_max),
        _los_fast(u[: 4 + 2 * n], n, dt),
    )


def _pick(family, candidates: tuple[tr.Track, ...]) -> tr.Track:
    """The candidate of family ``family`` (a traced int32)."""
    index = jnp.asarray(_CANDIDATE, jnp.int32)[family]
    return jax.tree.map(lambda *x: jnp.stack(x)[index], *candidates)


def sample_wide_track(key: jax.Array, weights=WIDE_MIX, dt: float = 1e-3, horizon_steps: int = 3002,
                      num_segments: int | None = None, *, cfg: tr.TrackConfig = _PAPER_TRACKS,
                      agile_acc_max=AGILE_ACC_MAX, agile_speed_max=AGILE_SPEED_MAX,
                      with_family: bool = False) -> tr.Track:  # fmt: skip
    """One track of the wide mixture: family ``i`` of :data:`FAMILIES` with probability
    ∝ ``weights[i]`` (static floats).  ``cfg`` gives the paper's LOS family its literal start
    point.  ``num_segments`` (static) defaults to :func:`wide_num_segments`.  With
    ``with_family``: ``(track, i)``."""
    w = jnp.cumsum(jnp.asarray(check_weights("weights", weights)))
    check_agile(agile_acc_max, agile_speed_max)
    n = tr._segments(num_segments, wide_num_segments(horizon_steps, dt), horizon_steps)
    u = jax.random.uniform(jax.random.fold_in(key, _WIDE_TAG), (1 + _block(n),), tr._float())
    family = jnp.sum(u[0] * w[-1] >= w[:-1].astype(u.dtype))
    track = _pick(
        family, _candidates(u[1:], family, n, dt, horizon_steps, cfg, agile_acc_max, agile_speed_max)
    )
    return (track, family) if with_family else track


def wide_validation_families(weights=WIDE_MIX, per_family: int = VALIDATION_PER_FAMILY) -> tuple[str, ...]:
    """The family of each track of :func:`wide_validation_tracks`, in its order."""
    weights = check_weights("weights", weights)
    return tuple(name for name, w in zip(FAMILIES, weights, strict=True) if w > 0 for _ in range(per_family))


def wide_validation_tracks(weights=WIDE_MIX, dt: float = 1e-3, horizon_steps: int = 3002,
                           num_segments: int | None = None, per_family: int = VALIDATION_PER_FAMILY, *,
                           cfg: tr.TrackConfig = _PAPER_TRACKS, agile_acc_max=AGILE_ACC_MAX,
                           agile_speed_max=AGILE_SPEED_MAX) -> tr.Track:  # fmt: skip
    """Fixed validation tracks (a batched Track): ``per_family`` of every family of positive
    weight, in :func:`wide_validation_families` order, drawn from their own key."""
    checks.integer("per_family", per_family, 1)
    names = wide_validation_families(weights, per_family)
    check_agile(agile_acc_max, agile_speed_max)
    n = tr._segments(num_segments, wide_num_segments(horizon_steps, dt), horizon_steps)
    base = jax.random.PRNGKey(_WIDE_VALIDATION_TAG)

    def one(i, family):
        u = jax.random.uniform(jax.random.fold_in(base, i), (_block(n),), tr._float())
        return _pick(
            family, _candidates(u, family, n, dt, horizon_steps, cfg, agile_acc_max, agile_speed_max)
        )

    ids = jnp.asarray([FAMILIES.index(name) for name in names], jnp.int32)
    return jax.vmap(one)(jnp.arange(len(names)), ids)
