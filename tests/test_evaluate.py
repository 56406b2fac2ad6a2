"""Evaluation of saved runs, run-time figures and robustness (``ttd3_jax.evaluate``,
``ttd3_jax.control``), and the env's robustness options (``action_delay``,
``thrust_map_mass``)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import experiment
from tiny import tiny

from ttd3_jax.cli import train
from ttd3_jax.cli.evaluate import main
from ttd3_jax.cli.export import main as export_main
from ttd3_jax.control.closed_loop import closed_loop, evaluate_on_tracks, hover_controller, sensed_controller
from ttd3_jax.control.closed_loop import test_tracks as make_test_tracks
from ttd3_jax.control.evaluator import controller_build
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.control.robustness import (
    ROBUSTNESS_CONDITIONS,
    ROBUSTNESS_DESCRIPTIONS,
    evaluate_robustness,
    robustness_conditions,
)
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import report, rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.run.report import TRACE_COLUMNS
from ttd3_jax.run.sharding import per_seed
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.dynamics import yaw_of
from ttd3_jax.sim.env import TrackingEnv, hover_action
from ttd3_jax.td3 import networks
from ttd3_jax.td3.networks import init_params, twin_q
from ttd3_jax.td3.trainer import seed_keys


def fake_run_dir(path, spec: sp.RunSpec | None = None, obs_var: float | None = None) -> str:
    """A run directory as the runner writes it (config.json of ``spec``, default ``tiny`` with
    a change to the preset's env config; an orbax checkpoint of the whole train state at epoch
    2), without the ~40 s of compiling a real run: the state is zeros except for freshly
    initialised actor and critic weights (``init_params`` with key 3) and, with ``obs_var``,
    observation statistics of mean 0 and that variance."""
    base = tiny()
    s = spec or sp.replace(base, task=base.task.replace(obs_frame="world"))
    trainer = sp.trainer_for(s)
    like = jax.eval_shape(
        per_seed(trainer.init, s.num_seeds, (0, None)), seed_keys(s.seed, s.num_seeds), s.hp
    )
    state = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), like)
    actor, critic = init_params(trainer.nets, jax.random.PRNGKey(3), trainer.env.obs_size, 4)
    lead = lambda tree: jax.tree.map(lambda x: x[None], tree)  # noqa: E731  (the seed axis)
    state = state.replace(actor=lead(actor), critic=lead(critic))
    if obs_var is not None:
        n = trainer.env.obs_size
        stats = networks.ObsStats(count=jnp.ones((1,)), mean=jnp.zeros((1, n)), m2=jnp.full((1, n), obs_var))
        state = state.replace(obs_stats=stats)
    os.makedirs(path)
    with open(os.path.join(path, "config.json"), "w") as fh:
        json.dump(sp.to_dict(s), fh)
    ckpt.save(ckpt.manager(str(path)), 2, state)
    return str(path)


def check_evaluation_json(run_dir: str, epoch: int, obs_frame: str = "track") -> dict:
    with open(os.path.join(run_dir, "evaluation.json")) as fh:
        out = json.load(fh)
    with open(os.path.join(run_dir, "config.json")) as fh:
        task = json.load(fh)["task"]
    assert out["epoch"] == epoch
    assert out["env_config"] == task  # the run's whole env config (the practical preset's) ...
    assert out["env_config"]["action_repeat"] == 10  # ... not the paper preset
    assert out["env_config"]["observation"]["obs_frame"] == obs_frame  # with the run's changes to the preset
    res = out["results"]["seed 0"]
    assert set(res) == {"spiral_rt", "los_rt"}
    for m in res.values():
        assert m["crashed"] in (0.0, 1.0)
        assert m["energy"] > 0 and m["control_steps"] == 300
        assert m["loop_s"] > 0 and m["scan_s"] > 0 and m["act_ms"] > 0 and m["compile_scan_s"] > 0
        assert len(m["loop_runs_s"]) == 1
    for track in ("spiral_rt", "los_rt"):
        for kind in ("3d", "error", "actions"):
            assert os.path.isfile(os.path.join(run_dir, f"{track}_{kind}.png"))
        rows = read_trace(os.path.join(run_dir, f"{track}_trace.csv"))
        assert set(rows["label"]) == {"seed 0"} and rows.size == 300  # one row per control step
        np.testing.assert_allclose(rows["t_s"][[0, -1]], [0.01, 3.0], rtol=1e-6)
    return out


def flat(text: str) -> str:
    """``text`` with the frames of tyro's error boxes removed and its lines joined (so that a
    message wrapped at the terminal width reads as one line)."""
    return " ".join(re.sub("[│╭╮╰╯─]", " ", text).split())


def read_trace(path: str) -> np.ndarray:
    rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert ",".join(rows.dtype.names) == TRACE_COLUMNS
    return rows


def test_cli_evaluates_a_saved_checkpoint(tmp_path, capsys):
    run_dir = fake_run_dir(tmp_path / "run")
    assert main([run_dir, "--repeats", "1"]) == 0
    text = capsys.readouterr().out
    assert "epoch 2" in text and "seed 0" in text and "loop s" in text
    check_evaluation_json(run_dir, 2, obs_frame="world")
    # flags that do not apply to a run directory are refused
    with pytest.raises(SystemExit):
        main([run_dir, "--controller", "nmpc"])
    with pytest.raises(SystemExit):
        main([run_dir, "--task.reward.e-max", "1"])  # a run keeps the env it trained in
    for bad in (["--task.disturbances.wind-sigma", "1"], ["--task.tracks.track", "los_rt"],
                ["--task.action-repeat", "0"], ["--task.mass", "2"]):  # fmt: skip
        with pytest.raises(SystemExit):
            main(["--controller", "hover", *bad])
    err = flat(capsys.readouterr().err)
    assert "set by the evaluation protocol" in err and "action_repeat must be an integer >= 1" in err
    assert "Unrecognized options: --task.mass" in err
    assert main([run_dir, "--seed-index", "3"]) == 2
    assert main([str(tmp_path / "missing")]) == 2


def test_a_run_whose_training_csv_moved_is_evaluated_and_exported_but_not_resumed(tmp_path, capsys):
    """Issue 49: evaluate and export read a run whose training-track CSV has moved (neither
    reads it; the training envs' track tables take the size its checkpoint holds), the same
    policies as before; resuming, which trains on it, and training on it anew are refused in
    one line naming the file."""
    csv = str(tmp_path / "hop.csv")
    ct.to_csv(ct.step((0.0, 0.0, 0.3), 1.0, name="hop"), csv)  # 1002 rows: more than the mixture's
    base = tiny()
    spec = sp.replace(base, task=base.task.replace(train_tracks=(csv,), train_tracks_weight=0.5))
    run_dir = fake_run_dir(tmp_path / "run", spec)
    (tmp_path / "run" / "metrics.csv").write_text("epoch,seed\n2,0\n")
    theta = rundir.load_run(run_dir).thetas[0][1]
    ckpt.save_policy(run_dir, 0, 2, 1.0, {"actor": theta[0], "obs_stats": theta[1]})
    os.rename(csv, csv + ".moved")
    for best in (False, True):
        jax.tree.map(np.testing.assert_array_equal, rundir.load_run(run_dir, best=best).thetas[0][1], theta)
    assert main([run_dir, "--no-timing", "--track", "spiral_rt", "--json", str(tmp_path / "e.json")]) == 0
    assert export_main([run_dir, "--out", str(tmp_path / "policy"), "--no-onnx"]) == 0
    assert os.path.isfile(tmp_path / "policy" / "policy.h")
    assert ckpt.saved_track_rows(run_dir) == 1002 > TrackingEnv(base.task).num_segments  # what it is about
    capsys.readouterr()
    assert train.main(["--resume", run_dir]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: --resume {run_dir}: its training track {csv!r} is not a file (moved or "
                   "deleted?); continuing the training reads the run's training tracks: put it back there "
                   "(evaluate and export read the run without it)")  # fmt: skip
    with pytest.raises(ValueError, match=f"task.tracks.train_tracks: {re.escape(repr(csv))} is not a file"):
        run(spec, out=str(tmp_path / "runs"), verbose=False)
    assert not (tmp_path / "runs").exists()  # refused before the run directory, before anything compiles


def test_cli_trace_csv_holds_the_rollout_behind_the_metrics(tmp_path):
    """The trace CSV of a classical controller's evaluation: at the paper's 1 kHz, one row
    per physics step, whose errors are the positions' distances and sum to Σ‖e‖."""
    out = tmp_path / "geometric.json"
    args = ["--controller", "geometric", "--track", "spiral_rt", "--no-timing", "--json", str(out)]
    assert main([*args, "--task.vehicle.quad.mass", "1.8"]) == 0  # a heavier vehicle
    with open(out) as fh:
        saved = json.load(fh)
    assert saved["env_config"]["vehicle"]["quad"]["mass"] == 1.8 and saved["task_args"] == [
        "--task.vehicle.quad.mass",
        "1.8",
    ]
    res = saved["results"]["geometric"]["spiral_rt"]
    rows = read_trace(str(tmp_path / "spiral_rt_trace.csv"))
    assert not (tmp_path / "los_rt_trace.csv").exists()
    assert set(rows["label"]) == {"geometric"} and rows.size == 3000
    np.testing.assert_allclose(rows["t_s"], 1e-3 * np.arange(1, 3001), rtol=1e-6)
    pos = np.stack([rows[c] for c in ("x_m", "y_m", "z_m")], -1)
    ref = np.stack([rows[c] for c in ("x_ref_m", "y_ref_m", "z_ref_m")], -1)
    np.testing.assert_allclose(rows["error_m"], np.linalg.norm(pos - ref, axis=-1), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(rows["error_m"].sum(), res["tracking_error"], rtol=1e-5)
    actions = np.stack([rows[c] for c in ("a0_thrust", "a1_wx", "a2_wy", "a3_wz")], -1)
    assert np.all(np.abs(actions) <= 1.0) and np.ptp(actions[:, 0]) > 0
    # the velocity is the positions' derivative (central differences, 1 ms apart)
    vel = np.stack([rows[c] for c in ("vx_mps", "vy_mps", "vz_mps")], -1)
    np.testing.assert_allclose((pos[2:] - pos[:-2]) / 2e-3, vel[1:-1], atol=2e-3)
    quat = np.stack([rows[c] for c in ("qw", "qx", "qy", "qz")], -1)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(rows["yaw_rad"], yaw_of(jnp.asarray(quat.T)), atol=1e-6)


def test_cli_refuses_the_episode_length_as_a_protocol_field(capsys):
    """The evaluation protocol fixes the episode (3 s); --task.episode-steps may not shorten it."""
    with pytest.raises(SystemExit) as exc:
        main(["--controller", "geometric", "--task.episode-steps", "10"])
    assert exc.value.code == 2
    err = flat(capsys.readouterr().err)
    assert "--task.episode-steps is set by the evaluation protocol" in err
    assert "Traceback" not in err


def test_cli_refuses_two_vehicles_for_a_classical_controller(capsys):
    """A classical controller flies one vehicle: --task.randomization.vehicles is refused (it
    used to fly the first one silently), naming --vehicle instead."""
    with pytest.raises(SystemExit) as exc:
        main(["--controller", "geometric", "--preset", "practical", "--task.vehicle.hover-centered-thrust",
              "--task.randomization.vehicles", "paper", "crazyflie"])  # fmt: skip
    assert exc.value.code == 2
    err = flat(capsys.readouterr().err)
    assert "--task.randomization.vehicles paper crazyflie: a classical controller flies one vehicle" in err
    assert "allowed: --vehicle NAME" in err and "Traceback" not in err


def test_probe_critics_reads_a_run_and_matches_a_direct_critic_call(tmp_path, capsys):
    pc = experiment("probe_critics")
    run_dir = fake_run_dir(tmp_path / "run")
    r = pc.probe(run_dir)
    # oracle: the same critics called directly on the start state (the fake run's obs stats
    # are zeros, so the normaliser maps every observation to the clip bounds or 0)
    loaded = rundir.load_train_state(run_dir)
    trainer = loaded.trainer
    _, critic = init_params(trainer.nets, jax.random.PRNGKey(3), trainer.env.obs_size, 4)
    env = TrackingEnv(loaded.spec.task.for_eval("spiral_rt"))
    obs = networks.normalize(
        jax.tree.map(lambda x: x[0], loaded.state.obs_stats), env.reset(jax.random.PRNGKey(0)).obs
    )
    hover = hover_action(env.config)
    np.testing.assert_allclose(r["q_hover"], twin_q(trainer.nets, critic, None, obs, hover), rtol=1e-6)
    np.testing.assert_allclose(r["hover"], hover, atol=1e-7)
    assert r["hover"][0] == pytest.approx(0.0, abs=1e-6)  # hover-centred thrust: a0 = 0 is hover
    assert all(-1.0 <= a <= 1.0 for a in r["policy"])
    assert min(r["max_dq"]) > 0 and r["q_policy"] != r["q_hover"]
    # the hover action held from rest on Spiral-RT: the error grows as the track moves away
    assert 0 < r["final_error_hover"] < 10 and r["error_hover"] > 0 and r["error_policy"] > 0
    assert pc.main([run_dir, "--track", "los_rt"]) == 0
    assert "max |dQ|" in capsys.readouterr().out
    assert pc.main([run_dir, "--seed-index", "1"]) == 2
    assert "seed_index must be in [0, 1)" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_evaluates_a_real_tiny_run(tmp_path):
    summary = run(tiny(), out=str(tmp_path), verbose=False)
    assert main([summary["run_dir"], "--repeats", "1"]) == 0
    check_evaluation_json(summary["run_dir"], 2)


# --------------------------------------------------------------------------- env options


def test_action_delay_applies_the_previous_action():
    cfg = make_config("paper").for_eval("spiral_rt")
    delayed, plain = TrackingEnv(cfg, action_delay=1), TrackingEnv(cfg)
    key = jax.random.PRNGKey(0)
    a, b = jnp.array([0.9, 0.3, -0.2, 0.1]), jnp.array([-0.5, 0.0, 0.4, 0.0])
    hover = hover_action(cfg)
    s1 = delayed.step(delayed.reset(key), a)
    s2 = delayed.step(s1, b)
    r1 = plain.step(plain.reset(key), hover)  # step 1 applies the reset's hover action ...
    r2 = plain.step(r1, a)  # ... and step 2 applies a
    for s, r in ((s1, r1), (s2, r2)):
        jax.tree.map(np.testing.assert_array_equal, s.pipeline_state.quad, r.pipeline_state.quad)
        assert float(s.metrics["energy"]) == pytest.approx(float(r.metrics["energy"]))
    np.testing.assert_array_equal(s2.pipeline_state.prev_action, b)
    # closed_loop records the applied (delayed) action
    r = closed_loop(delayed, hover_controller(cfg), delayed.reset(key))
    np.testing.assert_allclose(r.action, np.broadcast_to(hover, r.action.shape), atol=1e-7)
    for bad in (2, -1, True, 0.5):
        with pytest.raises(ValueError, match="action_delay"):
            EnvConfig().replace(action_delay=bad)
    with pytest.raises(ValueError, match="thrust_map_mass"):
        EnvConfig().replace(thrust_map_mass=0.0)


def _flat(cfg: EnvConfig) -> dict:
    """``{group.field: value}`` of a config (its own fields as they are)."""
    out = {}
    for k, v in dataclasses.asdict(cfg).items():
        out.update({f"{k}.{f}": x for f, x in v.items()} if isinstance(v, dict) else {k: v})
    return out


def test_robustness_conditions_carry_exactly_the_stated_perturbations():
    cfg = make_config("practical", hover_centered_thrust=True, thrust_map_mass=None)
    conds = robustness_conditions(cfg)
    nominal = conds["nominal"]
    assert nominal == cfg.for_eval("los_rt") and tuple(conds) == ROBUSTNESS_CONDITIONS
    assert set(ROBUSTNESS_CONDITIONS) == set(ROBUSTNESS_DESCRIPTIONS)
    d = 0.02 / math.sqrt(3)
    expected = {
        "nominal": {},
        "wind0.5": {"disturbances.wind_sigma": 0.5},
        "wind1.0": {"disturbances.wind_sigma": 1.0},
        "mass+30": {"randomization.mass": (1.3, 1.3)},
        "mass-30": {"randomization.mass": (0.7, 0.7)},
        "thrust-20": {"randomization.thrust_gain": (0.8, 0.8)},
        "rate_tau0.05": {"randomization.tau_rate": (0.05 / 0.03, 0.05 / 0.03)},
        "latency10ms": {"randomization.latency": (0.01, 0.01)},
        "latency20ms": {"randomization.latency": (0.02, 0.02)},
        "obs_noise": {
            "disturbances.obs_noise_pos": 0.01,
            "disturbances.obs_noise_vel": 0.05,
            "disturbances.obs_noise_quat": 0.005,
        },  # fmt: skip
        "pos_bias2cm": {"randomization.pos_bias": (d, d, d)},
    }
    assert set(expected) == set(conds)
    flat0 = _flat(nominal)
    for name, c in conds.items():
        changed = {k: v for k, v in _flat(c).items() if v != flat0[k]}
        assert changed.keys() == expected[name].keys(), name
        for k, v in expected[name].items():
            assert changed[k] == pytest.approx(v), (name, k)
        # the controller's (nominal) vehicle and action map are untouched: the mismatch is unknown
        assert c.vehicle == nominal.vehicle, name
        np.testing.assert_allclose(hover_action(c), hover_action(nominal))
    assert rz.latency_steps(conds["latency10ms"]) == (10, 10)  # 1 ms physics steps: one 100 Hz step
    assert rz.latency_steps(conds["latency20ms"]) == (20, 20)
    assert rz.flown_rate_model(conds["rate_tau0.05"]) == "first_order"
    plant = rz.draw(conds["rate_tau0.05"], jax.random.PRNGKey(3))
    assert float(plant.quad.tau_rate) == pytest.approx(0.05)
    bias = rz.draw(conds["pos_bias2cm"], jax.random.PRNGKey(3)).pos_bias
    np.testing.assert_allclose(bias, [d, d, d], rtol=1e-6)  # fixed, not drawn
    assert float(np.linalg.norm(bias)) == pytest.approx(0.02, rel=1e-6)
    assert not rz.active(nominal)
    assert all(rz.active(conds[n]) for n in ("mass+30", "latency10ms", "pos_bias2cm"))
    for bad in ((0.01, 0.0), (0.0, 0.0, float("nan")), -0.01):
        with pytest.raises(ValueError, match="pos_bias"):
            nominal.replace(pos_bias=bad)


def test_mass_and_thrust_mismatch_are_unknown_to_the_controller():
    # the hover-centred map (a0 = 0 is hover thrust) would leak the mass if it used the true mass
    cfg = make_config("practical", episode_steps=500, hover_centered_thrust=True)
    conds = robustness_conditions(cfg)
    ctrl = hover_controller(conds["nominal"])  # the controller knows only the nominal config
    # any track: the hover controller ignores it; only the vehicle's own climb or sink is measured
    track = jax.tree.map(lambda x: x[0], make_test_tracks(TrackingEnv(conds["nominal"])))
    dz = {}
    for name in ("nominal", "mass+30", "mass-30", "thrust-20"):
        env = TrackingEnv(conds[name])
        r = closed_loop(env, ctrl, env.reset_with_track(jax.random.PRNGKey(0), track))
        dz[name] = float(r.pos[-1, 2] - r.pos[0, 2])
    t = 0.5  # s
    assert abs(dz["nominal"]) < 1e-3
    # the heavier quad sinks with a = g(1/1.3 - 1), the lighter one climbs with g(1/0.7 - 1),
    # 20 % less thrust sinks with g(0.8 - 1)
    assert dz["mass+30"] == pytest.approx(0.5 * 9.81 * (1 / 1.3 - 1) * t**2, rel=0.05)
    assert dz["mass-30"] == pytest.approx(0.5 * 9.81 * (1 / 0.7 - 1) * t**2, rel=0.05)
    assert dz["thrust-20"] == pytest.approx(0.5 * 9.81 * (0.8 - 1) * t**2, rel=0.05)


def test_sensed_controller_on_the_track_frame_equals_the_true_state_controller():
    """Without noise the observation holds the true state: fed from a track-frame
    observation (positions shifted back by p_d,k, q possibly negated), the geometric
    controller flies the same closed loop as on the true state."""
    env = TrackingEnv(make_config("practical").for_eval("los_rt"))
    assert env.config.observation.obs_frame == "track"
    geo = geometric_controller(env.config)
    tracks = make_test_tracks(env)
    run_ = jax.jit(lambda c: evaluate_on_tracks(env, c, tracks)["tracking_error"], static_argnums=0)
    plain, sensed = run_(geo), run_(sensed_controller(geo, env.config))
    assert np.all(np.isfinite(plain))
    np.testing.assert_allclose(sensed, plain, rtol=1e-5)


# --------------------------------------------------------------------------- robustness


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_robustness_returns_finite_statistics():
    cfg = make_config("paper", episode_steps=300)
    nominal = cfg.for_eval("los_rt")
    seeds = (1, 2)
    conditions = ("nominal", "wind0.5", "rate_tau0.05", "latency20ms", "obs_noise", "pos_bias2cm")
    geo = evaluate_robustness(controller_build("geometric", nominal), None, cfg, seeds, conditions=conditions)
    assert tuple(geo) == conditions
    for name, r in geo.items():
        los = r["los_rt"]
        assert los["seeds"] == [1, 2] and los["crashed"] == 0, name
        for key in ("tracking_error", "energy", "energy_sq", "rmse", "max_error"):
            assert math.isfinite(los[key]["mean"]) and math.isfinite(los[key]["std"]), (name, key)
            assert los[key]["std"] >= 0
        assert math.isfinite(r["spiral_rt"]["tracking_error"])
    e = {k: v["los_rt"]["tracking_error"]["mean"] for k, v in geo.items()}
    s = {k: v["spiral_rt"]["tracking_error"] for k, v in geo.items()}
    for name in conditions[1:]:  # each perturbation reaches the (sensed-state) geometric controller
        assert e[name] != e["nominal"], name
    # ... and makes its tracking worse (a slower or later actuation, a wrong position)
    for name in ("rate_tau0.05", "latency20ms", "pos_bias2cm"):
        assert s[name] > s["nominal"] and e[name] > e["nominal"], name
    with pytest.raises(ValueError, match="robustness condition"):
        evaluate_robustness(controller_build("hover", nominal), None, cfg, seeds, conditions=("gusts",))


# --------------------------------------------------------------------------- perturbation sweep


def _sweep_module():
    return experiment("perturbation_sweep")


def test_perturbation_sweep_prints_its_help():
    """--help formats every option (a bare % in a help string made argparse raise)."""
    text = _sweep_module().build_parser().format_help()
    assert "--mass MASS" in text and "in % (default" in text


def test_perturbation_sweep_refuses_bad_arguments(tmp_path, capsys):
    sweep = _sweep_module()
    run_dir = fake_run_dir(tmp_path / "run")
    out = str(tmp_path / "out")
    cases = {
        ("--seeds", "0"): "--seeds must be >= 1",
        ("--mass=-10,x",): "--mass takes comma-separated numbers",
        ("--mass=10,10",): "repeats a point",
        ("--mass=-100",): "--mass points must be in (-100, ∞)",
        ("--last", "--mass=40"): "--mass 40: EnvConfig.randomization.mass",  # the paper vehicle cannot hover
        ("--latency-ms", "60"): "--latency-ms points must be in [0, 50]",
        ("--noise=-1",): "--noise points must be in [0, ∞]",
        ("--controllers", "policy,mpc"): "--controllers takes policy, nmpc or both",
        ("--mass=", "--latency-ms=", "--noise="): "every panel is empty",
        (): "no selected policy",  # the fake run has no best/: --last takes its checkpoint
    }
    for flags, message in cases.items():
        with pytest.raises(SystemExit) as e:
            sweep.main([run_dir, "--out", out, *flags])
        assert e.value.code == 2, flags
        err = capsys.readouterr().err.strip().splitlines()
        assert message in err[-1], (flags, err)
    with pytest.raises(SystemExit):
        sweep.main([str(tmp_path / "nothing"), "--out", out])
    assert "not a ttd3_jax run directory" in capsys.readouterr().err
    assert not os.path.exists(out)


@pytest.mark.slow
def test_perturbation_sweep_writes_its_figures(tmp_path, capsys):
    sweep = _sweep_module()
    run_dir = fake_run_dir(tmp_path / "run")
    out = str(tmp_path / "out")
    argv = [run_dir, "--last", "--seeds", "1", "--out", out]
    argv += ["--mass=0,20", "--latency-ms=0,20", "--noise=0,2"]
    assert sweep.main(argv) == 0
    printed = capsys.readouterr().out
    assert "[policy] mass    +0 %" in printed and "[nmpc] obs_noise      ×2" in printed
    with open(os.path.join(out, "perturbation.json")) as fh:
        d = json.load(fh)
    assert d["los_seeds"] == [1] and set(d["panels"]) == {"mass", "latency", "obs_noise"}
    for who in ("policy", "nmpc"):
        rows = {p: {pt["x"]: pt for pt in d["panels"][p][who]} for p in d["panels"]}
        assert [sorted(r) for r in rows.values()] == [[0, 20], [0, 20], [0, 2]]
        # the zero of every panel is the nominal plant: one result
        zero = [rows[p][0]["los_mean"] for p in rows]
        assert all(math.isfinite(z) for z in zero) and zero[0] == zero[1] == zero[2], (who, zero)
        for p, x in (("mass", 20), ("latency", 20), ("obs_noise", 2)):
            assert rows[p][x]["los_mean"] != rows[p][0]["los_mean"], (who, p)
    with open(os.path.join(out, "perturbation.csv")) as fh:
        lines = fh.read().strip().splitlines()
    assert lines[0].startswith("panel,unit,size,controller,los_rt_error_mean") and len(lines) == 1 + 12
    assert os.path.getsize(os.path.join(out, "perturbation.png")) > 10_000


def test_format_robustness_aligns_the_widened_rows():
    los = {k: {"mean": 1.0, "std": 0.5} for k in ("tracking_error", "energy")}
    row = {"spiral_rt": {"tracking_error": 2.0}, "los_rt": dict(los, crashed=0, seeds=[1, 2])}
    lines = report.format_robustness("nmpc", {name: row for name in ROBUSTNESS_CONDITIONS}).splitlines()
    assert lines[0].startswith("robustness of nmpc: Spiral-RT, and LOS-RT seeds 1..2")
    assert [ln.split()[0] for ln in lines[2:]] == list(ROBUSTNESS_CONDITIONS)
    width = max(len(n) for n in ROBUSTNESS_CONDITIONS)
    assert len({ln.index("2.00") for ln in lines[2:]}) == 1 and lines[2].index("2.00") > width
