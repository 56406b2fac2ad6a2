"""Tests for the wide training-track families (``ttd3_jax.sim.track_families``, issue 37).

One module fixture draws 2048 tracks of the default wide mixture (plus the draws of the keys
the test tracks and the validation sets are made from) with one jitted ``vmap``; the
family statistics, bounds and the exclusion of the suite and test tracks are read from it.
Everything runs on CPU.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.control import generalization as gen
from ttd3_jax.sim import track_families as tf
from ttd3_jax.sim import trajectories as tr

DT = 1e-3  # s
NUM_POINTS = 3002  # the env's dense reference length
COMPARE_STEPS = 3001  # k = 0 … 3000: the first 3 s, an episode of the suite and the test tracks
NUM_DRAWS = 2048
NUM_TEST_SEEDS = 21  # LOS-RT seeds 0 … 20
MIN_RMS = 0.05  # m: half the env's ±0.1 m initial-position spread; no draw comes closer to a held-out track
# m: the same for the paper's three families, whose ranges contain Spiral-RT's parameters and
# spiral_fast's (docs/paper-notes.md, T8): random spirals come within 5-9 cm of them over 3 s
MIN_RMS_PAPER = 0.02
FAMILY = {name: i for i, name in enumerate(tf.FAMILIES)}


def training_keys() -> jax.Array:
    """Keys as the env draws them, plus the keys the test and validation tracks come from
    (a training key equal to one of those must still give another track)."""
    own = jax.random.split(jax.random.PRNGKey(2026), NUM_DRAWS)
    seeds = jnp.stack([jax.random.PRNGKey(s) for s in range(NUM_TEST_SEEDS)])
    tags = (tr._VALIDATION_TAG, tf._WIDE_VALIDATION_TAG)
    folds = [
        jax.random.fold_in(jax.random.PRNGKey(t), i) for t in tags for i in range(tr.NUM_VALIDATION_TRACKS)
    ]
    return jnp.concatenate([own, seeds, jnp.stack(folds)])


@jax.jit
def _draw(keys):
    tracks, family = jax.vmap(lambda k: tf.sample_wide_track(k, with_family=True))(keys)
    ref = jax.vmap(lambda t: tr.reference(t, DT, NUM_POINTS))(tracks)
    return tracks, family, ref


@pytest.fixture(scope="module")
def draws():
    tracks, family, ref = _draw(training_keys())
    return tracks, np.asarray(family), *(np.asarray(x, np.float64) for x in (ref.pos, ref.vel, ref.acc))


def rms_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) RMS position differences over the first 3 s, starts aligned."""
    x = (a[:, :COMPARE_STEPS] - a[:, :1]).reshape(len(a), -1)
    y = (b[:, :COMPARE_STEPS] - b[:, :1]).reshape(len(b), -1)
    d2 = (x * x).sum(1)[:, None] + (y * y).sum(1)[None] - 2.0 * x @ y.T
    return np.sqrt(np.maximum(d2, 0.0) / COMPARE_STEPS)


def dense_pos(track: tr.Track) -> np.ndarray:
    return np.asarray(tr.position(track, jnp.arange(COMPARE_STEPS), DT), np.float64)


def take(tracks: tr.Track, i: int) -> tr.Track:
    return jax.tree.map(lambda x: x[i], tracks)


def held_out_tracks() -> dict[str, np.ndarray]:
    """Every generalisation-suite track and the test tracks Spiral-RT and LOS-RT seeds 0 … 20."""
    out = {name: dense_pos(t) for name, t in gen.suite_tracks("generalization").items()}
    out["spiral_rt"] = dense_pos(tr.spiral_rt())
    out |= {f"los_rt_seed{s:02d}": dense_pos(tr.los_test_track(s)) for s in range(NUM_TEST_SEEDS)}
    return out


def test_family_frequencies_follow_the_weights(draws):
    family = draws[1][:NUM_DRAWS]
    freq = np.bincount(family, minlength=len(tf.FAMILIES)) / NUM_DRAWS
    w = np.asarray(tf.WIDE_MIX) / sum(tf.WIDE_MIX)
    assert np.all(np.abs(freq - w) <= 4.5 * np.sqrt(w * (1 - w) / NUM_DRAWS)), freq  # 4.5 binomial σ


@pytest.mark.parametrize("only", ["step", "circle", "los_fast"])
def test_a_single_family_weight_draws_only_it(only):
    weights = tuple(float(name == only) for name in tf.FAMILIES)
    keys = jax.random.split(jax.random.PRNGKey(1), 16)
    _, family = jax.jit(jax.vmap(lambda k: tf.sample_wide_track(k, weights, with_family=True)))(keys)
    assert np.all(np.asarray(family) == FAMILY[only])


def test_paper_only_weights_draw_the_paper_families():
    keys = jax.random.split(jax.random.PRNGKey(2), 64)
    _, family = jax.jit(jax.vmap(lambda k: tf.sample_wide_track(k, tf.PAPER_ONLY, with_family=True)))(keys)
    assert set(np.asarray(family).tolist()) == {0, 1, 2}


def test_every_track_starts_at_the_origin_and_the_families_from_hover_start_at_rest(draws):
    _, family, pos, vel, _ = draws
    assert np.all(pos[:, 0] == 0.0)
    at_rest = np.isin(family, [FAMILY[f] for f in ("dynamics", "step", "agile", "vertical")])
    # (a tabulated curve's table is within 1 cm/s of the curve's velocity, 0 at the start)
    assert np.abs(vel[at_rest, 0]).max() < 1e-2
    curves = np.isin(family, [FAMILY["circle"], FAMILY["figure8"]])
    spin_up = np.linalg.norm(vel[curves, 0], axis=-1) < 1e-2  # else >= 0.5 m/s
    assert abs(spin_up.mean() - tf.CURVE_RAMP_P) < 0.1  # half spin up from hover, half start at speed


def test_position_is_continuous_except_for_steps(draws):
    tracks, family, pos, vel, _ = draws
    jump = np.linalg.norm(np.diff(pos, axis=1), axis=-1)  # m per step
    speed = np.linalg.norm(vel, axis=-1)
    smooth = ~np.isin(family, [FAMILY["step"], FAMILY["los"]])
    # |Δp| ≤ max(|v_k|, |v_k+1|)·dt + ½|a|dt² ≤ that + 3e-6 m (|a| ≤ 6 m/s²): no jump
    bound = np.maximum(speed[:, :-1], speed[:, 1:]) * DT + 1e-5
    assert np.all(jump[smooth] <= bound[smooth])
    los = family == FAMILY["los"]  # the paper's LOS: only its literal start p_d(1) jumps
    assert np.all(jump[los, 1:] <= bound[los, 1:])
    steps = np.flatnonzero(family == FAMILY["step"])
    assert steps.size > 100
    for i in steps:
        at = np.flatnonzero(jump[i] > 0)
        hold = int(tracks.seg_steps[i])
        assert np.all(vel[i] == 0.0) and at.size >= 1 and np.all((at + 1) % hold == 0)
        assert round(tf.STEP_HOLD_S[0] / DT) <= at[0] + 1 <= round(tf.STEP_HOLD_S[1] / DT)
        assert np.all((jump[i, at] > tf.STEP_SIZE[0] - 1e-5) & (jump[i, at] < tf.STEP_SIZE[1] + 1e-5))


def family_arrays(draws, name):
    _, family, pos, vel, acc = draws
    m = family == FAMILY[name]
    assert m.sum() > 100
    return pos[m, :COMPARE_STEPS], vel[m, :COMPARE_STEPS], acc[m, :COMPARE_STEPS]


def test_curves_and_vertical_respect_their_bounds(draws):
    for name in ("circle", "figure8", "vertical"):
        _, vel, acc = family_arrays(draws, name)
        speed, a = np.linalg.norm(vel, axis=-1), np.linalg.norm(acc, axis=-1)
        top = tf.CURVE_SPEED[1] if name != "vertical" else math.hypot(tf.VERT_CLIMB, tf.VERT_DRIFT) + 2.0
        assert speed.max() <= top + 0.01, name
        assert a.max() <= 6.0, name  # 5.6 m/s² by construction (module docstring)
        assert a.max() > 4.0 and speed.max() > 3.0, name  # the bounds are exercised
    _, vel, acc = family_arrays(draws, "vertical")
    assert np.abs(vel[..., 2]).max() > 2.5 and np.abs(acc[..., 2]).max() > 4.0  # climbs and bobs


def test_agile_tracks_respect_their_bounds(draws):
    _, vel, acc = family_arrays(draws, "agile")
    cap_h, cap_z = tf.AGILE_SPEED_MAX
    speed_h = np.linalg.norm(vel[..., :2], axis=-1)
    assert speed_h.max() <= cap_h * (1 + 1e-5) and np.abs(vel[..., 2]).max() <= cap_z * (1 + 1e-5)
    assert speed_h.max() > 0.95 * cap_h
    bound = np.asarray(tf.AGILE_ACC_MAX)
    # the cap only ever shortens the drawn acceleration; one axis can pass its bound a little
    assert np.all(np.linalg.norm(acc[..., :2], axis=-1) <= np.linalg.norm(bound[:2]) + 1e-4)
    assert np.all(np.abs(acc) <= 1.05 * bound) and np.all(np.abs(acc).max(axis=(0, 1)) > 0.9 * bound)


def test_agile_bounds_are_configurable():
    keys = jax.random.split(jax.random.PRNGKey(3), 32)
    weights = tuple(float(n == "agile") for n in tf.FAMILIES)
    draw = lambda k: tf.sample_wide_track(
        k, weights, agile_acc_max=(1.0, 2.0, 0.5), agile_speed_max=(2.0, 0.3)
    )  # noqa: E731
    ref = jax.vmap(lambda t: tr.reference(t, DT, NUM_POINTS))(jax.jit(jax.vmap(draw))(keys))
    vel, acc = np.asarray(ref.vel), np.asarray(ref.acc)
    assert np.linalg.norm(vel[..., :2], axis=-1).max() <= 2.0 * (1 + 1e-5)
    assert np.abs(vel[..., 2]).max() <= 0.3 * (1 + 1e-5)
    assert np.all(np.abs(acc).max(axis=(0, 1)) <= 1.05 * np.array([1.0, 2.0, 0.5]))


def test_los_legs_reach_4_5_m_s(draws):
    _, vel, acc = family_arrays(draws, "los_fast")
    speed_h = np.linalg.norm(vel[..., :2], axis=-1)
    assert np.all(acc == 0.0) and np.all(np.abs(vel[..., 2]) <= tf.LOS_FAST_CLIMB + 1e-6)
    assert speed_h.min() >= tf.LOS_FAST_SPEED[0] - 1e-5 and speed_h.max() <= tf.LOS_FAST_SPEED[1] + 1e-5
    assert speed_h.max() > 4.4


@pytest.mark.parametrize("draw", [tf.circle_curve, tf.figure8_curve, tf.vertical_curve])
def test_curve_tables_follow_their_curves(draw):
    """The segment table is within 0.1 mm (position) and 1 cm/s (velocity) of the curve."""
    n = tf.wide_num_segments(NUM_POINTS, DT)
    steps = -(-NUM_POINTS // n)
    t = jnp.arange(NUM_POINTS) * DT

    def errors(u):
        c = draw(u)
        p = lambda t: tf.curve_position(c, t)  # noqa: E731
        ref = tr.reference(tf._curve_table(c, n, steps, DT, u.dtype), DT, NUM_POINTS)
        v = jax.vmap(lambda s: jax.jvp(lambda x: p(x[None])[0], (s,), (jnp.ones_like(s),))[1])(t)
        return jnp.abs(ref.pos - p(t)).max(), jnp.abs(ref.vel - v)[1:].max()  # k = 0: a start at speed

    u = jax.random.uniform(jax.random.PRNGKey(4), (64, 8))
    pos_err, vel_err = jax.jit(jax.vmap(errors))(u)
    assert steps * DT <= tf.CURVE_SEG_S
    assert float(pos_err.max()) < 1e-4 and float(vel_err.max()) < 1e-2


def test_no_suite_or_test_track_is_trained_on(draws):
    """No draw, from the env's keys or from the keys the held-out tracks came from, is within
    MIN_RMS (a draw of the paper's families: MIN_RMS_PAPER) of a generalisation-suite track,
    Spiral-RT or LOS-RT seeds 0 … 20 (measured: 21 cm and 5 cm)."""
    held = held_out_tracks()
    assert len(held) == len(gen.DESCRIPTIONS) + 1 + NUM_TEST_SEEDS
    d = rms_distances(draws[2], np.stack(list(held.values())))
    paper = draws[1] < 3
    for rows, bound in ((~paper, MIN_RMS), (paper, MIN_RMS_PAPER)):
        nearest = dict(zip(held, d[rows].min(0).round(3), strict=True))
        assert d[rows].min() > bound, {k: v for k, v in nearest.items() if v <= bound}


def test_training_keys_never_meet_the_held_out_keys():
    """Training folds its own tag into the env's key: the keys its draws use differ from the
    test tracks' ``PRNGKey(seed)`` (and LOS-RT's split of it) and from the validation sets'."""
    tags = {tf._WIDE_TAG, tf._WIDE_VALIDATION_TAG, tr._TRAIN_TAG, tr._VALIDATION_TAG}
    assert len(tags) == 4 and min(tags) >= NUM_TEST_SEEDS
    keys = training_keys()
    used = {tuple(k) for k in np.asarray(jax.vmap(lambda k: jax.random.fold_in(k, tf._WIDE_TAG))(keys))}
    held = [jax.random.PRNGKey(s) for s in range(NUM_TEST_SEEDS)]
    held += [k for s in range(NUM_TEST_SEEDS) for k in jax.random.split(jax.random.PRNGKey(s))]
    for tag in (tr._VALIDATION_TAG, tf._WIDE_VALIDATION_TAG):
        held += [jax.random.fold_in(jax.random.PRNGKey(tag), i) for i in range(64)]
    assert not used & {tuple(np.asarray(k)) for k in held}


@pytest.fixture(scope="module")
def validation():
    tracks = jax.jit(tf.wide_validation_tracks)()
    return tracks, np.stack([dense_pos(take(tracks, i)) for i in range(len(tracks.kind))])


def test_wide_validation_tracks_are_fixed_and_cover_every_family(validation):
    tracks, pos = validation
    names = tf.wide_validation_families()
    assert names == tuple(n for n in tf.FAMILIES for _ in range(tf.VALIDATION_PER_FAMILY))
    assert tracks.seg.shape[0] == len(names) and np.all(pos[:, 0] == 0.0)
    again = tf.wide_validation_tracks()
    assert np.array_equal(tracks.seg_steps, again.seg_steps) and np.array_equal(tracks.kind, again.kind)
    for i in range(len(names)):  # eager and jitted: positions equal to float32's last bits
        np.testing.assert_allclose(dense_pos(take(again, i)), pos[i], rtol=1e-5, atol=1e-5)
    kind = np.asarray(tracks.kind)
    assert np.all((kind == tr.SPIRAL) == np.array([n == "spiral" for n in names]))
    step = np.array([n == "step" for n in names])
    assert np.all(np.asarray(tracks.seg_v)[step] == 0.0)
    assert np.all(np.diff(pos[step], axis=1).any(-1).sum(-1) > 0)  # each steps at least once
    few = tf.wide_validation_families(tuple(float(n == "circle") for n in tf.FAMILIES), per_family=3)
    assert few == ("circle",) * 3


def test_wide_validation_tracks_are_distinct_from_training_draws(draws, validation):
    _, pos = validation
    d = rms_distances(pos, draws[2])
    assert d.min() > MIN_RMS
    own = rms_distances(pos, pos) + np.eye(len(pos))
    assert own.min() > MIN_RMS


def test_jit_and_vmap_agree_with_single_draws(draws):
    """Integers are equal; a tabulated curve's accelerations (differences of positions) can
    differ in float32's last bits, its positions by much less than a micrometre."""
    tracks, family, pos = draws[0], draws[1], draws[2]
    keys = training_keys()
    one = jax.jit(lambda k: tf.sample_wide_track(k, with_family=True))
    picks = [int(np.flatnonzero(family == i)[0]) for i in range(len(tf.FAMILIES))] + [NUM_DRAWS + 3]
    for i in picks:
        single, fam = one(keys[i])
        assert int(fam) == family[i] and int(single.kind) == int(tracks.kind[i])
        assert int(single.seg_steps) == int(tracks.seg_steps[i])
        np.testing.assert_allclose(dense_pos(single), pos[i, :COMPARE_STEPS], rtol=1e-5, atol=1e-5)


def test_table_size_matches_the_paper_mixture():
    """At 1 ms the wide tracks have the paper mixture's table: the env's state does not grow."""
    assert tf.wide_num_segments(NUM_POINTS, DT) == tr.train_num_segments(NUM_POINTS, DT)
    one = jax.eval_shape(tf.sample_wide_track, jax.random.PRNGKey(0))
    paper = jax.eval_shape(tr.sample_train_track, jax.random.PRNGKey(0))
    shapes = lambda t: jax.tree.map(lambda a: (a.shape, a.dtype), t)  # noqa: E731
    assert shapes(one) == shapes(paper)
    bigger = jax.eval_shape(lambda k: tf.sample_wide_track(k, num_segments=100), jax.random.PRNGKey(0))
    assert bigger.seg.shape == (100, 3, 3)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"weights": (1.0, 0.0)}, "weights"),
        ({"weights": (-0.1,) + (0.2,) * 8}, "weights"),
        ({"weights": (0.0,) * 9}, "weights"),
        ({"weights": (math.nan,) + (0.1,) * 8}, "weights"),
        ({"agile_acc_max": (6.0, 6.0)}, "agile_acc_max"),
        ({"agile_acc_max": (6.0, 0.0, 2.0)}, "agile_acc_max"),
        ({"agile_speed_max": (4.5, -1.0)}, "agile_speed_max"),
        ({"num_segments": 10}, "num_segments"),
    ],
)
def test_bad_arguments_are_refused_with_one_line(kwargs, field):
    with pytest.raises(ValueError, match=field) as e:
        tf.sample_wide_track(jax.random.PRNGKey(0), **kwargs)
    assert "\n" not in str(e.value)
    if field == "weights":
        with pytest.raises(ValueError, match=field):
            tf.check_weights("weights", kwargs["weights"])
