"""Users' own tracks (samples, functions, CSV files), the generalisation suite and the
evaluation CLI on them."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.cli.evaluate import main
from ttd3_jax.cli.train import parse
from ttd3_jax.control import generalization as gen
from ttd3_jax.control.closed_loop import Rollout
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EVAL_CRASH_M, make_config
from ttd3_jax.sim.env import TrackingEnv

DT = 1e-3


def circle(t):
    return np.stack([np.cos(2 * t), np.sin(2 * t), 0.1 * t], -1)


def test_a_function_track_has_its_derivatives_and_holds_its_last_point():
    c = ct.from_function(circle, 1.0, name="circle")
    assert c.pos.shape == (1001, 3) and math.isclose(c.duration_s, 1.0)
    t = np.arange(1001) * DT
    # second-order finite differences: O(dt^2) error (edges one-sided, also second order)
    vel = np.stack([-2 * np.sin(2 * t), 2 * np.cos(2 * t), 0.1 + 0 * t], -1)
    acc = np.stack([-4 * np.cos(2 * t), -4 * np.sin(2 * t), 0 * t], -1)
    np.testing.assert_allclose(c.vel, vel, atol=2e-5)
    np.testing.assert_allclose(c.acc[2:-2], acc[2:-2], atol=1e-4)  # differences of differences
    np.testing.assert_allclose(c.acc, acc, atol=1e-2)  # the one-sided edges are coarser
    track = c.track()
    k = jnp.arange(1001)
    np.testing.assert_allclose(tr.position(track, k, DT), c.pos, atol=1e-6)
    pos, v, a = tr.evaluate(track, jnp.asarray([1000, 1001, 1500, 5000]), DT)
    np.testing.assert_allclose(pos, np.repeat(c.pos[-1:], 4, 0), atol=1e-6)  # held after the end
    np.testing.assert_allclose(v[1:], 0.0)
    np.testing.assert_allclose(a[1:], 0.0)


def test_coarse_samples_are_resampled_onto_the_physics_grid():
    t = np.linspace(0.0, 2.0, 201) + 5.0  # 100 Hz, starting at 5 s (shifted to 0)
    c = ct.from_samples(t, circle(t - 5.0))
    assert c.pos.shape == (2001, 3)
    tg = np.arange(2001) * DT
    np.testing.assert_allclose(c.pos, circle(tg), atol=1e-4)  # linear interpolation of a smooth path
    np.testing.assert_allclose(c.vel[:, 2], 0.1, atol=1e-9)


def test_csv_round_trip_and_episode_length(tmp_path):
    c = ct.from_function(circle, 0.5, name="c")
    path = str(tmp_path / "c.csv")
    ct.to_csv(c, path)
    back = ct.from_csv(path)
    assert back.name == "c"
    for a, b in ((back.pos, c.pos), (back.vel, c.vel), (back.acc, c.acc)):
        np.testing.assert_allclose(a, b, atol=1e-7)
    assert back.episode_steps(1) == 500 and back.episode_steps(10) == 500 and back.episode_steps(30) == 480


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty file"),
        ("t,x,y\n0,0,0\n", r"lacks column\(s\) \['z'\]"),
        ("t,x,y,z,w\n0,0,0,0,0\n", r"unknown column\(s\) \['w'\]"),
        ("t,x,y,z\n0,0,0,0\n0.1,1,0,0\n", "at least 3 samples"),
        (
            "t,x,y,z\n0,0,0,0\n0.2,1,0,0\n0.1,1,0,0\n",
            r"line 4: t = 0.1 s does not increase \(previous row: 0.2",
        ),
        (
            "# a comment\nt,x,y,z\n0,0,0,0\n\n0.1,nan,0,0\n0.2,1,0,0\n",
            "line 5: x = nan; every value must be finite",
        ),
        ("t,x,y,z\n0,0,0,0\n0.1,a,0,0\n0.2,1,0,0\n", "line 3: every value must be a number"),
        ("t,x,y,z\n0,0,0,0\n0.1,1,0\n0.2,1,0,0\n", r"line 3: 3 values for the 4 columns"),
        ("t,x,y,z,vx\n0,0,0,0,0\n0.1,1,0,0,0\n0.2,1,0,0,0\n", r"give all of \['vx', 'vy', 'vz'\]"),
        ("t,x,y,z\n0,0,0,0\n0.0005,1,0,0\n0.001,1,0,0\n", "must last at least 2 physics steps"),
    ],
)
def test_bad_csv_files_are_refused_with_the_file_and_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as e:
        ct.from_csv(str(path))
    assert str(path) in str(e.value)


def test_stacking_tracks_of_any_size_changes_no_reference():
    cfg = tr.TrackConfig()
    tracks = [tr.spiral_rt(cfg), tr.los_test_track(0, cfg), ct.step((0.5, 0, 0), 1.0).track(),
              ct.from_function(circle, 4.0).track()]  # fmt: skip
    batch = ct.stack(tracks, DT)
    k = jnp.arange(0, 6000, 7)
    for i, t in enumerate(tracks):
        one = jnp.stack(tr.evaluate(t, k, DT))
        both = jnp.stack(tr.evaluate(jax_index(batch, i), k, DT))
        np.testing.assert_allclose(both, one, rtol=1e-6, atol=1e-5)


def jax_index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def test_the_suite_tracks_start_at_rest_from_the_origin_and_cover_the_preview():
    tracks = gen.suite_tracks("generalization")
    assert list(tracks) == list(gen.DESCRIPTIONS)
    for name, t in tracks.items():
        p0 = tr.position(t, 0, DT)
        np.testing.assert_allclose(p0, 0.0, atol=1e-9, err_msg=name)
        if t.kind == tr.PIECEWISE:  # the table runs past the episode and the NMPC's 1 s preview
            assert t.num_segments * int(t.seg_steps) > 3000 + 1000, name
    with pytest.raises(ValueError, match="unknown suite 'x'"):
        gen.suite_tracks("x")


def test_step_overshoot_and_steady_error():
    n = 300
    t = 0.01 * np.arange(1, n + 1)
    x = np.minimum(1.2 * t, 0.5 + 0.1 * np.exp(-(t - 0.5)))  # passes the 0.5 m target by 0.1 m
    pos = np.stack([x, 0 * x, 0 * x], -1)
    ref = np.tile([0.5, 0.0, 0.0], (n, 1))
    r = Rollout(pos, ref, np.zeros((n, 4)), np.zeros(n), np.zeros(n), pos, np.zeros((n, 4)))
    p = gen.precision(r, 0.01, "step")
    assert p["overshoot"] == pytest.approx(100 * 0.1 * np.exp(-(0.5 - 0.5)) / 0.5, rel=0.05)
    e = np.abs(x - 0.5)
    assert p["steady_error"] == pytest.approx(np.mean(e[t > 1.0]))
    assert math.isnan(gen.precision(r, 0.01, "circle")["overshoot"])


def test_every_controller_is_judged_by_one_crash_threshold():
    for cfg in (make_config("paper"), make_config("practical", e_max=1.5)):
        assert cfg.for_eval("los_rt").reward.e_max == EVAL_CRASH_M


def test_cli_evaluates_a_csv_track_at_its_own_length(tmp_path, capsys):
    path = str(tmp_path / "hop.csv")
    ct.to_csv(ct.step((0.0, 0.0, 0.2), 1.5, name="hop"), path)
    out = tmp_path / "e.json"
    assert main(["--controller", "geometric", "--track", path, "--no-timing", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "track hop: 1.5 s (1500 physics steps evaluated)" in text and "holds the last point" in text
    saved = json.loads(out.read_text())
    res = saved["results"]["geometric"]["hop"]
    assert saved["crash_threshold_m"] == EVAL_CRASH_M and saved["control_hz"] == 1000
    assert (
        res["crashed"] == 0
        and 0 < res["steady_error"] < 0.2
        and res["max_error"] == pytest.approx(0.2, rel=1e-3)
    )
    assert (tmp_path / "hop_trace.csv").is_file() and (tmp_path / "hop_error.png").is_file()
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n0,1\n")
    with pytest.raises(SystemExit) as e:
        main(["--controller", "geometric", "--track", str(bad)])
    assert e.value.code == 2
    assert "--track:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--controller", "geometric", "--track", path, "--suite", "generalization"])


def test_users_training_tracks_join_the_mixture_and_nothing_else_changes(tmp_path):
    """With ``train_tracks`` a share of the resets flies the user's track; without, the
    training env draws exactly the tracks it drew before."""
    path = str(tmp_path / "hop.csv")
    ct.to_csv(ct.step((0.0, 0.0, 0.3), 1.0, name="hop"), path)
    keys = jax.random.split(jax.random.PRNGKey(4), 64)
    plain = TrackingEnv(make_config("practical"))
    mixed = TrackingEnv(make_config("practical", train_tracks=(path,), train_tracks_weight=0.5))
    assert mixed.num_segments == 1002 > plain.num_segments
    draw = lambda env: jax.vmap(env.sample_track)(keys)  # noqa: E731
    a, b = draw(plain), draw(mixed)
    k = jnp.arange(0, 3000, 25)
    pa = jax.vmap(lambda t: tr.position(t, k, DT))(a)
    pb = jax.vmap(lambda t: tr.position(t, k, DT))(b)
    hop = np.where(k[:, None] >= 1, [0.0, 0.0, 0.3], 0.0)
    is_hop = np.all(np.abs(np.asarray(pb) - hop) < 1e-6, axis=(1, 2))
    assert 16 <= is_hop.sum() <= 48  # about half of 64
    np.testing.assert_allclose(pb[~is_hop], pa[~is_hop], atol=1e-5)  # the others: the mixture's own draws
    nope = make_config("practical", train_tracks=("/nope.csv",))  # a run whose CSV moved still loads
    with pytest.raises(ValueError, match="train_tracks: '/nope.csv' is not a file"):
        TrackingEnv(nope)  # the training env reads it
    assert TrackingEnv(nope, track_rows=1002).num_segments == 1002  # a reader's does not
    with pytest.raises(ValueError, match=r"train_tracks_weight must be a finite number in \(0, 1\], got 0.0"):
        make_config("practical", train_tracks=(path,), train_tracks_weight=0.0)


def test_train_cli_takes_a_directory_of_tracks(tmp_path):
    for name in ("a", "b"):
        ct.to_csv(ct.step((0.1, 0.0, 0.0), 0.5, name=name), str(tmp_path / f"{name}.csv"))
    _, spec = parse(["--train-tracks", str(tmp_path), "--out", str(tmp_path / "runs")])
    assert spec.task.tracks.train_tracks == (str(tmp_path / "a.csv"), str(tmp_path / "b.csv"))
    (tmp_path / "c.csv").write_text("t,x\n")
    with pytest.raises(ValueError, match="c.csv"):
        parse(["--train-tracks", str(tmp_path)])
    with pytest.raises(ValueError, match="remove --train-tracks"):
        parse(["--resume", str(tmp_path), "--train-tracks", str(tmp_path)])
