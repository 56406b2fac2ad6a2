"""Issue 34's table of mishandled inputs, each refused with one line that names the flag or
field, exit status 2 and no traceback, before anything compiles (the CLIs run in-process)."""

from __future__ import annotations

import glob
import json
import os
import re

import pytest
from tiny import TINY_CLI, tiny

from ttd3_jax.cli import evaluate, export, train
from ttd3_jax.run import rundir, status
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.trajectories import TrackConfig

HERE = os.path.dirname(__file__)
T = ["--total-transitions", "20000", "--epochs", "2"]


def refused(main, argv, capsys) -> str:
    """``main(argv)``'s stderr, after checking it exited 2 without a traceback."""
    try:
        code = main(argv)
    except SystemExit as e:  # argparse and tyro exit themselves
        code = e.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and err.strip(), err
    return err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--seed", "99999999999999999999", *T], r"seed must be an integer in \[0, 4294967295\]"),
        (["--seed", "4294967296", *T], r"seed must be an integer in \[0, 4294967295\]"),
        (["--seed", "4294967295", "--num-seeds", "2", *T], r"seed must be an integer in \[0, 4294967294\]"),
        ([*T, "--out", "/proc/ttd3"], r"--out '/proc/ttd3': cannot write in '/proc'"),
        (["--preset", "", *T], r"--preset must be one of .*got ''"),
        (["--out", "", *T], r"--out must name a directory, got ''"),
        ([*T, "--task.tracks.generator.los-climb-rate", "0.2"], r"Unrecognized options"),  # a reading: Python
        (
            [*T, "--normalize-obs", "false"],
            r"--normalize-obs takes no value: .* --no-normalize-obs for false",
        ),
        ([*T, "--task.observation.obs-memory", "no"], r"--task.observation.no-obs-memory for false"),
        ([*T, "--hp.lr-critic", "1e30"], r"hp.lr_critic must be a finite number in \(0, 1\]"),
        ([*T, "--hp.reward-scale", "1e30"], r"hp.reward_scale must be a finite number in \(0, 1000\]"),
        (["--epochs", "x"], r"python -m ttd3_jax.train --help"),  # tyro names the module, not train.py
    ],
)
def test_train_refuses(argv, message, capsys):
    assert re.search(message, refused(train.main, argv, capsys))


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("los_climb_rate", float("inf"), r"los_climb_rate must be a finite number"),
        ("los_init_point", (float("nan"), 0.0, 0.0), r"los_init_point must be 3 finite numbers"),
    ],
)
def test_a_bad_reading_of_the_paper_is_refused_in_python(field, value, message):
    """The readings of the paper are run-spec fields, not flags: set in Python, checked there."""
    with pytest.raises(ValueError, match=message):
        make_config("paper", generator=TrackConfig(**{field: value}))


@pytest.mark.skipif(not os.path.isdir("/sys/kernel"), reason="needs sysfs")
def test_train_refuses_a_read_only_out(capsys):
    assert "--out '/sys/ttd3': cannot write in '/sys'" in refused(
        train.main, [*T, "--out", "/sys/ttd3"], capsys
    )


def test_binary_and_bom_track_files(tmp_path, capsys):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(bytes([0xBE, 0xEF, 0x00, 0xFF]) * 16)
    err = refused(train.main, [*T, "--train-tracks", str(junk)], capsys)
    assert re.search(r"--train-tracks: .*junk.bin is not a CSV text file \(byte 0xbe at offset 0\)", err)
    err = refused(evaluate.main, ["--track", str(junk)], capsys)
    assert "--track: " in err and "is not a CSV text file" in err
    bom = tmp_path / "excel.csv"
    bom.write_bytes("\ufefft,x,y,z\n0,0,0,0\n0.5,1,0,0\n1,2,0,0\n".encode())
    assert ct.from_csv(str(bom)).duration_s == pytest.approx(1.0)


def test_track_coordinates_must_be_bounded(tmp_path, capsys):
    path = tmp_path / "wild.csv"
    path.write_text("t,x,y,z\n" + "".join(f"{i * 0.1},{(i % 2) * 1e30},0,0\n" for i in range(6)))
    err = refused(evaluate.main, ["--track", str(path)], capsys)
    assert re.search(r"pos \[m\] must be finite and within ±10000; entry \(1, 0\) is 1e\+30", err)
    with pytest.raises(ValueError, match=r"vel \[m/s\] \(from pos\) must be finite and within"):
        ct.from_samples([0, 1e-3, 2e-3], [[0, 0, 0], [5e3, 0, 0], [0, 0, 0]])


def test_evaluate_output_paths_are_checked_before_evaluating(tmp_path, capsys):
    afile, adir = tmp_path / "afile", tmp_path / "adir"
    afile.write_text("")
    adir.mkdir()
    hover = ["--controller", "hover", "--no-timing"]
    err = refused(evaluate.main, [*hover, "--json", str(adir)], capsys)
    assert f"--json '{adir}' is a directory" in err
    err = refused(evaluate.main, [*hover, "--json", "/proc/x/y.json"], capsys)
    assert "--json '/proc/x/y.json': cannot write in '/proc'" in err
    err = refused(evaluate.main, [*hover, "--json", str(tmp_path / "ok.json"), "--plots", str(afile)], capsys)
    assert f"--plots '{afile}': '{afile}' is a file" in err
    assert not (tmp_path / "ok.json").exists()  # refused before anything was written


def test_evaluate_refuses_a_physics_step_the_integrator_does_not_take(capsys):
    err = refused(evaluate.main, ["--controller", "geometric", "--task.dt", "0.5"], capsys)
    assert re.search(r"EnvConfig.dt must be a finite number in \(0, 0.01\] s", err) and "got 0.5" in err


def test_export_out_must_be_a_writable_directory(tmp_path, capsys):
    run_dir = rundir.new_run_dir(str(tmp_path / "runs"), tiny())
    afile = tmp_path / "afile"
    afile.write_text("")
    err = refused(export.main, [run_dir, "--out", "/proc/x", "--no-onnx"], capsys)
    assert "--out '/proc/x': cannot write in '/proc'" in err
    err = refused(export.main, [run_dir, "--out", f"{afile}/pol", "--no-onnx"], capsys)
    assert f"--out '{afile}/pol': '{afile}' is a file" in err


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.clear(), "config.json is format None, written by an older ttd3_jax"),
        (
            lambda d: [d.pop(k) for k in ("env", "train", "hp", "task", "brax", "seed", "num_seeds")],
            'fields "env", "train", "hp", "task", "brax", "seed", "num_seeds" are missing',
        ),
        (
            lambda d: d["train"].update(hidden="64,64"),
            "field \"train.hidden\" - should be a list, got '64,64'",
        ),
        (
            lambda d: [d["task"]["observation"].pop(k) for k in ("obs_frame", "lookahead_k")],
            'fields "task.observation.lookahead_k", "task.observation.obs_frame" are missing',
        ),
        (lambda d: d["train"].pop("critic_arch"), 'field "train.critic_arch"'),
    ],
)
def test_a_config_json_missing_a_field_or_of_a_wrong_type_is_refused(tmp_path, edit, message, capsys):
    run_dir = rundir.new_run_dir(str(tmp_path), tiny())
    path = os.path.join(run_dir, "config.json")
    with open(path) as fh:
        d = json.load(fh)
    edit(d)
    with open(path, "w") as fh:
        json.dump(d, fh)
    assert message in refused(evaluate.main, [run_dir, "--no-timing"], capsys)
    assert message in refused(train.main, ["--resume", run_dir], capsys)  # before "resumed ... at epoch"
    assert "resumed" not in capsys.readouterr().out


def test_a_config_of_another_format_gets_one_line_naming_it(tmp_path, capsys):
    """config.json has one format: a file of another (an older ttd3_jax's) or none is refused
    with one line that names its format and what to do, by train --resume, evaluate and export."""
    d = json.loads(json.dumps(sp.to_dict(tiny())))
    assert sp.from_dict(d) == tiny()
    for other in (9, None):
        old = {k: v for k, v in d.items() if k != "format"} if other is None else {**d, "format": other}
        with pytest.raises(ValueError, match=f"config.json is format {other!r}, written by an older"):
            sp.from_dict(old)
    run_dir = rundir.new_run_dir(str(tmp_path), tiny())
    with open(os.path.join(run_dir, "config.json"), "w") as fh:
        json.dump({**d, "format": 9}, fh)
    for main, args in ((evaluate.main, [run_dir, "--no-timing"]), (train.main, ["--resume", run_dir]),
                       (export.main, [run_dir, "--out", str(tmp_path / "p"), "--no-onnx"])):  # fmt: skip
        message = refused(main, args, capsys)
        assert "format 9" in message and "Traceback" not in message and len(message.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "main, args, message",
    [
        (evaluate.main, ["--json", "{run}/config.json"], "is config.json of the run"),
        (evaluate.main, ["--json", "{run}/metrics.csv"], "is metrics.csv of the run"),
        (evaluate.main, ["--json", "{run}/state.json"], "is state.json of the run"),
        (evaluate.main, ["--json", "{run}/checkpoints/x.json"], "is inside checkpoints/ of the run"),
        (evaluate.main, ["--plots", "{run}/best"], "is inside best/ of the run"),
        (export.main, ["--out", "{run}/checkpoints/4", "--no-onnx"], "is inside checkpoints/ of the run"),
        (export.main, ["--out", "{run}/best/policy", "--no-onnx"], "is inside best/ of the run"),
    ],
)
def test_readers_never_write_into_a_runs_own_files(tmp_path, capsys, main, args, message):
    """evaluate and export refuse an output over a run's config.json, metrics.csv, state.json
    (...) or inside its checkpoints/ or best/, before anything loads, and leave it as it was."""
    run_dir = rundir.new_run_dir(str(tmp_path), tiny())
    before = open(os.path.join(run_dir, "config.json")).read()
    argv = [run_dir, *(a.format(run=run_dir) for a in args)]
    assert message in refused(main, argv + (["--no-timing"] if main is evaluate.main else []), capsys)
    assert open(os.path.join(run_dir, "config.json")).read() == before
    for name in ("metrics.csv", "state.json", "best"):
        assert not os.path.exists(os.path.join(run_dir, name)), name


def test_robustness_seeds_that_cannot_fit_are_refused_before_anything_compiles(capsys):
    err = refused(evaluate.main, ["--controller", "hover", "--robustness", "--robustness-seeds", "100000000",
                                  "--no-timing"], capsys)  # fmt: skip
    assert re.search(r"--robustness-seeds 100000000 needs about [\d.e+]+ GiB .* fits", err), err


def test_a_fifo_track_is_refused_not_read(tmp_path, capsys):
    fifo = tmp_path / "track.csv"
    os.mkfifo(fifo)  # opening it for reading would block until a writer comes
    err = refused(evaluate.main, ["--controller", "hover", "--track", str(fifo), "--no-timing"], capsys)
    assert "not a regular file (a directory, FIFO or device)" in err


def test_a_training_track_far_longer_than_an_episode_is_refused(tmp_path, capsys):
    """An 83 MB training CSV made every env keep a 3,000,000-row table: 100x the reference an
    episode flies is the most a training track may last."""
    path = str(tmp_path / "long.csv")
    ct.to_csv(ct.step((0.0, 0.0, 0.3), 400.0, name="long"), path)
    err = refused(train.main, [*TINY_CLI, "--train-tracks", path, "--out", str(tmp_path / "runs")], capsys)
    assert f"{path} lasts 400 s, but an episode flies" in err and "cut it to at most" in err
    assert not (tmp_path / "runs").exists()  # before the run directory


def test_every_committed_run_spec_loads():
    found = glob.glob(os.path.join(HERE, "..", "results", "**", "config.json"), recursive=True)
    assert len(found) >= 8
    for path in found:
        assert rundir.load_spec(os.path.dirname(path)).train.epochs >= 1, path


def test_help_puts_each_option_under_its_own_text(capsys):
    with pytest.raises(SystemExit):
        train.main(["--help"])
    parts = re.split(r"(?m)^[^\w-]*(--[a-z][\w.-]*)", capsys.readouterr().out)
    texts = {
        flag: " ".join(re.sub(r"[│|]", " ", body).split())
        for flag, body in zip(parts[1::2], parts[2::2], strict=False)
    }
    assert "widths of the hidden layers" in texts["--hidden"] and "0: the actor" not in texts["--hidden"]
    bodies = list(texts.values())
    assert len(bodies) > 50 and not [
        b for a, b in zip(bodies, bodies[1:], strict=False) if a == b
    ]  # no text repeated


def test_resume_takes_an_out_directory_like_evaluate_and_export(tmp_path, capsys):
    """``--resume OUT`` resolves a training --out folder to its newest run (here a finished
    one, which it names and leaves alone, without compiling)."""
    run_dir = rundir.new_run_dir(str(tmp_path), tiny())
    status.mark(run_dir, "finished", epoch=2)
    assert train.main(["--resume", str(tmp_path)]) == 0
    out = capsys.readouterr()
    assert f"{run_dir} finished all 2 epochs" in out.out + out.err
    assert "not a ttd3_jax run directory" not in out.err and "Traceback" not in out.err


def test_tiny_cli_still_parses():
    known, spec = train.parse([*TINY_CLI, "--out", "runs_x"])
    assert spec.train.hidden == (32, 32) and known.out == "runs_x"
