"""Policy export: the ONNX model and the C header compute the JAX actor (normalisation
included), the header's ttd3_step flies the run's env as the JAX actor does, a closed loop
flown by the ONNX model reproduces the run's eval.json, and bad input is refused before
anything loads."""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import experiment
from test_policy_header import fly_against_c
from tiny import tiny

from ttd3_jax.cli.evaluate import main as evaluate_main
from ttd3_jax.cli.export import main as export_main
from ttd3_jax.control import closed_loop as cl
from ttd3_jax.interop import policy as pe
from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.td3.trainer import act

ort = pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    run_dir = run(tiny(), out=str(root / "runs"), verbose=False)["run_dir"]
    assert export_main([run_dir, "--out", str(root / "policy")]) == 0
    return run_dir, str(root / "policy")


def jax_policy(run_dir):
    """The run's loaded policies and the first seed's actor as a jitted raw-obs function."""
    loaded = rundir.load_run(run_dir)
    setup = sp.trainer_for(loaded.spec).setup
    actor, stats = loaded.thetas[0][1]
    return loaded, jax.jit(lambda obs: act(setup, actor, stats, obs))


def random_obs(n=256, size=17):
    return np.random.default_rng(0).normal(0.0, 2.0, (n, size)).astype(np.float32)


def test_onnx_reproduces_the_jax_actor(exported):
    run_dir, out = exported
    _, policy = jax_policy(run_dir)
    obs = random_obs()
    sess = ort.InferenceSession(os.path.join(out, "policy.onnx"), providers=["CPUExecutionProvider"])
    got = sess.run(["action"], {"obs": obs})[0]
    want = np.asarray(policy(jnp.asarray(obs)))
    assert got.shape == (256, 4) and np.all(np.abs(got) <= 1 + 1e-6)  # onnxruntime tanh: within an ulp
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_c_header_compiles_and_reproduces_the_jax_actor(exported, tmp_path):
    run_dir, out = exported
    _, policy = jax_policy(run_dir)
    src = tmp_path / "shim.c"
    src.write_text('#include "policy.h"\nvoid shim(const float *o, float *a) { policy_forward(o, a); }\n')
    lib = tmp_path / "libpolicy.so"
    cmd = ["cc", "-std=c99", "-O2", "-Wall", "-Werror", "-shared", "-fPIC", "-I", out, str(src)]
    subprocess.run([*cmd, "-o", str(lib), "-lm"], check=True)
    shim = ctypes.CDLL(str(lib)).shim
    obs = random_obs()
    got = np.zeros((len(obs), 4), np.float32)
    for o, a in zip(obs, got, strict=True):
        shim(o.ctypes.data_as(ctypes.c_void_p), a.ctypes.data_as(ctypes.c_void_p))
    np.testing.assert_allclose(got, np.asarray(policy(jnp.asarray(obs))), atol=1e-5, rtol=0)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_c_headers_step_flies_the_runs_env_as_the_jax_actor_does(exported, tmp_path):
    """policy.h's ttd3_step, given each control step's measured state and reference points of a
    flight of the run's env (fast's observation: nothing kept), builds the env's observation
    and the JAX actor's action."""
    run_dir, out = exported
    loaded, policy = jax_policy(run_dir)
    api = json.load(open(os.path.join(out, "policy.json")))["c_api"]
    header = open(os.path.join(out, "policy.h")).read()
    assert api["state"] == [] and api["reference_points"] == {"now": 0, "ahead": 50}
    assert "\n".join(f" * {line}".rstrip() for line in api["call_order"]) in header
    fly_against_c(loaded.env_config, api, header, lambda obs: policy(jnp.asarray(obs)), tmp_path)


def test_a_closed_loop_flown_by_the_onnx_model_reproduces_eval_json(exported):
    run_dir, out = exported
    loaded, _ = jax_policy(run_dir)
    sess = ort.InferenceSession(os.path.join(out, "policy.onnx"), providers=["CPUExecutionProvider"])

    def onnx_policy(obs):
        def host(o):
            o = np.asarray(o, np.float32)
            return sess.run(["action"], {"obs": o.reshape(-1, o.shape[-1])})[0].reshape(o.shape[:-1] + (4,))

        shape = jax.ShapeDtypeStruct(obs.shape[:-1] + (4,), jnp.float32)
        return jax.pure_callback(host, shape, obs, vmap_method="broadcast_all")

    controller = cl.policy_controller(onnx_policy)
    m = jax.jit(lambda: cl.test_and_validation_metrics(loaded.env_config, controller))()
    want = json.load(open(os.path.join(run_dir, "eval.json")))["final_eval"][0]
    for k in ("spiral_tracking_error", "los_tracking_error"):
        assert float(m[k]) == pytest.approx(want[k], rel=1e-4), k


def test_a_numpy_reimplementation_from_policy_json_reproduces_eval_json(exported, capsys):
    """experiments/fly_exported.py flies policy.onnx on the committed protocol CSVs from what
    policy.json says alone (no ttd3_jax import) and gets the run's Σ‖e‖; a policy whose
    observation it does not build is refused, naming the part."""
    run_dir, out = exported
    fx = experiment("fly_exported")
    assert fx.main([out, "--tracks", "spiral_rt", "los_rt_seed00"]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[1:]}
    want = json.load(open(os.path.join(run_dir, "eval.json")))["final_eval"][0]
    for name, key in (("spiral_rt", "spiral_tracking_error"), ("los_rt_seed00", "los_tracking_error")):
        assert float(rows[name][1]) == pytest.approx(want[key], rel=1e-4), name
    meta = json.load(open(os.path.join(out, "policy.json")))
    meta["observation_spec"]["parts"].append({"name": "preview", "start": 17, "size": 3})
    assert "parts this script does not build: ['preview']" in fx.check(meta)
    assert fx.main([str(out), "--tracks", "nope"]) == 2
    assert "no such file" in capsys.readouterr().err


def test_the_sidecar_says_what_the_policy_reads_and_writes(exported):
    run_dir, out = exported
    meta = json.load(open(os.path.join(out, "policy.json")))
    cfg = rundir.load_spec(run_dir).task
    assert len(meta["observation"]) == meta["obs_size"] == TrackingEnv(cfg).observation_size == 17
    assert meta["control_hz"] == pytest.approx(1 / cfg.control_dt)
    assert meta["vehicle"]["mass"] == cfg.vehicle.quad.mass
    assert meta["source"]["run"] == os.path.basename(run_dir) and meta["source"]["epoch"] == 2
    thrust = meta["action_map"]["thrust_N"]
    assert thrust["min"] < thrust["hover"] < thrust["max"]
    obs = meta["observation_spec"]
    assert (
        obs["lookahead_physics_steps"] == cfg.observation.lookahead_k and obs["names"] == meta["observation"]
    )
    assert ("track" in obs["frame"]) == (cfg.observation.obs_frame == "track") and "qw >= 0" in obs[
        "quaternion_sign"
    ]
    assert "scalar first" in meta["conventions"]["attitude"] and "z up" in meta["conventions"]["world_frame"]
    assert "no drag" in meta["dynamics"]["velocity"]
    assert "before the first" in meta["evaluation_protocol"]["timing"]
    assert meta["rate_model"]["name"] == cfg.vehicle.quad.rate_model
    assert meta["evaluation_protocol"]["physics_steps"] == cfg.episode_steps
    assert meta["action_repeat"] == cfg.action_repeat
    assert pe.env_config(meta) == cfg  # the run's env config, rebuilt (experiments/transfer_crazyflow.py)
    assert "Threefry" in meta["test_tracks"] and "experiments/tracks/protocol" in meta["test_tracks"]
    # the Σ‖e‖ the exported (final) policy reached: eval.json's
    want = json.load(open(os.path.join(run_dir, "eval.json")))["final_eval"][0]
    got = meta["expected_tracking_error"]["sum_norm_e_m"]
    assert got["spiral_rt"] == pytest.approx(want["spiral_tracking_error"], rel=1e-6)
    assert got["los_rt_seed00"] == pytest.approx(want["los_tracking_error"], rel=1e-6)


def test_bad_input_is_refused_before_loading(exported, tmp_path, capsys):
    run_dir, out = exported
    with pytest.raises(SystemExit):
        export_main([run_dir, "--out", out])  # files there, no --force
    assert "already holds" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        export_main([run_dir, "--out", str(tmp_path / "x"), "--best", "--epoch", "1"])
    assert "exclude each other" in capsys.readouterr().err
    assert export_main([str(tmp_path), "--out", str(tmp_path / "y")]) == 2
    assert "not a ttd3_jax run directory" in capsys.readouterr().err
    assert export_main([run_dir, "--out", str(tmp_path / "z"), "--seed-index", "3"]) == 2
    assert "the run has seeds 0..0" in capsys.readouterr().err


def test_numpy_forward_matches_the_onnx_graph_without_normalisation():
    rng = np.random.default_rng(1)
    layers = [(rng.normal(size=(n, m)).astype(np.float32), rng.normal(size=m).astype(np.float32))
              for n, m in ((17, 8), (8, 4))]  # fmt: skip
    p = pe.Policy(layers, np.zeros(17, np.float32), np.ones(17, np.float32))
    sess = ort.InferenceSession(pe.onnx_model(p).SerializeToString(), providers=["CPUExecutionProvider"])
    obs = random_obs(32)
    np.testing.assert_allclose(sess.run(["action"], {"obs": obs})[0], pe.forward(p, obs), atol=1e-5)


@pytest.mark.parametrize(
    "edit, shapes",
    [
        (lambda d: d["train"].update(hidden=[16, 16]), "of shape (1, 32), but config.json gives (1, 16)"),
        (lambda d: d.update(num_seeds=2), "of shape (1, 32), but config.json gives (2, 32)"),
    ],
)
def test_a_hand_edited_config_is_named_by_evaluate_and_export_not_a_traceback(exported, tmp_path, capsys,
                                                                               edit, shapes):  # fmt: skip
    """A config.json whose sizes no longer match the run's checkpoints (hidden, num_seeds) is
    refused in one line by export and evaluate (export wrote a policy and evaluate raised a
    flax traceback or IndexError before); no older checkpoint is tried in its place."""
    run_dir = str(tmp_path / "run")
    shutil.copytree(exported[0], run_dir)
    path = os.path.join(run_dir, "config.json")
    d = json.load(open(path))
    edit(d)
    json.dump(d, open(path, "w"))
    for main, args in (
        (export_main, ["--out", str(tmp_path / "p"), "--no-onnx"]),
        (evaluate_main, ["--no-timing"]),
    ):
        assert main([run_dir, *args]) == 2
        err = capsys.readouterr().err
        assert shapes in err and "was it edited?" in err and "Traceback" not in err, err
    assert not (tmp_path / "p").exists()
