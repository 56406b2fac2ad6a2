"""Tests for the reference-trajectory generators (``ttd3_jax.sim.trajectories``, spec §2.3, T1-T8).

The paper's two test tracks are checked against independent float64 numpy
re-implementations of their definitions:

* Spiral-RT (eq. 6): ``p_d(t) = (0.1 t cos(πt/20), 0.1 t sin(πt/20), 0.1 t)`` with
  ``t = k·dt`` in seconds (T2), optionally ``t → s·t``;
* LOS-RT (eq. 7): ``p_d(0) = 0``, ``p_d(1) = (0.1, 0.1, 0.1)``,
  ``p_d(k+1) = p_d(k) + (p cosθ dt, p sinθ dt, 1e-4)`` with θ and p held for
  segments of 100 steps (T3-T7), plus every reading kept as an option.

The training mixture (T8) is checked statistically and for smoothness, and the
config validation, ``vmap``-ability and float64 support are covered as well.

Compilation dominates the runtime, so the expensive batches (2000 training tracks
and their dense references) are built once per module by jitted fixtures, and the
eager ``vmap`` tests use batches of 10 keys so that they share compiled
primitives with :func:`validation_tracks`.  Everything runs on CPU.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.trajectories import (
    NUM_VALIDATION_TRACKS,
    PIECEWISE,
    SPIRAL,
    Track,
    TrackConfig,
    los_rt,
    los_test_track,
    position,
    reference,
    sample_train_track,
    spiral_rt,
    validation_tracks,
)

DT = 1e-3  # s, control period (T1)
NUM_POINTS = 3002  # dense reference length used by the environment (3000 steps + 2)
EPISODE_STEPS = 3000  # 3 s
EPS32 = float(np.finfo(np.float32).eps)

THETA_MAX = math.pi / 120  # rad, LOS deflection bound
P_RANGE = (1.5, 2.5)  # LOS p range
LOS_INIT = np.array([0.1, 0.1, 0.1])  # m, literal p_d(1)
LOS_DZ = 1e-4  # m per step

SPEED_CAP_H = 3.0  # m/s, horizontal speed cap of the training mixture
SPEED_CAP_Z = 0.5  # m/s, vertical speed cap of the training mixture
NUM_MIX_KEYS = 2000
NUM_DENSE_KEYS = 512
NUM_TEST_SEEDS = 21  # LOS-RT seeds 0 (headline) and 1..20


# --------------------------------------------------------------------------- helpers

# Compilation dominates the runtime.  Run eagerly, each generator compiles every op on
# first use (~1.5-2 s per generator and dtype); these jitted wrappers compile in a
# fraction of that.  The eager paths are still exercised (spiral_rt, los_rt, reference,
# and eager vmap of sample_train_track / los_rt).
_reference_jit = jax.jit(reference, static_argnums=(1, 2))
_position_jit = jax.jit(position, static_argnums=2)
_train_one = jax.jit(sample_train_track)
_train_batch = jax.jit(jax.vmap(lambda k: sample_train_track(k)))
_dense_batch = jax.jit(jax.vmap(lambda t: reference(t, DT, NUM_POINTS)))


def keys_from_seeds(seeds) -> jax.Array:
    """Batch of ``PRNGKey(seed)`` keys, shape (len(seeds), 2)."""
    return jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])


def dense(track: Track, jit: bool = False):
    """(pos, vel, acc) of ``reference(track)`` as float64 numpy arrays, each (NUM_POINTS, 3).

    ``jit=True`` goes through ``jax.jit`` (used by the x64 tests, see above).
    """
    ref = (_reference_jit if jit else reference)(track, DT, NUM_POINTS)
    return tuple(np.asarray(x, np.float64) for x in (ref.pos, ref.vel, ref.acc))


def take(tree, i):
    """Track ``i`` of a batched Track."""
    return jax.tree.map(lambda x: x[i], tree)


def assert_trees_close(a, b, rtol=1e-5, atol=1e-6):
    """Leaf-wise comparison of two pytrees with equal structure, dtypes and shapes."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(la, lb, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def float_dtypes(tree) -> set:
    """The set of floating dtypes among the leaves of ``tree`` (arrays or ShapeDtypeStructs)."""
    return {jnp.dtype(x.dtype) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)}


def trees_equal(a, b) -> bool:
    """Bit-for-bit equality of two Tracks (or other pytrees)."""
    if jax.tree.structure(a) != jax.tree.structure(b):
        return False
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in pairs)


def spiral_formula(k, dt: float = DT, scale: float = 1.0) -> np.ndarray:
    """Paper eq. 6 in float64 with t = scale·k·dt seconds; (len(k), 3) m."""
    t = scale * np.asarray(k, np.float64) * dt
    w = math.pi / 20
    return np.stack([0.1 * t * np.cos(w * t), 0.1 * t * np.sin(w * t), 0.1 * t], -1)


def los_draws_from_table(track: Track, cfg: TrackConfig, dt: float = DT):
    """Read back the (θ_j, p_j) the generator drew, from the segment velocity table.

    Inverts ``V_j = (v cosψ_j, v sinψ_j, climb)`` with ``v = p`` (speed reading) or
    ``v = p/dt`` (literal reading), and ``ψ_j = θ_j`` or ``ψ_j = Σ_{i≤j} θ_i``.
    """
    v = np.asarray(track.seg_v, np.float64)
    psi = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    speed = np.hypot(v[:, 0], v[:, 1])
    p = speed if cfg.los_p_is_speed else speed * dt
    theta = np.diff(psi, prepend=0.0) if cfg.los_heading == "cumulative" else psi
    return theta, p


def los_recursion(theta, p, cfg: TrackConfig, num_points: int = NUM_POINTS, dt: float = DT) -> np.ndarray:
    """Independent float64 LOS-RT recursion (eq. 7 under the readings in ``cfg``).

    ``p_d(0) = 0``; under the literal start ``p_d(1) = (0.1, 0.1, 0.1)``; otherwise
    every step, ``p_d(k+1) = p_d(k) + (ℓ cosψ, ℓ sinψ, 1e-4)`` where ℓ = p·dt (or p)
    and ψ, ℓ belong to segment ``k // S``.
    """
    S = cfg.los_segment_steps
    psi = np.cumsum(theta) if cfg.los_heading == "cumulative" else np.asarray(theta)
    length = np.asarray(p) * (dt if cfg.los_p_is_speed else 1.0)
    dz = cfg.los_climb_rate * dt
    pos = np.zeros((num_points, 3))
    first = 0
    if cfg.los_literal_init:
        pos[1] = cfg.los_init_point
        first = 1
    for k in range(first, num_points - 1):
        j = k // S
        pos[k + 1] = pos[k] + (length[j] * math.cos(psi[j]), length[j] * math.sin(psi[j]), dz)
    return pos


def per_step_heading_and_length(pos: np.ndarray):
    """Horizontal heading (rad) and length (m) of each step p_d(k) → p_d(k+1)."""
    inc = np.diff(pos, axis=0)
    return np.arctan2(inc[:, 1], inc[:, 0]), np.hypot(inc[:, 0], inc[:, 1]), inc[:, 2]


def segment_slices(num_points: int, seg_steps: int, first: int):
    """Slices of step indices k (step k → k+1) belonging to each segment, skipping k < first."""
    out = []
    for start in range(0, num_points - 1, seg_steps):
        lo, hi = max(start, first), min(start + seg_steps, num_points - 1)
        if lo < hi:
            out.append(slice(lo, hi))
    return out


def is_dynamics_track(tracks: Track) -> np.ndarray:
    """Piecewise tracks with non-zero acceleration are the "dynamics-generated" kind."""
    return (np.asarray(tracks.kind) == PIECEWISE) & np.any(np.asarray(tracks.seg_a) != 0, axis=(-2, -1))


def is_los_track(tracks: Track) -> np.ndarray:
    return (np.asarray(tracks.kind) == PIECEWISE) & np.all(np.asarray(tracks.seg_a) == 0, axis=(-2, -1))


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module", autouse=True)
def _on_cpu():
    """Run this module on the CPU even where an accelerator is present (without touching
    the process-wide platform setting other test modules may rely on)."""
    with jax.default_device(jax.devices("cpu")[0]):
        yield


@pytest.fixture(scope="module")
def train_tracks() -> Track:
    """Training tracks for keys PRNGKey(0..1999) (so indices 0..20 are the test seeds)."""
    return _train_batch(jax.vmap(jax.random.PRNGKey)(jnp.arange(NUM_MIX_KEYS)))


@pytest.fixture(scope="module")
def train_dense(train_tracks):
    """Dense (pos, vel, acc) float64 arrays (N, NUM_POINTS, 3) for the first NUM_DENSE_KEYS tracks."""
    ref = _dense_batch(take(train_tracks, slice(0, NUM_DENSE_KEYS)))
    return tuple(np.asarray(x, np.float64) for x in (ref.pos, ref.vel, ref.acc))


@pytest.fixture(scope="module")
def val_tracks() -> Track:
    return validation_tracks()


# --------------------------------------------------------------------------- 1. Spiral-RT


@pytest.mark.parametrize("scale", [1.0, 2.0])
def test_spiral_rt_matches_paper_formula(scale):
    track = spiral_rt(TrackConfig(spiral_time_scale=scale))
    steps = np.array([0, 1, 17, 1500, 3001])
    expected = spiral_formula(steps, scale=scale)
    np.testing.assert_allclose(np.asarray(_position_jit(track, steps, DT)), expected, rtol=1e-5, atol=1e-7)
    pos, _, _ = dense(track)
    np.testing.assert_allclose(pos[steps], expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(pos, spiral_formula(np.arange(NUM_POINTS), scale=scale), rtol=1e-5, atol=1e-6)
    assert int(track.kind) == SPIRAL


def test_spiral_rt_endpoint_and_speed():
    """T2: t in seconds, the track runs 0 → (0.27, 0.14, 0.30) m at ≤ 0.15 m/s."""
    pos, vel, _ = dense(spiral_rt())
    np.testing.assert_allclose(pos[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(pos[EPISODE_STEPS], [0.27, 0.14, 0.30], atol=5e-3)
    assert np.linalg.norm(vel, axis=-1).max() <= 0.15


def test_spiral_rt_float64_exact():
    with jax.enable_x64(True):
        track = spiral_rt(TrackConfig(spiral_time_scale=2.0))
        pos = np.asarray(_reference_jit(track, DT, NUM_POINTS).pos)
    assert float_dtypes(track) == {jnp.dtype(jnp.float64)}
    assert pos.dtype == np.float64
    np.testing.assert_allclose(pos, spiral_formula(np.arange(NUM_POINTS), scale=2.0), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- 2. LOS-RT

LOS_CONFIGS = {
    "default": TrackConfig(),
    "cumulative": TrackConfig(los_heading="cumulative"),
    "p_per_step": TrackConfig(los_p_is_speed=False),
    "no_literal_init": TrackConfig(los_literal_init=False),
    "segment_1": TrackConfig(los_segment_steps=1),
}


def los_position_tolerance(pos: np.ndarray) -> float:
    """float32 evaluation error bound for LOS positions of this magnitude."""
    return 64 * EPS32 * (1.0 + np.abs(pos).max())


@pytest.mark.parametrize("seed", [0, 13])
@pytest.mark.parametrize("name", list(LOS_CONFIGS))
def test_los_rt_matches_numpy_recursion(name, seed):
    cfg = LOS_CONFIGS[name]
    track = los_test_track(seed, cfg)
    theta, p = los_draws_from_table(track, cfg)
    expected = los_recursion(theta, p, cfg)
    pos, _, _ = dense(track)
    np.testing.assert_allclose(pos, expected, rtol=0, atol=los_position_tolerance(expected))
    # The draws themselves are in the paper's ranges ...
    assert np.all(np.abs(theta) <= THETA_MAX * (1 + 1e-6))
    assert np.all((p >= P_RANGE[0] * (1 - 1e-6)) & (p <= P_RANGE[1] * (1 + 1e-6)))
    # ... and they are actually random (not a constant table).
    used = (NUM_POINTS - 2) // cfg.los_segment_steps + 1
    assert np.ptp(theta[:used]) > 0.2 * THETA_MAX and np.ptp(p[:used]) > 0.2
    assert int(track.kind) == PIECEWISE
    np.testing.assert_array_equal(np.asarray(track.seg_a), 0.0)


@pytest.mark.parametrize("seed", [0, 13])
@pytest.mark.parametrize("name", list(LOS_CONFIGS))
def test_los_rt_geometry_from_positions(name, seed):
    """Check the polyline from positions only: start, jump, per-segment heading/length/climb."""
    cfg = LOS_CONFIGS[name]
    pos, _, _ = dense(los_test_track(seed, cfg))
    S = cfg.los_segment_steps
    np.testing.assert_array_equal(pos[0], 0.0)
    first = 1 if cfg.los_literal_init else 0
    if cfg.los_literal_init:
        np.testing.assert_allclose(pos[1], LOS_INIT, atol=1e-7)

    heading, length, dz = per_step_heading_and_length(pos)
    lo, hi = (x * (DT if cfg.los_p_is_speed else 1.0) for x in P_RANGE)
    # float32 resolution of one step (~1.5e-3 m, or ~1.5 m literal) at positions up to ~8 m (8 km)
    rel = 1e-3
    np.testing.assert_allclose(dz[first:], LOS_DZ, atol=1e-3 * LOS_DZ + 2 * EPS32 * np.abs(pos[:, 2]).max())
    assert np.all(length[first:] >= lo * (1 - rel)) and np.all(length[first:] <= hi * (1 + rel))

    seg_heading = []
    for sl in segment_slices(NUM_POINTS, S, first):
        h, ell = heading[sl], length[sl]
        assert np.ptp(h) <= rel, f"heading varies inside segment {sl}"
        assert np.ptp(ell) <= rel * ell.mean(), f"step length varies inside segment {sl}"
        seg_heading.append(h.mean())
    seg_heading = np.unwrap(np.array(seg_heading))

    if cfg.los_heading == "absolute":
        assert np.all(np.abs(seg_heading) <= THETA_MAX + rel)
    else:  # ψ_j = Σ θ_i: the heading changes by at most π/120 per segment
        assert abs(seg_heading[0]) <= THETA_MAX + rel
        assert np.all(np.abs(np.diff(seg_heading)) <= THETA_MAX + 2 * rel)
    # θ/p are redrawn at segment boundaries: the heading changes between most segments.
    changes = np.abs(np.diff(seg_heading)) > 2 * rel
    assert changes.mean() > 0.5


def test_los_heading_modes_share_draws():
    """Same key: the cumulative heading is the running sum of the absolute headings."""
    absolute = los_draws_from_table(los_test_track(0), TrackConfig())[0]
    cfg = TrackConfig(los_heading="cumulative")
    cumulative_theta = los_draws_from_table(los_test_track(0, cfg), cfg)[0]
    np.testing.assert_allclose(cumulative_theta, absolute, atol=1e-5)
    y_abs = dense(los_test_track(0))[0][:, 1]
    y_cum = dense(los_test_track(0, cfg))[0][:, 1]
    assert np.abs(y_abs).max() < 0.3  # nearly straight (T5: max |y| ≈ 0.14 m)
    assert np.abs(y_cum - y_abs).max() > 0.05  # the heading modes do differ


def test_los_literal_and_speed_readings_relate():
    """Same key: p-per-step is 1/dt times longer horizontally; no-jump start only shifts the track."""
    base = dense(los_test_track(3))[0]
    per_step = dense(los_test_track(3, TrackConfig(los_p_is_speed=False)))[0]
    no_jump = dense(los_test_track(3, TrackConfig(los_literal_init=False)))[0]
    d_base, d_step = np.diff(base[1:], axis=0), np.diff(per_step[1:], axis=0)
    np.testing.assert_allclose(d_step[:, :2], d_base[:, :2] / DT, rtol=5e-3, atol=5e-3)
    np.testing.assert_allclose(d_step[:, 2], d_base[:, 2], atol=1e-5)
    # No literal start: p_d(1) = p_d(0) + first increment (no 0.17 m jump) ...
    np.testing.assert_allclose(no_jump[1] - no_jump[0], base[2] - base[1], atol=1e-6)
    assert np.linalg.norm(no_jump[1]) < 3e-3
    # ... and for k >= 1 the literal track is the same polyline shifted by (0.1,0.1,0.1) - p_d(1).
    shift = np.broadcast_to(LOS_INIT - no_jump[1], base[1:].shape)
    np.testing.assert_allclose(base[1:] - no_jump[1:], shift, atol=1e-5)


def test_los_test_track_is_los_rt_of_prngkey():
    assert trees_equal(los_test_track(5), los_rt(jax.random.PRNGKey(5)))
    assert not trees_equal(los_test_track(5), los_test_track(6))


# --------------------------------------------------------------------------- 3. derivatives


def test_spiral_reference_derivatives_are_consistent():
    """Central differences of the spiral agree with vel/acc to O(dt²) (float64)."""
    with jax.enable_x64(True):
        for scale in (1.0, 2.0):
            pos, vel, acc = dense(spiral_rt(TrackConfig(spiral_time_scale=scale)), jit=True)
            v_fd = (pos[2:] - pos[:-2]) / (2 * DT)
            a_fd = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) / DT**2
            # |p'''| <= a·s³·Ω²·(3 + Ω·s·t) < 1e-2·s³ over 3 s, so the error is <= dt²/6 of that
            assert np.abs(v_fd - vel[1:-1]).max() < 2e-9 * scale**3
            # truncation dt²/12·|p⁗| plus roundoff ~4·eps·|p|/dt², together < 1e-8·s⁴
            assert np.abs(a_fd - acc[1:-1]).max() < 1e-8 * scale**4
            assert np.abs(acc).max() > 1e-3  # a genuinely curved track


def test_spiral_reference_derivatives_float32():
    pos, vel, acc = dense(spiral_rt())
    np.testing.assert_allclose((pos[2:] - pos[:-2]) / (2 * DT), vel[1:-1], atol=1e-4)
    np.testing.assert_allclose((vel[2:] - vel[:-2]) / (2 * DT), acc[1:-1], atol=1e-4)
    np.testing.assert_allclose(vel[0], [0.1, 0.0, 0.1], atol=1e-7)  # analytic dp/dt at t = 0


@pytest.mark.parametrize("name", list(LOS_CONFIGS))
def test_los_reference_derivatives(name):
    cfg = LOS_CONFIGS[name]
    track = los_test_track(2, cfg)
    pos, vel, acc = dense(track)
    first = 1 if cfg.los_literal_init else 0
    scale = 1.0 if cfg.los_p_is_speed else 1.0 / DT
    v_fd = np.diff(pos, axis=0) / DT
    tol = los_position_tolerance(pos) / DT * 4
    np.testing.assert_allclose(v_fd[first:], vel[first:-1], atol=tol)
    # vel is the segment velocity (p cosψ, p sinψ, 0.1) and acc is exactly zero
    seg = np.asarray(track.seg_v, np.float64)[np.arange(NUM_POINTS) // cfg.los_segment_steps]
    np.testing.assert_allclose(vel, seg, rtol=1e-6)
    np.testing.assert_allclose(vel[:, 2], 0.1, rtol=1e-6)
    speed = np.hypot(vel[:, 0], vel[:, 1]) / scale
    assert np.all((speed >= 1.5 - 1e-5) & (speed <= 2.5 + 1e-5))
    np.testing.assert_array_equal(acc, 0.0)
    if cfg.los_literal_init:  # the literal jump: 0 → (0.1, 0.1, 0.1) in one step
        np.testing.assert_allclose(pos[1] - pos[0], LOS_INIT, atol=1e-7)
        assert np.linalg.norm(v_fd[0] - vel[0]) > 100.0


def test_train_reference_derivatives_away_from_boundaries(train_tracks, train_dense):
    pos, vel, acc = train_dense
    seg_steps = np.asarray(train_tracks.seg_steps)[:NUM_DENSE_KEYS]
    first = np.asarray(train_tracks.first_step)[:NUM_DENSE_KEYS]
    kind = np.asarray(train_tracks.kind)[:NUM_DENSE_KEYS]
    k = np.arange(1, NUM_POINTS - 1)
    v_fd = (pos[:, 2:] - pos[:, :-2]) / (2 * DT)
    a_fd = (vel[:, 2:] - vel[:, :-2]) / (2 * DT)
    for i in range(NUM_DENSE_KEYS):
        # velocity may jump at a boundary jS (LOS): the acceleration stencil at jS-1 straddles it too
        smooth = kind[i] == SPIRAL
        interior = (k > first[i]) & (smooth | (k % seg_steps[i] != 0))
        interior_a = interior & (smooth | ((k + 1) % seg_steps[i] != 0))
        tol_v = 8 * EPS32 * (1 + np.abs(pos[i]).max()) / (2 * DT) + 1e-5
        tol_a = 8 * EPS32 * (1 + np.abs(vel[i]).max()) / (2 * DT) + 1e-4
        err_v = np.abs(v_fd[i] - vel[i, 1:-1])[interior].max()
        err_a = np.abs(a_fd[i] - acc[i, 1:-1])[interior_a].max()
        assert err_v <= tol_v, f"track {i} (kind {kind[i]}): velocity error {err_v}"
        assert err_a <= tol_a, f"track {i} (kind {kind[i]}): acceleration error {err_a}"


def test_train_tracks_are_continuous(train_tracks, train_dense):
    """No position jump above max speed·dt, except the literal LOS start (k = 0 → 1)."""
    pos = train_dense[0]
    first = np.asarray(train_tracks.first_step)[:NUM_DENSE_KEYS]
    step = np.linalg.norm(np.diff(pos, axis=1), axis=-1)  # (N, NUM_POINTS-1)
    max_step = math.hypot(SPEED_CAP_H, SPEED_CAP_Z) * DT + 1e-5
    assert np.all(step[:, 1:] <= max_step)
    assert np.all(step[first == 0, 0] <= max_step)
    # the literal-start tracks jump to (0.1, 0.1, 0.1), and both kinds of start occur
    literal = first == 1
    assert 0 < literal.sum() < NUM_DENSE_KEYS
    np.testing.assert_allclose(pos[literal, 1], np.broadcast_to(LOS_INIT, (literal.sum(), 3)), atol=1e-6)


# --------------------------------------------------------------------------- 4. vmap


def test_vmap_sample_train_track_matches_one_by_one(train_tracks):
    keys = keys_from_seeds(range(10))
    batched = jax.vmap(lambda k: sample_train_track(k))(keys)
    assert batched.seg_p.shape[0] == 10 and batched.kind.shape == (10,)
    for i in (0, 3, 9):
        assert_trees_close(take(batched, i), _train_one(keys[i]))
    assert_trees_close(batched, take(train_tracks, slice(0, 10)))  # jit(vmap) agrees too


def test_vmap_los_rt_matches_one_by_one():
    keys = keys_from_seeds(range(10))
    batched = jax.vmap(los_rt)(keys)
    assert batched.seg_p.shape[0] == 10 and batched.kind.shape == (10,)
    for i in (0, 5, 9):
        assert_trees_close(take(batched, i), los_test_track(i))


def test_generation_is_deterministic_per_key():
    key = jax.random.PRNGKey(42)
    assert trees_equal(_train_one(key), _train_one(key))
    assert trees_equal(los_rt(key), los_rt(key))


def test_different_keys_give_different_tracks(train_dense):
    pos = train_dense[0][:64, :EPISODE_STEPS:10].reshape(64, -1)
    dist = np.abs(pos[:, None] - pos[None]).max(axis=-1)
    off_diagonal = dist[~np.eye(len(pos), dtype=bool)]
    assert off_diagonal.min() > 1e-3
    los = [dense(los_test_track(s))[0] for s in range(4)]
    for a in range(4):
        for b in range(a + 1, 4):
            assert np.abs(los[a] - los[b]).max() > 1e-3


# --------------------------------------------------------------------------- 5. training mixture


def test_train_tracks_start_at_origin(train_tracks):
    p0 = jax.jit(jax.vmap(lambda t: position(t, 0, DT)))(train_tracks)
    assert p0.shape == (NUM_MIX_KEYS, 3)
    np.testing.assert_array_equal(np.asarray(p0), 0.0)


def test_train_speed_caps(train_dense):
    pos, vel, _ = train_dense
    k = slice(0, EPISODE_STEPS + 1)
    speed_h = np.hypot(vel[:, k, 0], vel[:, k, 1])
    assert speed_h.max() <= SPEED_CAP_H * (1 + 1e-5)
    assert np.abs(vel[:, k, 2]).max() <= SPEED_CAP_Z * (1 + 1e-5)
    step_h = np.hypot(*np.moveaxis(np.diff(pos[:, 1 : EPISODE_STEPS + 1, :2], axis=1), -1, 0)) / DT
    assert step_h.max() <= SPEED_CAP_H + 1e-2
    assert speed_h.max() > 0.8 * SPEED_CAP_H  # the bound is exercised, not vacuous


def test_train_mixture_fractions(train_tracks):
    kind = np.asarray(train_tracks.kind)
    dyn, los = is_dynamics_track(train_tracks), is_los_track(train_tracks)
    assert np.all(dyn ^ los ^ (kind == SPIRAL))  # each track is exactly one kind
    fractions = np.array([dyn.mean(), (kind == SPIRAL).mean(), los.mean()])
    # binomial std ≈ 0.011 for n = 2000: allow ~4.5σ
    np.testing.assert_allclose(fractions, TrackConfig().train_mix, atol=0.05)
    # the kinds look like what they claim to be
    spiral = kind == SPIRAL
    assert np.all(np.asarray(train_tracks.gain)[spiral] > 0)
    assert np.all(np.asarray(train_tracks.first_step)[dyn] == 0)


@pytest.mark.parametrize(
    ("mix", "predicate"),
    [
        ((0.0, 1.0, 0.0), lambda t: np.asarray(t.kind) == SPIRAL),
        ((1.0, 0.0, 0.0), is_dynamics_track),
        ((0.0, 0.0, 1.0), is_los_track),
    ],
    ids=["spiral_only", "dynamics_only", "los_only"],
)
def test_custom_train_mix_gives_one_kind(mix, predicate):
    cfg = TrackConfig(train_mix=mix)
    # 10 keys: under the default mixture all 10 would share one kind with probability < 1e-3
    tracks = jax.vmap(lambda k: sample_train_track(k, cfg))(keys_from_seeds(range(100, 110)))
    assert np.all(predicate(tracks))


# --------------------------------------------------------------------------- 6. test instances never drawn


def test_train_tracks_are_not_test_instances(train_tracks, train_dense):
    """Training keys PRNGKey(0..20) never reproduce LOS-RT seeds 0..20 or Spiral-RT."""
    spiral = dense(spiral_rt())[0]
    for s in (0, NUM_TEST_SEEDS - 1):  # the batch holds the one-by-one draws
        np.testing.assert_allclose(
            dense(_train_one(jax.random.PRNGKey(s)))[0], train_dense[0][s], rtol=1e-5, atol=1e-5
        )
    for s in range(NUM_TEST_SEEDS):
        pos = train_dense[0][s]
        assert np.abs(pos - dense(los_test_track(s))[0]).max() > 1e-2
        assert np.abs(pos - spiral).max() > 1e-2
        assert not trees_equal(take(train_tracks, s), los_test_track(s))


def test_validation_tracks_fixed_and_distinct(val_tracks):
    assert val_tracks.kind.shape == (NUM_VALIDATION_TRACKS,)
    assert val_tracks.seg_p.shape[0] == NUM_VALIDATION_TRACKS == 10
    assert trees_equal(val_tracks, validation_tracks())
    val_pos = [dense(take(val_tracks, i))[0] for i in range(NUM_VALIDATION_TRACKS)]
    test_pos = [dense(spiral_rt())[0]] + [dense(los_test_track(s))[0] for s in range(NUM_TEST_SEEDS)]
    for v in val_pos:
        np.testing.assert_array_equal(v[0], 0.0)
        for t in test_pos:
            assert np.abs(v - t).max() > 1e-2
    for a in range(NUM_VALIDATION_TRACKS):
        for b in range(a + 1, NUM_VALIDATION_TRACKS):
            assert np.abs(val_pos[a] - val_pos[b]).max() > 1e-3


# --------------------------------------------------------------------------- 7. config validation


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("los_heading", "relative"),
        ("los_segment_steps", 0),
        ("los_segment_steps", 2.5),
        ("los_theta_max", -0.1),
        ("train_mix", (-0.1, 0.6, 0.5)),
        ("train_mix", (0.5, 0.5)),
        ("train_mix", (0.0, 0.0, 0.0)),
        ("spiral_time_scale", 0.0),
        ("spiral_time_scale", -1.0),
        ("los_speed", (2.5, 1.5)),
        ("los_speed", (-1.0, 1.5)),
    ],
)
def test_track_config_rejects_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        TrackConfig(**{field: value})


def test_track_config_accepts_edge_values():
    """Boundary values are legal: θmax = 0 gives a straight LOS line, S = 1 a redraw every step."""
    cfg = TrackConfig(
        los_heading="cumulative", los_segment_steps=1, los_p_is_speed=False, los_literal_init=False,
        los_theta_max=0.0, los_speed=(2.0, 2.0), spiral_time_scale=1e-3, train_mix=(0.0, 1.0, 0.0),
    )  # fmt: skip
    pos, _, _ = dense(los_test_track(0, cfg))
    np.testing.assert_array_equal(pos[:, 1], 0.0)
    np.testing.assert_allclose(np.diff(pos[:, 0]), 2.0, rtol=1e-3)  # 2 m per step (literal p)


@pytest.mark.parametrize("seed", [-1, 1.5])
def test_los_test_track_rejects_bad_seed(seed):
    with pytest.raises(ValueError, match="seed"):
        los_test_track(seed)


# --------------------------------------------------------------------------- 8. float64


@pytest.mark.parametrize("name", ["default", "cumulative", "p_per_step", "no_literal_init"])
def test_los_float64_matches_recursion(name):
    cfg = LOS_CONFIGS[name]
    with jax.enable_x64(True):
        track = los_test_track(0, cfg)
        ref = _reference_jit(track, DT, NUM_POINTS)
        pos, vel, acc = (np.asarray(x) for x in (ref.pos, ref.vel, ref.acc))
    assert float_dtypes(track) == {jnp.dtype(jnp.float64)}
    assert pos.dtype == vel.dtype == acc.dtype == np.float64
    theta, p = los_draws_from_table(track, cfg)
    expected = los_recursion(theta, p, cfg)
    scale = 1.0 if cfg.los_p_is_speed else 1e3  # the literal reading runs over kilometres
    np.testing.assert_allclose(pos, expected, rtol=0, atol=1e-10 * scale)
    assert np.abs(theta).max() <= THETA_MAX and p.min() >= P_RANGE[0] and p.max() <= P_RANGE[1]


def test_training_generators_float64_dtypes():
    with jax.enable_x64(True):
        one = jax.eval_shape(sample_train_track, jax.random.PRNGKey(0))
        val = jax.eval_shape(validation_tracks)
        ref = jax.eval_shape(lambda t: reference(t, DT, NUM_POINTS), one)
    for tree in (one, val, ref):
        assert float_dtypes(tree) == {jnp.dtype(jnp.float64)}
    assert one.kind.dtype == jnp.int32 and one.seg_steps.dtype == jnp.int32
    # and the default is float32
    assert float_dtypes(jax.eval_shape(sample_train_track, jax.random.PRNGKey(0))) == {jnp.dtype(jnp.float32)}


def test_los_test_instance_does_not_depend_on_the_horizon():
    short = tr.los_test_track(3, num_segments=13, horizon_steps=1102)
    std = tr.los_test_track(3)
    long = tr.los_test_track(3, horizon_steps=6002)
    k = jnp.arange(1100)
    np.testing.assert_array_equal(tr.position(short, k, 1e-3), tr.position(std, k, 1e-3))
    k = jnp.arange(3002)
    np.testing.assert_array_equal(tr.position(std, k, 1e-3), tr.position(long, k, 1e-3))
