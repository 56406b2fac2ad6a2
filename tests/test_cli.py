"""The training CLI as a user drives it: bad input refused early with a message naming it,
a SIGKILL at any point resumed, and the compilation cache."""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import time

import jax
import pytest
from tiny import TINY_CLI

from ttd3_jax.cli.train import main
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import rundir, status
from ttd3_jax.run import spec as sp
from ttd3_jax.run.cache import default_compile_cache, use_compile_cache


def test_help_lists_the_options_a_user_sets(capsys):
    """``train --help`` shows at most 70 options (a ``--no-X`` switch is its option's other
    half); the readings of the paper and internal constants are run-spec fields, not flags."""
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    options = {re.sub(r"(^--|\.)no-", r"\1", f) for f in re.findall(r"--[a-z][a-z0-9.-]*[a-z0-9]", out)}
    assert "--hp.lr-actor" in options and "--task.vehicle.quad.mass" in options
    assert "--task.tracks.generator.los-heading" not in options and "--noise.delta-reduce" not in options
    assert len(options) <= 70, sorted(options)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--num-envs", "0"], "num_envs must be an integer in"),
        (
            ["--total-transitions", "1000000000000000"],
            r"total_transitions must be an integer in \[1, 2,000,000,000\]",
        ),
        (["--hp.lam", "inf"], "hp.lam must be a finite number"),
        (["--hp.beta", "nan"], "hp.beta must be a finite number"),
        (["--task.reward.e-max", "-1"], "EnvConfig.reward.e_max must be a finite number > 0"),
        (["--task.reward.err-cost", "cubic"], "err_cost must be one of"),
        (["--task.tracks.track", "spiral_rt"], "Unrecognized options: --task.tracks.track"),  # internal
        (["--task.observation.lookahead-k", "100000"], r"lookahead_k must be <= episode_steps \(3000"),
        (
            ["--task.tracks.train-tracks-weight", "0.5"],
            "train_tracks_weight must be 0.25 without train_tracks",
        ),
        (["--task.observation.preview-s", *map(str, range(1, 2001))], r"preview_s must be .*2,000 values\)"),
        (
            ["--preset", "mujoco", "--task.reward.e-max", "1.5"],
            r"--task.\* sets the quadrotor env; env 'hopper' has none",
        ),
        (
            ["--preset", "quick"],
            "--preset must be one of " + re.escape(str(sp.PRESETS)) + ", got 'quick'",
        ),
        (["--resume", "/nonexistent/run"], "not a ttd3_jax run directory"),
        (
            ["--resume", "/nonexistent/run", "--preset", "fast"],
            "--resume continues the saved run spec; remove --preset",
        ),
        (["--resume", "/nonexistent/run", "--epochs", "3"], "remove --epochs 3"),
        (["--resume", "/nonexistent/run", "--out", "x"], "remove --out"),
    ],
)
def test_bad_input_is_refused_before_anything_compiles(argv, message, capsys):
    try:
        code = main(argv)
    except SystemExit as e:  # tyro reports its own parse and validation errors, status 2
        code = e.code
    assert code == 2
    err = capsys.readouterr().err
    flat = " ".join(re.sub(r"[│|]", " ", err).split())  # tyro wraps its messages in a box
    assert re.search(message, flat), err
    assert "Traceback" not in err


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main([*TINY_CLI, "--out", str(blocker)]) == 2
    assert "--out" in capsys.readouterr().err


def test_task_e_max_big_is_refused_with_the_field_and_its_type(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--task.reward.e-max", "big"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--task.reward.e-max" in err and "FLOAT" in err.upper()


def test_sigkill_then_resume_finishes_the_run(tmp_path):
    """A run killed at an arbitrary point resumes from its last complete checkpoint."""
    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "ttd3_jax.train", *TINY_CLI, "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.time() + 300
    run_dir = None
    while time.time() < deadline and proc.poll() is None:
        dirs = list(out.glob("*/checkpoints/1")) if out.exists() else []
        if dirs:
            run_dir = dirs[0].parent.parent
            break
        time.sleep(0.05)
    assert run_dir is not None, (
        proc.stdout.read().decode() if proc.poll() is not None else "no checkpoint in time"
    )
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    mngr = ckpt.manager(str(run_dir))
    last = ckpt.latest_epoch(mngr)
    assert last is not None and last >= 1
    mngr.close()
    res = subprocess.run([sys.executable, "-m", "ttd3_jax.train", "--resume", str(run_dir)],
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"resumed {run_dir} at epoch {last}/4" in res.stdout
    # the CLI uses $JAX_COMPILATION_CACHE_DIR (tests/conftest.py sets it) as its cache
    assert f"XLA compilation cache: {os.environ['JAX_COMPILATION_CACHE_DIR']}" in res.stdout
    assert [int(r["epoch"]) for r in rundir.read_metrics(str(run_dir))] == [1, 2, 3, 4]
    assert os.path.isfile(run_dir / "eval.json")


def _train_until_checkpoint(out, *extra):
    """A tiny CLI run of 60 short epochs, once its first epoch is checkpointed: ``(proc, run_dir)``."""
    cmd = [sys.executable, "-m", "ttd3_jax.train", *TINY_CLI, "--epochs", "60", "--total-transitions",
           str(16 * (8 + 2 * 60)), *extra, "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        dirs = list(out.glob("*/checkpoints/1")) if out.exists() else []
        if dirs:
            return proc, dirs[0].parent.parent
        time.sleep(0.05)
    raise AssertionError(proc.communicate()[1] if proc.poll() is not None else "no checkpoint in time")


def test_ctrl_c_stops_the_run_after_its_epoch_and_resume_out_continues_it(tmp_path):
    """Ctrl-C is a normal way to stop: one line saying where, the epoch it finished
    checkpointed, no traceback, state ``stopped``; ``--resume OUT`` then finishes the run."""
    out = tmp_path / "runs"
    proc, run_dir = _train_until_checkpoint(out)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stdout + stderr
    assert "Traceback" not in stdout + stderr and "KeyboardInterrupt" not in stdout + stderr
    state = status.state(str(run_dir))
    assert state["state"] == "stopped" and state["reason"] == "SIGINT", state
    epoch = state["epoch"]
    assert 1 <= epoch < 60
    line = f"stopped by SIGINT after epoch {epoch}/60 (checkpointed); continue with python -m ttd3_jax.train"
    assert f"{line} --resume {run_dir}" in stdout
    mngr = ckpt.manager(str(run_dir))
    assert ckpt.latest_epoch(mngr) == epoch  # the epoch it finished is on disk
    mngr.close()
    res = subprocess.run([sys.executable, "-m", "ttd3_jax.train", "--resume", str(out)],
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"resumed {run_dir} at epoch {epoch}/60" in res.stdout
    assert [int(r["epoch"]) for r in rundir.read_metrics(str(run_dir))] == list(range(1, 61))
    assert status.state(str(run_dir))["state"] == "finished"


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_a_second_sigterm_stops_at_once_keeping_the_newest_checkpoint(tmp_path):
    out = tmp_path / "runs"
    proc, run_dir = _train_until_checkpoint(out)
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "Traceback" not in stdout + stderr, stdout + stderr
    state = status.state(str(run_dir))
    assert state["state"] == "stopped" and state["reason"] == "SIGTERM", state
    lines = stderr.strip().splitlines()
    assert lines[-1].startswith("stopped by SIGTERM") or "stopped by SIGTERM after epoch" in stdout, stderr


def test_compile_cache_default_and_bad_directory(tmp_path, monkeypatch):
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "env"))
    assert default_compile_cache() == str(tmp_path / "env")
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_compile_cache() == str(tmp_path / "xdg" / "ttd3_jax" / "xla")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(ValueError, match="a_file.*cannot be created.*--compile-cache none"):
        use_compile_cache(str(blocker / "cache"))
    # an unwritable default only warns and turns the cache off (then back on for the suite)
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    try:
        assert use_compile_cache() is None
        assert not jax.config.jax_enable_compilation_cache
    finally:
        jax.config.update("jax_enable_compilation_cache", True)


@pytest.mark.slow
def test_cli_compile_cache_is_written_then_reused_with_identical_results(tmp_path):
    """A second launch loads the first one's programs from --compile-cache DIR; the
    results (all but the wall-clock columns) are identical."""
    cache = tmp_path / "xla"
    out = []
    for i in range(2):
        cmd = [
            sys.executable,
            "-m",
            "ttd3_jax.train",
            *TINY_CLI,
            "--epochs",
            "2",
            "--total-transitions",
            "512",
        ]
        cmd += ["--out", str(tmp_path / f"runs{i}"), "--compile-cache", str(cache)]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stdout + res.stderr
        assert f"XLA compilation cache: {cache}" in res.stdout
        if i == 0:
            assert len(list(cache.iterdir())) > 0  # programs written
        (metrics,) = (tmp_path / f"runs{i}").glob("*/metrics.csv")
        with open(metrics) as fh:
            out.append(
                [
                    {k: v for k, v in r.items() if k not in ("wall_s", "steps_per_s")}
                    for r in csv.DictReader(fh)
                ]
            )
    assert out[0] == out[1] and len(out[0]) == 2
