"""The runner and the run directory: exact resume, checkpoints that do not load, divergence,
the selected policy, and the compiled programs the epochs share."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import time

import jax
import numpy as np
import pytest
from tiny import tiny

from ttd3_jax.cli.evaluate import main as evaluate_main
from ttd3_jax.control.closed_loop import evaluate_on_tracks
from ttd3_jax.control.closed_loop import test_tracks as make_test_tracks
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import provenance, rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import LiveBar, TrainingDiverged, check_finite, run
from ttd3_jax.run.sharding import runner_fns
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.trainer import seed_keys

COMPARED = ("critic_loss", "actor_loss", "sigma", "env_steps", "spiral_tracking_error", "los_tracking_error")


def assert_same_rows(ra, rb):
    assert len(ra) == len(rb)
    for x, y in zip(ra, rb, strict=True):
        for k in COMPARED:
            assert x[k] == pytest.approx(y[k], rel=1e-6, abs=1e-7), k


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_resume_equals_uninterrupted(tmp_path):
    """The model-based actor (the default preset's path); the paper's actor update is resumed
    exactly in the checkpoint-fallback test below."""
    s = tiny(epochs=3, model_horizon=4)
    full = run(s, out=str(tmp_path / "a"), verbose=False)
    part = run(s, out=str(tmp_path / "b"), verbose=False, stop_after=1)
    assert part["stopped_at"] == 1
    resumed = run(resume=part["run_dir"], verbose=False)
    assert_same_rows(rundir.read_metrics(full["run_dir"]), rundir.read_metrics(resumed["run_dir"]))
    assert full["final_eval"] == resumed["final_eval"]
    for name in ("config.json", "metrics.csv", "eval.json", "learning_curve.png"):
        assert os.path.isfile(os.path.join(resumed["run_dir"], name))
    assert rundir.load_spec(resumed["run_dir"]) == s  # config.json holds the whole spec
    ev = json.load(open(os.path.join(full["run_dir"], "eval.json")))
    assert set(ev["final_eval"][0]) >= {"spiral_tracking_error", "los_tracking_error", "spiral_energy"}


def _break_newest(run_dir: str) -> int:
    """Damage the newest checkpoint as a crash or a careless rm would: its array data gone."""
    newest = ckpt.latest_epoch(ckpt.manager(run_dir))
    shutil.rmtree(os.path.join(run_dir, "checkpoints", str(newest), "default"))
    return newest


def test_a_checkpoint_that_does_not_load_is_skipped_by_resume_and_evaluate(tmp_path, capsys, shown_messages):
    """Resume and evaluate fall back to the newest checkpoint that loads and say which one
    they skipped; the resumed run then equals an uninterrupted one."""
    s = tiny(epochs=3)
    full = run(s, out=str(tmp_path / "a"), verbose=False)
    part = run(s, out=str(tmp_path / "b"), verbose=False, stop_after=2)["run_dir"]
    assert _break_newest(part) == 2
    loaded = rundir.load_train_state(part)
    assert loaded.epoch == 1 and [e for e, _ in loaded.skipped] == [2]
    # the training --out directory names its (only) run
    assert evaluate_main([str(tmp_path / "b"), "--no-timing", "--json", str(tmp_path / "e.json")]) == 0
    err = capsys.readouterr().err
    assert "skipped checkpoint 2, which does not load" in err and "Traceback" not in err
    resumed = run(resume=part, verbose=True)
    out = capsys.readouterr().out
    assert "skipped checkpoint 2, which does not load" in out and "resumed" in out and "at epoch 1/3" in out
    assert_same_rows(rundir.read_metrics(full["run_dir"]), rundir.read_metrics(resumed["run_dir"]))
    # each launch recorded what ran it: the code, JAX, the machine
    launches = provenance.launches(part)
    assert [x["launch"] for x in launches] == ["start", "resume"]
    assert launches[0]["code"] == provenance.code_version() and launches[0]["jax"] == jax.__version__


def test_resume_refuses_a_run_without_checkpoints_and_leaves_its_metrics(tmp_path):
    part = run(tiny(), out=str(tmp_path), verbose=False, stop_after=1)["run_dir"]
    metrics = open(os.path.join(part, "metrics.csv")).read()
    shutil.rmtree(os.path.join(part, "checkpoints"))
    os.makedirs(os.path.join(part, "checkpoints"))
    with pytest.raises(FileNotFoundError, match="holds no checkpoint, so there is nothing to resume"):
        run(resume=part, verbose=False)
    assert open(os.path.join(part, "metrics.csv")).read() == metrics


def test_damaged_config_json_is_named(tmp_path):
    part = run(tiny(), out=str(tmp_path), verbose=False, stop_after=0)["run_dir"]
    path = os.path.join(part, "config.json")
    text = open(path).read()
    open(path, "w").write(text[: len(text) // 2])
    with pytest.raises(ValueError, match=r"config.json is not valid JSON .*damaged"):
        rundir.load_spec(part)
    open(path, "w").write(text.replace('"e_max": 1.0', '"e_max": "big"'))
    with pytest.raises(
        ValueError, match=r'config.json: run spec: wrong value type for field "task.reward.e_max"'
    ):
        rundir.load_spec(part)
    with pytest.raises(FileNotFoundError, match="not a ttd3_jax run directory"):
        rundir.load_spec(str(tmp_path))


def test_out_must_be_a_writable_directory(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(ValueError, match=r"--out .*a_file.* is a file, not a directory"):
        run(tiny(), out=str(blocker / "runs"), verbose=False)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as a user who can write anywhere (root)")
        with pytest.raises(ValueError, match="is not writable"):
            run(tiny(), out=str(locked / "runs"), verbose=False)
    finally:
        locked.chmod(0o700)


def test_restored_state_lowers_to_the_fresh_runs_epoch_program(tmp_path):
    """A resumed run finds its epoch program in the compilation cache: the restored state
    (``place`` of a checkpoint) lowers to the same program text as a fresh one."""
    s = tiny()
    keys = seed_keys(s.seed, s.num_seeds)
    init_fn, epoch_fn, _, place = runner_fns(sp.trainer_for(s), keys, s.hp)
    fresh = init_fn(keys, s.hp)
    mngr = ckpt.manager(str(tmp_path))
    ckpt.save(mngr, 0, fresh)
    restored = ckpt.restore(mngr, 0, jax.eval_shape(init_fn, keys, s.hp))
    assert epoch_fn.lower(place(restored), s.hp).as_text() == epoch_fn.lower(fresh, s.hp).as_text()
    for x, y in zip(jax.tree.leaves(fresh), jax.tree.leaves(place(restored)), strict=True):
        np.testing.assert_array_equal(x, y)


def test_a_background_save_keeps_the_state_it_was_given_when_that_state_is_donated(tmp_path):
    """``save(..., wait=False)`` on an asynchronous manager returns before the checkpoint is
    on disk; the epoch program then donates (frees) the saved state.  The checkpoint still
    holds the state as it was, and the next epoch's state is unaffected."""
    s = tiny()
    keys = seed_keys(s.seed, s.num_seeds)
    init_fn, epoch_fn, _, _ = runner_fns(sp.trainer_for(s), keys, s.hp)
    ts = init_fn(keys, s.hp)
    before = [np.array(x) for x in jax.tree.leaves(ts)]
    mngr = ckpt.manager(str(tmp_path), asynchronous=True)
    ckpt.save(mngr, 0, ts, wait=False)
    ts, _ = epoch_fn(ts, s.hp)  # donates the saved state's buffers
    assert ckpt.latest_epoch(mngr) == 0  # waits for the background write
    ckpt.finish(mngr)
    restored = ckpt.restore(ckpt.manager(str(tmp_path)), 0, jax.eval_shape(init_fn, keys, s.hp))
    for x, y in zip(before, jax.tree.leaves(restored), strict=True):
        np.testing.assert_array_equal(x, y)
    assert any(not np.array_equal(x, np.asarray(y)) for x, y in zip(before, jax.tree.leaves(ts), strict=True))


def test_epochs_reuse_one_program_with_no_host_transfers_and_donated_state():
    """The runner's epoch function compiles once for all epochs, runs with implicit
    host<->device transfers disallowed, and donates the train state."""
    s = tiny(epochs=3)
    keys = seed_keys(s.seed, s.num_seeds)
    init_fn, epoch_fn, _, _ = runner_fns(sp.trainer_for(s), keys, s.hp)
    hp = jax.device_put(s.hp)
    ts = init_fn(keys, hp)
    for _ in range(s.train.epochs):
        old = ts
        with jax.transfer_guard("disallow"):
            ts, m = epoch_fn(ts, hp)
        assert old.buffer.data.obs.is_deleted()  # donated
    jax.block_until_ready(ts)
    assert epoch_fn._cache_size() == 1
    assert np.all(np.isfinite(np.asarray(m["critic_loss"])))


def test_divergence_message_names_what_went_non_finite(tmp_path):
    s = tiny()
    keys = seed_keys(s.seed, s.num_seeds)
    ts = jax.jit(jax.vmap(sp.trainer_for(s).init, in_axes=(0, None)))(keys, s.hp)
    mngr = ckpt.manager(str(tmp_path))
    ckpt.save(mngr, 0, ts)
    ok = {"critic_loss": np.array([1.0]), "q_mean": np.array([1.0]), "actor_loss": np.array([1.0]),
          "env_steps": np.array([2048.0])}  # fmt: skip
    check_finite(ok, ts, 1, str(tmp_path), mngr)  # all finite: no error
    with pytest.raises(
        TrainingDiverged, match=r"non-finite critic_loss in epoch 1 .*epoch 0.*--hp.lr-critic"
    ):
        check_finite({**ok, "critic_loss": np.array([np.nan])}, ts, 1, str(tmp_path), mngr)
    bad_actor = ts.replace(actor=jax.tree.map(lambda x: x * np.nan, ts.actor))
    with pytest.raises(TrainingDiverged, match=r"non-finite actor_loss, actor parameters .*--hp.lr-actor"):
        check_finite({**ok, "actor_loss": np.array([np.inf])}, bad_actor, 1, str(tmp_path), mngr)


def test_diverging_run_keeps_last_good_checkpoint(tmp_path):
    s = tiny(epochs=3)  # learning rates no spec accepts (hp.lr_* <= 1), set past the validation
    object.__setattr__(s, "hp", Hyper(lr_critic=1e30, lr_actor=1e30))
    with pytest.raises(TrainingDiverged, match="non-finite"):
        run(s, out=str(tmp_path), verbose=False)
    (run_dir,) = [os.path.join(tmp_path, d) for d in os.listdir(tmp_path)]
    assert ckpt.latest_epoch(ckpt.manager(run_dir)) is not None
    like = jax.eval_shape(sp.trainer_for(s).init, seed_keys(s.seed, 1)[0], s.hp)
    assert ckpt.restore_newest(run_dir, jax.tree.map(lambda x: jax.ShapeDtypeStruct((1, *x.shape), x.dtype),
                                                     like))[0] == 0  # fmt: skip


def test_csv_log_drops_rows_past_checkpoint(tmp_path):
    path = str(tmp_path / "m.csv")
    log = rundir.CsvLog(path)
    log.write([{"epoch": 1, "seed": 0, "x": 1.0}])
    log.write([{"epoch": 2, "seed": 0, "x": 2.0}])
    rundir.CsvLog(path, keep_through_epoch=1)
    with open(path) as fh:
        assert fh.read().count("\n") == 2  # header + epoch 1


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_policy_selected_on_validation_tracks_is_saved_and_reloads(tmp_path):
    """Each seed keeps the policy of its epoch with the lowest validation error (spec T8,
    never the test tracks); eval.json names that epoch with its test figures, and
    ``rundir.load_run(best=True)`` reloads it: evaluated again it gives the same numbers."""
    summary = run(tiny(num_seeds=2, epochs=3), out=str(tmp_path), verbose=False)
    rows = rundir.read_metrics(summary["run_dir"])
    record = ckpt.best_record(summary["run_dir"])
    assert sorted(record) == [0, 1]
    for sel in summary["selected"]:
        mine = [r for r in rows if int(r["seed"]) == sel["seed"]]
        best = min(mine, key=lambda r: r["val_tracking_error"])
        assert sel["epoch"] == int(best["epoch"]) == record[sel["seed"]]["epoch"]
        assert sel["spiral_tracking_error"] == pytest.approx(best["spiral_tracking_error"])
    assert len(summary["selected_beats_paper"]) == 2
    loaded = rundir.load_run(summary["run_dir"], best=True)
    assert loaded.epoch == {s["seed"]: s["epoch"] for s in summary["selected"]}
    env = TrackingEnv(loaded.env_config.for_eval("los_rt"))
    for (seed, theta), sel in zip(loaded.thetas, summary["selected"], strict=True):
        assert seed == sel["seed"]
        m = jax.jit(lambda th: evaluate_on_tracks(env, loaded.build(th), make_test_tracks(env)))(theta)
        np.testing.assert_allclose(float(m["tracking_error"][0]), sel["spiral_tracking_error"], rtol=1e-4)
        np.testing.assert_allclose(float(m["tracking_error"][1]), sel["los_tracking_error"], rtol=1e-4)


def test_fast_preset_model_actor_learns_on_a_small_budget(tmp_path, caplog):
    """The default ``fast`` preset's first two epochs (100 rollouts of 16 envs, the first 4
    the random warm-up, 80k transitions, one seed; about 12 s on 2 CPU cores).  The untrained
    policy scores about 4e4 on both tracks; at this point of training
    ``experiments/fast_sweep.py`` measured Spiral-RT 14-29 and LOS-RT 227-241 (seeds 0-2,
    vmapped), a seed-0 run 9.6 and 231, and the bars are 2.3-3.4x above the worst.  Around
    the three programs the launch compiles nothing but the seeds' keys: an eager jax op on
    the host path (a key, a slice of the state, a zero) is a compile of its own, 10-100 ms
    each (issue 51)."""
    with jax.log_compiles(), caplog.at_level(logging.WARNING, logger="jax"):
        part = run(sp.preset("fast"), out=str(tmp_path), verbose=False, stop_after=2)
    row = rundir.read_metrics(part["run_dir"])[-1]
    sp_, los = float(row["spiral_tracking_error"]), float(row["los_tracking_error"])
    print(f"Spiral-RT {sp_:.1f}, LOS-RT {los:.1f}")
    assert int(row["epoch"]) == 2 and sp_ < 100 and los < 550, (sp_, los)
    compiled = set(re.findall(r"Compiling jit\((\w+)\)", caplog.text))
    # the three programs (stored: traced as flat, run as call; as plain jit where another test
    # turned the program store off: per_seed's one) and seed_keys' program
    assert compiled and compiled <= {"flat", "call", "one", "_fold_seeds"}, compiled


@pytest.mark.slow
def test_fast_dpg_preset_learns_on_a_small_budget(tmp_path):
    """The paper's actor update (``fast_dpg``): a real improvement over the untrained policy
    on the fixed test tracks (one seed, about a minute on 2 CPU cores).  Untrained Σ||e||
    is in the 1e4 range; the bar is a 10x reduction on both tracks (measured: 86x and 34x)."""
    s = sp.preset("fast_dpg", total_transitions=160_000, buffer_size=160_000, epochs=4)
    t = sp.trainer_for(s)
    before = jax.device_get(jax.jit(t.evaluate)(jax.jit(t.init)(seed_keys(0, 1)[0], s.hp)))
    after = run(s, out=str(tmp_path), verbose=False)["final_eval"][0]
    for track in ("spiral", "los"):
        b, a = float(before[f"{track}_tracking_error"]), after[f"{track}_tracking_error"]
        print(f"{track}: untrained {b:.0f}, trained {a:.0f}")
        assert a < b / 10, (track, b, a)


@pytest.mark.slow
def test_brax_mjx_inverted_double_pendulum_smoke(tmp_path):
    """The same trainer drives a Brax/MJX task: a few hundred steps (slow: MJX compiles for minutes)."""
    brax = sp.BraxSettings(episode_length=50, eval_episodes=2)
    s = tiny(env="inverted_double_pendulum", num_envs=4, total_transitions=4 * 100, warmup_transitions=4 * 20,
             buffer_size=4 * 100, batch_size=32, brax=brax)  # fmt: skip
    summary = run(s, out=str(tmp_path), verbose=False)
    ret = summary["final_eval"][0]["eval_return"]
    assert np.isfinite(ret) and ret > 0  # IDP pays a positive alive bonus each step
    rows = rundir.read_metrics(summary["run_dir"])
    assert len(rows) == 2 and rows[-1]["env_steps"] == 4 * (20 + 2 * 40)


def test_find_run_takes_a_run_or_the_newest_run_under_an_out_directory(tmp_path):
    for name, mtime in (("old", 1_000), ("new", 2_000)):
        os.makedirs(tmp_path / name)
        (tmp_path / name / "config.json").write_text("{}")
        os.utime(tmp_path / name / "config.json", (mtime, mtime))
    assert rundir.find_run(str(tmp_path / "old")) == (str(tmp_path / "old"), None)
    path, note = rundir.find_run(str(tmp_path))
    assert path == str(tmp_path / "new") and "holds 2 runs; using the newest, new" in note
    os.makedirs(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="or its subdirectories: not a ttd3_jax run directory"):
        rundir.find_run(str(tmp_path / "empty"))


def test_the_live_bar_counts_seconds_then_estimates_from_the_last_epoch(capsys):
    bar = LiveBar(epochs=10, interval_s=0.01)
    bar.start(1)
    time.sleep(0.1)
    bar.stop()
    first = capsys.readouterr().out
    assert "epoch 1/10  running" in first and first.endswith("\r")  # drawn, then cleared
    assert bar.last_s == pytest.approx(0.1, abs=0.09)
    bar.epoch = 2
    assert bar.line(bar.last_s / 2).startswith("  epoch 2/10 [##########..........] ~ 50%")
    assert "~ 99%" in bar.line(10 * bar.last_s)  # a slow epoch never shows done
    bar.stop()  # stopping a bar that is not running does nothing
    assert capsys.readouterr().out == ""
