"""Vehicle presets (``ttd3_jax.sim.vehicles``): the Crazyflie's numbers, its hover
equilibrium in both action maps, the geometric controller on Spiral-RT with it, ``--vehicle``
on both CLIs (and its refusals), and the vehicle's round trip through ``config.json``."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.cli import train
from ttd3_jax.cli.evaluate import build_parser, check_run_vehicle, classical_env
from ttd3_jax.cli.evaluate import main as evaluate_main
from ttd3_jax.control.closed_loop import closed_loop, metrics
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import vehicles as vh
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.dynamics import QuadParams, QuadState, rk4_step
from ttd3_jax.sim.env import TrackingEnv, action_to_control, hover_action


def test_presets_paper_is_the_default_and_crazyflie_has_its_sources():
    assert vh.vehicle("paper") == QuadParams() == make_config("paper").vehicle.quad
    cf = vh.vehicle("crazyflie")
    assert cf.mass == 0.027 and cf.thrust_max == pytest.approx(4 * 0.1302)
    assert cf.inertia == (1.029e-5, 1.105e-5, 2.005e-5)
    assert cf.rate_max == pytest.approx(np.deg2rad(720.0)) and cf.rate_min == -cf.rate_max
    assert 1.8 <= vh.thrust_to_weight(cf) <= 2.2
    assert vh.VEHICLE_NAMES == tuple(vh.VEHICLES) == ("paper", "crazyflie", "cf2")
    assert {k for k in vh.CRAZYFLIE_SOURCES} >= {"mass", "thrust_max", "inertia", "tau_rate", "torque_max"}
    assert vh.vehicle_of(cf) == "crazyflie" and vh.vehicle_of(cf.replace(mass=0.03)) is None


def test_cf2_is_the_identified_crazyflie_with_its_firmware_loop():
    cf2 = vh.vehicle("cf2")
    assert cf2.rate_model == "firmware" and cf2.loop is not None
    assert cf2.mass == 0.0328 and cf2.thrust_max == pytest.approx(4 * 0.12)
    assert vh.thrust_to_weight(cf2) == pytest.approx(1.49, abs=0.01)  # crazyflow's identified vehicle
    assert vh.MIXABLE_NAMES == ("paper", "crazyflie")  # a firmware loop has nothing to blend with
    assert {"mass", "inertia", "loop.kp/ki/kd/i_limit/torque_limit", "loop.tau_up/tau_down"} <= set(
        vh.CF2_SOURCES
    )


def test_unknown_vehicle_and_a_pinned_thrust_map_are_refused():
    with pytest.raises(ValueError, match=r"unknown vehicle 'x500'; allowed: \('paper', 'crazyflie', 'cf2'\)"):
        vh.vehicle("x500")
    with pytest.raises(ValueError, match="thrust_map_mass=1.5 pins another vehicle"):
        vh.with_vehicle(make_config("paper", thrust_map_mass=1.5), "crazyflie")


def _fly(cfg, a: jax.Array, steps: int = 1000) -> QuadState:
    """The vehicle after ``steps`` physics steps from rest at the origin under action ``a``."""
    u = action_to_control(cfg, a)

    def step(x, _):
        return rk4_step(cfg.vehicle.quad, x, u, cfg.dt), None

    return jax.lax.scan(step, QuadState.hover(), None, length=steps)[0]


@pytest.mark.parametrize("centred", [False, True])
def test_crazyflie_hover_action_keeps_it_still_for_one_second(centred):
    cfg = vh.with_vehicle(make_config("paper", hover_centered_thrust=centred), "crazyflie")
    a = hover_action(cfg)
    x = _fly(cfg, a)
    assert float(jnp.max(jnp.abs(x.p))) < 1e-4 and float(jnp.max(jnp.abs(x.v))) < 1e-4
    # and the test can fail: 1 % more of the thrust range climbs by centimetres in that second
    up = _fly(cfg, a.at[0].add(0.02))
    assert float(up.p[2]) > 0.02


def test_geometric_controller_tracks_spiral_rt_on_the_crazyflie():
    cfg = vh.with_vehicle(make_config("paper"), "crazyflie").for_eval("spiral_rt")
    env = TrackingEnv(cfg)
    ctrl = geometric_controller(cfg)

    @jax.jit
    def run(key):
        r = closed_loop(env, ctrl, env.reset(key))
        return r, metrics(env, r)

    r, m = run(jax.random.PRNGKey(0))
    assert not bool(m["crashed"])
    assert float(m["max_error"]) < 0.1, float(m["max_error"])  # m
    # it flew the Crazyflie: the commanded thrust stays near its 0.26 N hover, inside 0-0.52 N
    thrust = np.asarray(action_to_control(cfg, r.action)[..., 0])
    assert 0.15 < float(np.median(thrust)) < 0.4 and thrust.max() <= cfg.vehicle.quad.thrust_max + 1e-6


def _code(fn, argv) -> int:
    try:
        return fn(argv)
    except SystemExit as e:  # argparse and tyro exit 2 themselves
        return e.code


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--vehicle", "x500"], r"--vehicle must be one of \('paper', 'crazyflie', 'cf2'\), got 'x500'"),
        (["--preset", "mujoco", "--vehicle", "crazyflie"], "env 'hopper' has none"),
        (["--resume", "/nonexistent/run", "--vehicle", "crazyflie"], "remove --vehicle"),
    ],
)
def test_train_refuses_bad_vehicle_flags(argv, message, capsys):
    assert _code(train.main, argv) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err


def test_train_vehicle_round_trips_through_config_json(tmp_path):
    known, spec = train.parse(["--vehicle", "crazyflie", "--task.vehicle.quad.rate-model", "torque"])
    assert spec.task.vehicle.quad == vh.CRAZYFLIE.replace(rate_model="torque")  # --task.vehicle.quad.* on top
    assert spec.task.vehicle.hover_centered_thrust  # the fast preset's other task fields are kept
    back = rundir.load_spec(rundir.new_run_dir(str(tmp_path), spec))
    assert back == spec and back.task.vehicle.quad.inertia == vh.CRAZYFLIE.inertia
    _, plain = train.parse(["--vehicle", "crazyflie"])
    assert (
        vh.vehicle_of(rundir.load_spec(rundir.new_run_dir(str(tmp_path), plain)).task.vehicle.quad)
        == "crazyflie"
    )


def test_evaluate_vehicle_with_run_dir_only_if_it_is_the_runs_own(tmp_path, capsys):
    run_dir = rundir.new_run_dir(str(tmp_path), sp.preset("fast"))  # a paper-vehicle run
    assert _code(evaluate_main, [run_dir, "--vehicle", "crazyflie"]) == 2
    assert "--vehicle crazyflie does not match RUN_DIR's vehicle (paper)" in capsys.readouterr().err
    assert _code(evaluate_main, ["--controller", "geometric", "--vehicle", "x500"]) == 2
    assert "invalid choice: 'x500'" in capsys.readouterr().err
    # the run's own vehicle is accepted (checked before anything loads or compiles)
    ap = build_parser()
    args = ap.parse_args([run_dir, "--vehicle", "paper"])
    args.task_args = []
    check_run_vehicle(ap, args)


def test_evaluate_classical_env_flies_the_vehicle_with_task_flags_on_top():
    cfg = classical_env("practical", ["--task.vehicle.quad.mass", "0.03"], "crazyflie")
    assert cfg.vehicle.quad == vh.CRAZYFLIE.replace(mass=0.03) and cfg.action_repeat == 10
    assert classical_env("paper", [], "crazyflie").replace(quad=QuadParams()) == make_config("paper")
