"""The wide training mixture wired into the env (``EnvConfig.tracks.wide_mix``, issue 37):
training draws, the validation bank and policy selection, the memory estimate, users' tracks
on top, config.json, the exclusion of the held-out tracks through the env's own keys, and a
tiny training run.  Everything runs on CPU.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_track_families import MIN_RMS, MIN_RMS_PAPER, NUM_TEST_SEEDS, held_out_tracks, rms_distances
from tiny import tiny

from ttd3_jax.control import closed_loop as cl
from ttd3_jax.run import memory, rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import track_families as tf
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv, num_validation_tracks, validation_tracks
from ttd3_jax.td3.trainer import seed_keys

DT = 1e-3
WIDE = make_config("practical", wide_mix=tf.WIDE_MIX)
COMPARE_STEPS = 3001  # as test_track_families: the first 3 s


def trees_equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def wide_draws(cfg, keys, n):
    """``sample_wide_track`` as the env of ``cfg`` calls it, with the family of each draw."""
    t = cfg.tracks
    draw = lambda k: tf.sample_wide_track(k, t.wide_mix, cfg.dt, cfg.horizon_steps, n, with_family=True)  # noqa: E731
    return jax.jit(jax.vmap(draw))(keys)


def test_the_default_env_draws_the_paper_mixture_and_wide_mix_the_wide_one():
    keys = jax.random.split(jax.random.PRNGKey(5), 64)
    plain = TrackingEnv(make_config("practical"))
    c = plain.config
    draw = lambda k: tr.sample_train_track(k, c.tracks.generator, c.dt, c.horizon_steps)  # noqa: E731
    paper = jax.jit(jax.vmap(draw))(keys)
    assert trees_equal(jax.jit(jax.vmap(plain.sample_track))(keys), paper)  # bit-identical to before
    env = TrackingEnv(WIDE)
    assert env.num_segments == tf.wide_num_segments(WIDE.horizon_steps, DT)
    want, family = wide_draws(WIDE, keys, env.num_segments)
    assert trees_equal(jax.jit(jax.vmap(env.sample_track))(keys), want)
    assert len(set(np.asarray(family).tolist())) >= 5  # 9 families at these weights: all seen here


def test_the_wide_mix_is_validated_with_one_line():
    for bad in ((0.5, 0.5), (0.0,) * 9, (-0.1,) + (0.2,) * 8, (float("nan"),) + (0.1,) * 8):
        with pytest.raises(ValueError, match=r"^EnvConfig\.tracks\.wide_mix must be 9 non-negative") as e:
            make_config("practical", wide_mix=bad)
        assert "\n" not in str(e.value)
    gen = dataclasses.replace(tr.TrackConfig(), train_mix=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="wide_mix replaces generator.train_mix"):
        make_config("practical", wide_mix=tf.WIDE_MIX, generator=gen)


def test_users_tracks_mix_into_the_wide_mixture(tmp_path):
    path = str(tmp_path / "hop.csv")
    ct.to_csv(ct.step((0.0, 0.0, 0.3), 1.0, name="hop"), path)
    keys = jax.random.split(jax.random.PRNGKey(4), 64)
    env = TrackingEnv(WIDE.replace(train_tracks=(path,), train_tracks_weight=0.5))
    assert env.num_segments == 1002 > tf.wide_num_segments(WIDE.horizon_steps, DT)
    got = jax.jit(jax.vmap(env.sample_track))(keys)
    want, _ = wide_draws(WIDE, keys, tf.wide_num_segments(WIDE.horizon_steps, DT))
    k = jnp.arange(0, 3000, 25)
    pos = lambda t: np.asarray(jax.vmap(lambda x: tr.position(x, k, DT))(t))  # noqa: E731
    pg, pw = pos(got), pos(want)
    is_hop = np.all(np.abs(pg - np.where(k[:, None] >= 1, [0.0, 0.0, 0.3], 0.0)) < 1e-6, axis=(1, 2))
    assert 16 <= is_hop.sum() <= 48  # about half of 64
    np.testing.assert_allclose(pg[~is_hop], pw[~is_hop], atol=1e-5)  # the others: the wide draws


def test_validation_uses_the_wide_bank_and_the_memory_estimate_counts_it():
    n = tf.wide_num_segments(WIDE.horizon_steps, DT)
    bank = jax.jit(lambda: validation_tracks(WIDE))()
    assert num_validation_tracks(WIDE) == len(tf.wide_validation_families(tf.WIDE_MIX)) == 18
    assert num_validation_tracks(make_config("practical")) == tr.NUM_VALIDATION_TRACKS
    assert trees_equal(
        bank, jax.jit(lambda: tf.wide_validation_tracks(tf.WIDE_MIX, DT, WIDE.horizon_steps, n))()
    )
    venv = TrackingEnv(WIDE.for_eval("validation"))
    picked = jax.jit(jax.vmap(venv.sample_track))(jax.random.split(jax.random.PRNGKey(0), 32))
    # each pick is one of the 18 (a curve's table can differ in float32's last bits between compilations)
    diff = np.abs(np.asarray(picked.seg)[:, None] - np.asarray(bank.seg)[None]).max(axis=(2, 3, 4))
    assert np.all(diff.min(1) < 1e-4) and len(set(diff.argmin(1).tolist())) > 10
    spec = sp.preset("fast")
    wide = dataclasses.replace(spec, task=spec.task.replace(wide_mix=tf.WIDE_MIX))
    assert memory.track_bytes(wide) - memory.track_bytes(spec) == 8 * n * memory.TRACK_ROW_BYTES


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_val_tracking_error_is_read_on_the_wide_validation_tracks():
    """The only figure a policy is selected on: the mean over the wide bank with wide_mix set,
    over the paper's 10 validation tracks without (short episodes, a hover controller)."""
    for cfg in (make_config("practical", episode_steps=200), WIDE.replace(episode_steps=200)):
        ctrl = cl.hover_controller(cfg)
        got = jax.jit(functools.partial(cl.test_and_validation_metrics, cfg, ctrl))()["val_tracking_error"]
        venv = TrackingEnv(cfg.for_eval("validation"))
        if cfg.tracks.wide_mix:
            bank = tf.wide_validation_tracks(cfg.tracks.wide_mix, DT, cfg.horizon_steps, venv.num_segments)
        else:
            bank = tr.validation_tracks(cfg.tracks.generator, DT, cfg.horizon_steps, venv.num_segments)
        want = jax.jit(lambda b: cl.evaluate_on_tracks(venv, ctrl, b)["tracking_error"])(bank)  # noqa: B023
        assert want.shape == (num_validation_tracks(cfg),)
        np.testing.assert_allclose(float(got), float(jnp.mean(want)), rtol=1e-5)


def env_track_keys(num: int) -> jax.Array:
    """The keys a training env hands ``sample_track``: each reset splits its key into the
    track's and the rest's; the trainer's first resets come from its seeds' keys (as in
    ``td3.trainer.init``), later ones from keys of the same kind (here: random)."""
    first = jax.vmap(lambda k: jax.random.split(jax.random.split(k, 4)[1], 64))(seed_keys(0, 8))
    resets = jnp.concatenate([first.reshape(-1, 2), jax.random.split(jax.random.PRNGKey(37), num)])
    held = jnp.stack([jax.random.PRNGKey(s) for s in range(NUM_TEST_SEEDS)])  # a reset key equal to these
    return jax.vmap(lambda k: jax.random.split(k)[0])(jnp.concatenate([resets, held]))


def test_no_suite_or_test_track_is_trained_on_through_the_env():
    """The env's own draws (fast preset, wide mix; table size and horizon as in training) stay
    MIN_RMS from every generalisation-suite track, Spiral-RT and LOS-RT seeds 0-20, and the keys
    they fold ``_WIDE_TAG`` into never give a held-out track's key."""
    spec = sp.preset("fast")
    cfg = spec.task.replace(wide_mix=tf.WIDE_MIX)
    env = TrackingEnv(cfg)
    keys = env_track_keys(1024)
    tracks = jax.jit(jax.vmap(env.sample_track))(keys)
    _, family = wide_draws(cfg, keys, env.num_segments)
    pos = np.asarray(jax.jit(jax.vmap(lambda t: tr.position(t, jnp.arange(COMPARE_STEPS), DT)))(tracks))
    held = held_out_tracks()
    d = rms_distances(pos.astype(np.float64), np.stack(list(held.values())))
    paper = np.asarray(family) < 3
    assert 0 < paper.sum() < len(paper)
    for rows, bound in ((~paper, MIN_RMS), (paper, MIN_RMS_PAPER)):
        assert d[rows].min() > bound, dict(zip(held, d[rows].min(0).round(3), strict=True))
    used = {tuple(k) for k in np.asarray(jax.vmap(lambda k: jax.random.fold_in(k, tf._WIDE_TAG))(keys))}
    seeds = [jax.random.PRNGKey(s) for s in range(NUM_TEST_SEEDS)]
    held_keys = seeds + [k for s in seeds for k in jax.random.split(s)]
    assert not used & {tuple(np.asarray(k)) for k in held_keys}


def test_the_wide_mixture_survives_config_json():
    d = json.loads(json.dumps(sp.to_dict(tiny())))
    assert d["task"]["tracks"]["wide_mix"] == []
    del d["task"]["tracks"]["wide_mix"]
    with pytest.raises(ValueError, match='"task.tracks.wide_mix" is missing'):
        sp.from_dict(d)
    wide = tiny(task=tiny().task.replace(wide_mix=tf.WIDE_MIX))
    assert sp.from_dict(json.loads(json.dumps(sp.to_dict(wide)))) == wide


@pytest.mark.slow  # tests/test_robust.py's tiny robust run covers it by default
def test_a_tiny_run_trains_on_the_wide_mixture(tmp_path):
    spec = tiny(epochs=1, task=tiny().task.replace(wide_mix=tf.WIDE_MIX))
    summary = run(spec, out=str(tmp_path), verbose=False)
    (row,) = rundir.read_metrics(summary["run_dir"])
    assert np.isfinite(float(row["val_tracking_error"]))
    assert rundir.load_spec(summary["run_dir"]).task.tracks.wide_mix == tf.WIDE_MIX
