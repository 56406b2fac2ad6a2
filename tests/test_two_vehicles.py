"""One policy for two vehicles (``randomization.vehicles``, ``sim.vehicle_mix``): the draw between
the ``paper`` and ``crazyflie`` vehicles, the shared action map and the observed descriptor, the
checks of the field, evaluation on a named vehicle, and the exported constants of each vehicle."""

from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_evaluate import fake_run_dir
from tiny import tiny

from ttd3_jax.cli.evaluate import main as evaluate_main
from ttd3_jax.cli.export import main as export_main
from ttd3_jax.interop import policy as pe
from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv, action_to_control
from ttd3_jax.sim.vehicles import CRAZYFLIE, VEHICLES
from ttd3_jax.td3.trainer import act

BOTH = ("paper", "crazyflie")
CF_RATE = math.radians(720.0)  # rad/s, 12.57


def two(**kw):
    """The practical env, hover-centred, flying the vehicles between paper and crazyflie."""
    return make_config("practical", hover_centered_thrust=True, vehicles=BOTH, **kw)


def arrays(quad):
    return rz.vehicle_arrays(quad, jnp.float32)


def test_the_draw_gives_the_two_vehicles_at_its_ends_and_the_geometric_mean_between():
    paper, cf = (vm.flown_as(n, VEHICLES["paper"]) for n in BOTH)
    for s, want in ((0.0, paper), (1.0, cf)):
        got = vm.interpolate(paper, cf, jnp.float32(s))
        assert jax.tree.map(lambda x, y: bool(x == y), got, arrays(want)) == jax.tree.map(lambda _: True, got)
    mid = vm.interpolate(paper, cf, jnp.float32(0.25))
    assert float(mid.mass) == pytest.approx(1.5 * (0.027 / 1.5) ** 0.25, rel=1e-6)
    assert float(mid.thrust_max) == pytest.approx(20.0 * (CRAZYFLIE.thrust_max / 20.0) ** 0.25, rel=1e-6)
    assert (
        float(mid.rate_min) == -float(mid.rate_max) == pytest.approx(-6.0 * (CF_RATE / 6.0) ** 0.25, rel=1e-6)
    )
    assert float(mid.thrust_min) == 0.0 and float(mid.gravity) == pytest.approx(9.81)
    # each reset draws its nominal vehicle between the two; the unknown factors apply around it
    cfg = two(mass=(0.8, 1.2))
    plants = jax.vmap(lambda k: rz.draw(cfg, k))(jax.random.split(jax.random.PRNGKey(0), 64))
    m = np.asarray(plants.nominal.mass)
    assert m.min() >= 0.027 - 1e-7 and m.max() <= 1.5 + 1e-6 and len(np.unique(m)) == 64
    ratio = np.asarray(plants.quad.mass) / m
    assert ratio.min() >= 0.8 - 1e-6 and ratio.max() <= 1.2 + 1e-6 and ratio.std() > 0
    s = np.log(m / 1.5) / np.log(0.027 / 1.5)  # every field at the same s
    np.testing.assert_allclose(np.asarray(plants.nominal.rate_max), 6.0 * (CF_RATE / 6.0) ** s, rtol=1e-5)


def test_the_action_map_is_the_nominal_vehicles_own():
    cfg, cf = two(), arrays(CRAZYFLIE)
    u = np.asarray(action_to_control(cfg, jnp.array([[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, -1.0, 1.0]]), cf))
    assert u[0, 0] == pytest.approx(0.027 * 9.81, rel=1e-6) and np.all(u[0, 1:] == 0.0)
    np.testing.assert_allclose(u[1], [CRAZYFLIE.thrust_max, CF_RATE, -CF_RATE, CF_RATE], rtol=1e-6)
    # in the env: a = 0 holds every drawn vehicle in hover (no wind, level start)
    env = TrackingEnv(two(wind_sigma=0.0, randomize_init=False, track="spiral_rt"))

    def hover(key):
        s = jax.lax.fori_loop(0, 3, lambda _, s: env.step(s, jnp.zeros(4)), env.reset(key))
        return s.pipeline_state.quad.v[2], s.pipeline_state.plant.nominal.mass

    vz, mass = jax.jit(jax.vmap(hover))(jax.random.split(jax.random.PRNGKey(0), 8))
    assert np.abs(np.asarray(vz)).max() < 1e-5 and np.ptp(np.asarray(mass)) > 0.1


def test_the_actor_observes_the_known_vehicle():
    assert not TrackingEnv(make_config("practical", hover_centered_thrust=True)).layout.has("vehicle")
    env = TrackingEnv(two(mass=(0.9, 1.1)))
    part = env.layout.slice("vehicle")
    assert env.layout.describe()[-1]["name"] == "vehicle" and part.stop == env.actor_observation_size
    s = env.reset(jax.random.PRNGKey(3))
    np.testing.assert_array_equal(s.obs[part], vm.descriptor(s.pipeline_state.plant.nominal))
    cf = TrackingEnv(vm.pin_vehicle(two(), "crazyflie").for_eval("spiral_rt")).reset(jax.random.PRNGKey(0))
    tw = CRAZYFLIE.thrust_max / (0.027 * 9.81)
    np.testing.assert_allclose(
        cf.obs[part], [tw - 1, math.log(CF_RATE / 6.0), math.log(0.072 / 0.03)], rtol=1e-6
    )
    paper = TrackingEnv(two().for_eval("spiral_rt")).reset(jax.random.PRNGKey(0))  # the first vehicle
    np.testing.assert_allclose(paper.obs[part], [20.0 / (1.5 * 9.81) - 1, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(vehicles=("paper",)), r"EnvConfig.randomization.vehicles must be \(\) or two names of"),
        (dict(vehicles=("paper", "crazyflie", "paper")), "EnvConfig.randomization.vehicles must be"),
        (dict(vehicles=("paper", "bumblebee")), r"EnvConfig.randomization.vehicles must be .*'crazyflie'"),
        (dict(vehicles=BOTH), "EnvConfig.randomization.vehicles .* needs vehicle.hover_centered_thrust true"),
        (
            dict(vehicles=BOTH, hover_centered_thrust=True, thrust_map_mass=1.5),
            "needs vehicle.thrust_map_mass None",
        ),
        (
            dict(vehicles=BOTH, hover_centered_thrust=True, mass=(1.0, 2.0)),
            "must let every drawn vehicle hover",
        ),
    ],
)
def test_bad_vehicles_are_refused_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match) as e:
        make_config("practical", **kw)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="vehicle must be one of EnvConfig.randomization.vehicles"):
        vm.pin_vehicle(
            make_config("practical", hover_centered_thrust=True, vehicles=("paper", "paper")), "crazyflie"
        )


@pytest.fixture(scope="module")
def two_vehicle_run(tmp_path_factory):
    """A run directory of a ``tiny`` spec with ``vehicles`` (``fake_run_dir``: config.json and
    an epoch-2 checkpoint of freshly initialised networks, unit-ish observation statistics)."""
    base = tiny()
    s = sp.replace(base, task=base.task.replace(vehicles=BOTH))
    path = fake_run_dir(tmp_path_factory.mktemp("two") / "run", s, obs_var=0.25)
    with open(os.path.join(path, "metrics.csv"), "w") as fh:
        fh.write("epoch,seed\n")  # no epoch evaluated
    return path


def evaluation(run_dir, tmp_path, *flags):
    out = str(tmp_path / f"eval{'_'.join(flags)}.json")
    assert evaluate_main([run_dir, "--track", "spiral_rt", "--no-timing", "--json", out, *flags]) == 0
    with open(out) as fh:
        return json.load(fh)


def test_a_two_vehicle_run_is_evaluated_on_either_vehicle(two_vehicle_run, tmp_path, capsys):
    cf, paper = (evaluation(two_vehicle_run, tmp_path, "--vehicle", v) for v in ("crazyflie", "paper"))
    assert (
        cf["vehicle"] == "crazyflie" and paper["vehicle"] == "paper" and cf["trained_vehicles"] == list(BOTH)
    )
    assert cf["env_config"]["vehicle"]["quad"]["mass"] == 0.027
    assert cf["env_config"]["randomization"]["vehicles"] == ["crazyflie", "crazyflie"]
    e = [r["results"]["seed 0"]["spiral_rt"]["tracking_error"] for r in (cf, paper)]
    assert e[0] != e[1] and all(map(math.isfinite, e))
    assert "vehicle crazyflie of the vehicles paper to crazyflie" in capsys.readouterr().out


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_c_header_flies_both_vehicles_from_the_same_weights(two_vehicle_run, tmp_path):
    out = str(tmp_path / "policy")
    assert export_main([two_vehicle_run, "--out", out, "--no-onnx"]) == 0
    with open(os.path.join(out, "policy.json")) as fh:
        meta = json.load(fh)
    assert meta["evaluated_on"] == list(BOTH) and meta["trained_under"]["randomization"]["vehicles"] == list(
        BOTH
    )
    v = meta["vehicles"]
    assert set(v["per_vehicle"]) == set(BOTH) and meta["observation"][v["descriptor_start"]].startswith(
        "vehicle."
    )
    src = tmp_path / "shim.c"
    src.write_text(
        '#include "policy.h"\nvoid shim(const float *o, float *a, float *u, int cf) {\n'
        "  float x[TTD3_OBS_SIZE]; int i;\n"
        "  const float *v = cf ? TTD3_VEHICLE_CRAZYFLIE : TTD3_VEHICLE_PAPER;\n"
        "  for (i = 0; i < TTD3_OBS_SIZE; ++i) x[i] = o[i];\n"
        "  ttd3_set_vehicle(x, v);\n  ttd3_policy_forward(x, a);\n  ttd3_action_to_control(v, a, u);\n}\n"
    )
    lib = tmp_path / "libpolicy.so"
    cmd = ["cc", "-std=c99", "-O2", "-Wall", "-Werror", "-shared", "-fPIC", "-I", out, str(src)]
    subprocess.run([*cmd, "-o", str(lib), "-lm"], check=True)
    shim = ctypes.CDLL(str(lib)).shim
    loaded = rundir.load_run(two_vehicle_run)
    setup = sp.trainer_for(loaded.spec).setup
    actor, stats = loaded.thetas[0][1]
    policy = pe.from_params(actor, stats, len(meta["observation"]))
    ptr = lambda x: x.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
    actions = {}
    for i, name in enumerate(BOTH):
        cfg = vm.pin_vehicle(loaded.env_config, name).for_eval("spiral_rt")
        env = TrackingEnv(cfg)
        obs = np.asarray(env.reset(jax.random.PRNGKey(0)).obs, np.float32)  # the descriptor of ``name``
        blank = obs.copy()
        blank[env.layout.slice("vehicle")] = 0.0  # the C shim writes it from TTD3_VEHICLE_<NAME>
        a, u = np.zeros(4, np.float32), np.zeros(4, np.float32)
        shim(ptr(blank), ptr(a), ptr(u), i)
        want = np.asarray(act(setup, actor, stats, jnp.asarray(obs)))
        np.testing.assert_allclose(a, want, atol=1e-5, rtol=0)
        np.testing.assert_allclose(pe.forward(policy, obs), want, atol=1e-5, rtol=0)
        np.testing.assert_allclose(
            u, np.asarray(action_to_control(cfg, jnp.asarray(want))), rtol=1e-5, atol=1e-6
        )
        actions[name] = a
    assert not np.allclose(actions["paper"], actions["crazyflie"])  # the descriptor matters
