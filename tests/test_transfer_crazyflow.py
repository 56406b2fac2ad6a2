"""experiments/transfer_crazyflow.py: the rate loop's signs and hover in crazyflow, the
harness's observation against ttd3_jax's env (the ONNX action from it equals the JAX
policy's), and the command line.

Runs where crazyflow imports: its own venv (``pip install -e '.[transfer]'``; crazyflow 0.4.0
excludes jax 0.10.2), with this file on its own (crazyflow must be imported before scipy,
which other test modules import)::

    .venv-crazyflow/bin/python -m pytest tests/test_transfer_crazyflow.py -o addopts=""
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

try:
    pytest.importorskip("crazyflow")
except RuntimeError as e:  # scipy already imported in this process without SCIPY_ARRAY_API
    pytest.skip(f"run this file on its own: {str(e).splitlines()[0]}", allow_module_level=True)
ort = pytest.importorskip("onnxruntime")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from experiment_scripts import experiment  # noqa: E402

tc = experiment("transfer_crazyflow")
ROBUST = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "results", "robust", "run")


@pytest.fixture(scope="module")
def cf():
    return tc.Crazyflow("rotor_vel")


@pytest.fixture(scope="module")
def period(cf):
    return cf.rate_loop_period(10)


def fresh_pid():
    return (np.zeros(3, np.float32), np.zeros(3, np.float32))


@pytest.fixture(scope="module")
def robust(tmp_path_factory):
    """The committed robust run's seed-0 policy selected on validation, exported."""
    from ttd3_jax.cli.export import main as export_main

    out = str(tmp_path_factory.mktemp("robust") / "policy")
    assert export_main([ROBUST, "--out", out, "--best"]) == 0
    return out


def test_a_positive_torque_gives_a_positive_rate_on_each_axis(cf, period):
    """The mixer's torque, through crazyflow's own dynamics (rotors at their commanded speed),
    accelerates the body about that axis alone; and a positive rate setpoint through the rate
    PID, mixer and motors gives a positive body rate on that axis (roll, pitch, yaw; FLU)."""
    from crazyflow.drones import Drone
    from crazyflow.dynamics import parametrize
    from crazyflow.dynamics.first_principles import dynamics

    dyn = parametrize(dynamics, Drone(tc.DRONE))
    hover = cf.geo.mass * cf.geo.gravity
    zero, level = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    for axis, size in enumerate((1e-3, 1e-3, 5e-4)):  # N·m
        torque = np.zeros(3, np.float32)
        torque[axis] = size
        rpm = tc.rotor_rpm(
            cf.geo.rpm2thrust, np.asarray(tc.mix(cf.geo, hover, jnp.asarray(torque)), np.float64)
        )
        _, _, acc, w_dot, _ = dyn(pos=zero, quat=level, vel=zero, ang_vel=zero, cmd=rpm, rotor_vel=rpm)
        want = size / np.diag(np.asarray(cf.params["J"]))[axis]
        assert 0.8 * want < w_dot[axis] < 1.2 * want, (axis, w_dot)
        assert np.all(np.abs(np.delete(w_dot, axis)) < 1e-3 * want) and abs(acc[2]) < 0.02, (axis, w_dot, acc)
        data, pid = cf.start(np.zeros(3, np.float32)), fresh_pid()
        u = np.zeros(4, np.float32)
        u[0], u[1 + axis] = hover, 1.0  # N, rad/s
        for _ in range(15):  # 0.15 s
            data, pid, _, x = period(data, pid, u)
        rates = np.asarray(x)[10:13]
        assert rates[axis] > 0.5 and np.all(np.abs(np.delete(rates, axis)) < 0.1 * rates[axis]), (axis, rates)


def test_hover_thrust_and_zero_rates_hold_the_vehicle_within_1_cm_for_1_s(cf, period):
    p0 = np.array([0.3, -0.2, 1.0], np.float32)
    data, pid = cf.start(p0), fresh_pid()
    u = np.array([cf.geo.mass * cf.geo.gravity, 0, 0, 0], np.float32)
    worst = 0.0
    for _ in range(100):
        data, pid, pos, _ = period(data, pid, u)
        worst = max(worst, float(np.max(np.linalg.norm(np.asarray(pos) - p0, axis=-1))))
    assert worst < 0.01, worst


def test_the_harness_observation_gives_the_jax_policys_action(cf, robust):
    """Item 6: ttd3_jax's env flies the robust policy (memory, preview, reference integral) on
    LOS-RT seed 0 with the JAX actor; crazyflow is put in each visited state and the harness
    (state read back from crazyflow, fly_exported's observation and memory, the ONNX model)
    picks the JAX actor's action within 1e-5."""
    from ttd3_jax.run import rundir
    from ttd3_jax.run import spec as sp
    from ttd3_jax.sim.env import TrackingEnv
    from ttd3_jax.td3.trainer import act

    loaded = rundir.load_run(ROBUST, best=True)
    setup, (actor, stats) = sp.trainer_for(loaded.spec).setup, loaded.thetas[0][1]
    policy = jax.jit(lambda obs: act(setup, actor, stats, obs))
    env = TrackingEnv(loaded.env_config.for_eval("los_rt"))
    step = jax.jit(env.step)
    meta = json.load(open(os.path.join(robust, "policy.json")))
    session = ort.InferenceSession(os.path.join(robust, "policy.onnx"), providers=["CPUExecutionProvider"])
    ref = tc.reference("los_rt_seed00")
    harness = tc.policy_actor(meta, session, ref, 1.0)
    state, data, worst = env.reset(jax.random.PRNGKey(0)), cf.start(ref[0]), 0.0
    for _ in range(60):
        ps = state.pipeline_state
        quad, k = jax.device_get(ps.quad), int(ps.k)
        q = np.asarray(quad.q)  # (qw, qx, qy, qz) -> crazyflow's (qx, qy, qz, qw)
        states = data.states.replace(pos=jnp.asarray(quad.p).reshape(1, 1, 3),
                                     vel=jnp.asarray(quad.v).reshape(1, 1, 3),
                                     quat=jnp.asarray(np.r_[q[1:], q[0]]).reshape(1, 1, 4),
                                     ang_vel=jnp.asarray(quad.w).reshape(1, 1, 3))  # fmt: skip
        data = data.replace(states=states)
        harness(np.asarray(tc.Crazyflow.measured(data), np.float32), k)
        a = np.asarray(policy(state.obs))
        worst = max(worst, float(np.max(np.abs(harness.last["a"] - a))))
        state = step(state, jnp.asarray(a))
    assert int(state.pipeline_state.k) == 600 and not float(state.metrics["crashed"])
    assert worst < 1e-5, worst


def test_the_command_line_flies_a_track_and_writes_the_json(robust, tmp_path, capsys):
    path = str(tmp_path / "out.json")
    assert tc.main([robust, "--tracks", "spiral_rt", "--json", path]) == 0
    out = capsys.readouterr().out
    assert "spiral_rt" in out and "Mellinger" in out and "own-sim" in out
    d = json.load(open(path))
    r = d["tracks"]["spiral_rt"]
    for key in (
        "tracking_error",
        "crashed",
        "crash_time_s",
        "own_sim_tracking_error",
        "mellinger_tracking_error",
    ):
        assert key in r, key
    meta = json.load(open(os.path.join(robust, "policy.json")))
    want = meta["expected_tracking_error"]["sum_norm_e_m"]["spiral_rt"]
    assert r["own_sim_tracking_error"] == pytest.approx(want, rel=1e-3)
    assert r["crashed"] == (r["crash_time_s"] is not None) and r["tracking_error"] > 0
    s = d["settings"]
    assert s["crazyflow_version"] == "0.4.0" and s["drone"] == "cf2x_L250" and s["interface"] == "rate_loop"
    assert s["rate_pid"]["kp"] == list(tc.FIRMWARE_GAINS.kp)


def test_bad_input_gets_one_line_naming_it(robust, tmp_path, capsys):
    assert tc.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no policy.json" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert tc.main([robust, "--tracks", "spiral_rt", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown track 'nope'" in err and "circle_r0.5" in err and len(err.strip().splitlines()) == 1
