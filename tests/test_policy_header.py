"""policy.h compiles for any finite weights (exact zeros, integers, subnormals, ±1e38) and
computes what numpy computes; non-finite weights are refused; the README and policy.json name
the same C function.  Its ttd3_step, fed a flight's measured states and reference points,
builds the env's observation and keeps the policy's state (memory, reference integral) step
after step, for the robust and cf2 presets and a policy for two vehicles observed in the
world frame."""

from __future__ import annotations

import ctypes
import os
import re
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.interop import c_header as ch
from ttd3_jax.interop import policy as pe
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import observation
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv

README = os.path.join(os.path.dirname(__file__), "..", "README.md")
USAGE = os.path.join(os.path.dirname(__file__), "..", "docs", "usage.md")
CC = ["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-shared", "-fPIC"]
no_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


@pytest.mark.parametrize(
    "v, want",
    [(0.0, "0.0f"), (-0.0, "-0.0f"), (1.0, "1.0f"), (-3.0, "-3.0f"), (1e38, "9.99999968e+37f"),
     (2.0**-149, "1.40129846e-45f"), (0.5, "0.5f"), (16777216.0, "16777216.0f")],
)  # fmt: skip
def test_every_weight_is_a_c_float_literal_that_reads_back_exactly(v, want):
    assert ch.c_float(v) == want
    assert np.float32(float(want[:-1])) == np.float32(v)


def test_literals_of_random_float32_read_back_exactly():
    x = np.random.default_rng(0).standard_normal(2000).astype(np.float32) * np.float32(10.0) ** np.arange(
        -37, 37, 0.037, dtype=np.float32
    )
    lits = [ch.c_float(v) for v in x]
    assert all(re.fullmatch(r"-?\d+(\.\d*)?(e[+-]\d+)?f|-?\d+e[+-]\d+f", s) and ("." in s or "e" in s)
               for s in lits)  # fmt: skip
    np.testing.assert_array_equal(np.array([float(s[:-1]) for s in lits], np.float32), x)


def awkward_policy() -> pe.Policy:
    """Weights with exact zeros, integers, subnormals and ±1e38 (biases of the tanh layer)."""
    rng = np.random.default_rng(3)
    w0 = np.round(rng.normal(size=(17, 8)) * 2).astype(np.float32)  # integers, many exact zeros
    w0[0, :3] = [2.0**-149, -(2.0**-140), 0.0]
    b0 = np.zeros(8, np.float32)
    w1 = rng.normal(size=(8, 4)).astype(np.float32)
    w1[0, 0] = 1e38
    b1 = np.array([1e38, -1e38, 0.0, 3.0], np.float32)
    return pe.Policy([(w0, b0), (w1, b1)], np.zeros(17, np.float32), np.ones(17, np.float32))


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_a_header_of_awkward_weights_compiles_and_matches_numpy(tmp_path):
    p = awkward_policy()
    (tmp_path / "policy.h").write_text(ch.c_header(p))
    src = tmp_path / "shim.c"
    src.write_text(
        '#include "policy.h"\nvoid shim(const float *o, float *a) { ttd3_policy_forward(o, a); }\n'
    )
    lib = tmp_path / "libpolicy.so"
    cmd = [*CC[:2], "-O0", *CC[3:]]
    subprocess.run([*cmd, "-I", str(tmp_path), str(src), "-o", str(lib), "-lm"], check=True)
    shim = ctypes.CDLL(str(lib)).shim
    obs = np.random.default_rng(0).normal(0.0, 0.5, (64, 17)).astype(np.float32)
    got = np.zeros((len(obs), 4), np.float32)
    for o, a in zip(obs, got, strict=True):
        shim(o.ctypes.data_as(ctypes.c_void_p), a.ctypes.data_as(ctypes.c_void_p))
    with np.errstate(over="ignore"):  # 1e38 x a weight: inf, then tanh(inf) = 1, in C too
        want = pe.forward(p, obs)
    assert np.all(np.isfinite(got)) and got[:, 0].min() == 1.0 and got[:, 1].max() == -1.0
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_weights_are_refused_and_nothing_is_written(tmp_path, bad):
    p = awkward_policy()
    p.layers[1][0][2, 1] = bad
    meta = {"source": {"run": "r", "seed": 0, "epoch": 1}}
    with pytest.raises(ValueError, match=r"ttd3_w1 holds non-finite values .*earlier --epoch or --best"):
        pe.write(str(tmp_path / "out"), p, meta, onnx=False)
    assert not (tmp_path / "out").exists()


def test_the_readme_and_policy_json_name_the_header_function():
    header = ch.c_header(awkward_policy())
    assert "static void ttd3_policy_forward(const float *obs, float *action)" in header
    readme = open(README).read()
    assert "ttd3_policy_forward(const float *obs, float *action)" in readme
    assert "#define policy_forward ttd3_policy_forward" in header and "TTD3_NO_SHORT_NAMES" in readme
    # the step of a policy that keeps state: its call order opens the header and is in policy.json
    cfg = sp.preset("robust").task
    api = pe.c_api(cfg)
    header = ch.c_header(tracking_policy(cfg), "", None, api)
    assert "\n".join(f" * {line}".rstrip() for line in api["call_order"]) in header
    call = "ttd3_step(&s, p, v, q, omega, ref, action);"
    assert call in header and call in open(USAGE).read() and "ttd3_reset(&state)" in readme
    assert "static inline void ttd3_step(ttd3_state *s, const float p[3]" in header


# -- ttd3_step against the env ------------------------------------------------------------------

SHIM = """#include "policy.h"
static ttd3_state a, b; /* a: ttd3_step; b: the three calls it makes, to read the observation */
void reset(void) {
  ttd3_reset(&a);
  ttd3_reset(&b);
#ifdef VEHICLE
  a.vehicle = b.vehicle = VEHICLE;
#endif
}
void step(const float *p, const float *v, const float *q, const float *w, const float *ref, float *obs,
          float *action, float *action_b) {
  ttd3_step(&a, p, v, q, w, ref, action);
  ttd3_observe(&b, p, v, q, w, ref, obs);
  ttd3_policy_forward(obs, action_b);
  ttd3_remember(&b, action_b);
}
"""


def compiled(tmp_path, header: str, vehicle: str | None = None):
    """``(reset, step)`` of :data:`SHIM` on ``header``, compiled with every warning an error."""
    (tmp_path / "policy.h").write_text(header)
    (tmp_path / "shim.c").write_text(SHIM)
    lib = tmp_path / "libshim.so"
    define = [f"-DVEHICLE=TTD3_VEHICLE_{vehicle.upper()}"] if vehicle else []
    subprocess.run([*CC, *define, "-I", str(tmp_path), str(tmp_path / "shim.c"), "-o", str(lib), "-lm"],
                   check=True)  # fmt: skip
    shim = ctypes.CDLL(str(lib))
    return shim.reset, shim.step


class Measured(TrackingEnv):
    """The env, keeping what its last observation measured (noise and bias included) and omega,
    for the caller to read in the same trace."""

    def _measured(self, ps):
        p, v, q, ps = super()._measured(ps)
        self.measured = (p, v, q, ps.quad.w)
        return p, v, q, ps


def fly_against_c(cfg, api: dict, header: str, policy, tmp_path, steps=300, vehicle=None, seed=0):
    """Fly ``steps`` control steps of ``TrackingEnv(cfg)`` with ``policy`` (raw obs -> action) and
    check at each that policy.h's ``ttd3_step``, given that step's measured state and reference
    points, builds the env's observation and the policy's action (so its state updates as the
    env's do); q reaches it with either sign. Returns the env's last state."""
    env = Measured(cfg)
    offsets = list(api["reference_points"].values())

    def seen(state):  # the state, what it measured, and the reference points p_d(k + n)
        ps = state.pipeline_state
        refs = jnp.stack([tr.position(ps.track, ps.k + n, cfg.dt) for n in offsets])
        return state, (*env.measured, refs)

    reset, step = jax.jit(lambda key: seen(env.reset(key))), jax.jit(lambda s, a: seen(env.step(s, a)))
    on_host = lambda state, seen: (state, [np.asarray(x, np.float32) for x in seen])  # noqa: E731
    c_reset, c_step = compiled(tmp_path, header, vehicle)
    ptr = lambda x: None if x is None else x.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
    c_reset()
    state, (p, v, q, w, refs) = on_host(*reset(jax.random.PRNGKey(seed)))
    for i in range(steps):
        obs = np.asarray(state.obs, np.float32)
        action = np.asarray(policy(obs), np.float32)
        got, a, a_b = np.zeros_like(obs), np.zeros(4, np.float32), np.zeros(4, np.float32)
        q_in = -q if i % 2 and api["canonical_q"] else q  # the same attitude, qw < 0 half the time
        w_in = w if "omega" in api["parts"] else None  # unread: NULL will do
        c_step(*map(ptr, (p, v, q_in, w_in, refs, got, a, a_b)))
        np.testing.assert_allclose(got, obs, rtol=1e-5, atol=1e-5, err_msg=f"observation at step {i}")
        np.testing.assert_allclose(a, action, rtol=0, atol=1e-5, err_msg=f"action at step {i}")
        np.testing.assert_array_equal(a, a_b)
        state, (p, v, q, w, refs) = on_host(*step(state, jnp.asarray(action)))
    return state


def tracking_policy(cfg, seed=0) -> pe.Policy:
    """A policy that flies near the track (so that the reference integral integrates): a PD law on
    p_ahead_error and the velocity error (the reference's from the first preview point; plus
    error_integral) through the attitude to body rates,
    as an actor of ReLU pairs (tanh(K obs)) that reads every entry, the last action most, with a
    random normalisation folded in."""
    lay, quad, amap = observation.layout(cfg), cfg.vehicle.quad, pe.action_map(cfg)
    thrust = amap["thrust_N"]
    per_a0 = (thrust["max"] - thrust["hover"]) / (quad.mass if quad.thrust_units == "newton" else 1.0)
    rate, g, att = amap["body_rates_rad_s"]["max"][0], quad.gravity, 8.0  # att: 1/s
    t = cfg.observation.preview_s[0]  # the reference's velocity: its first preview point / t
    e, v, q, ahead = (lay.slice(n).start for n in ("p_ahead_error", "v", "q", observation.preview_name(t)))
    acc = np.zeros((3, lay.size))  # the desired acceleration (m/s^2) from the observation
    for i in range(3):
        acc[i, e + i], acc[i, v + i], acc[i, ahead + i] = 4.0, -3.0, 3.0 / t
        if lay.has("error_integral"):
            acc[i, lay.slice("error_integral").start + i] = 1.0
    k = np.zeros((4, lay.size))  # small angles: acceleration = g (2 qy, -2 qx), dq/dt = omega / 2
    k[0] = acc[2] / per_a0
    k[1] = 2 * att * -acc[1] / (2 * g) / rate
    k[2] = 2 * att * acc[0] / (2 * g) / rate
    for i in (1, 2, 3):
        k[i, q + i] -= 2 * att / rate
    rng = np.random.default_rng(seed)
    k += rng.normal(0.0, 1e-3, k.shape)  # every entry read (ttd3_step's observation is checked by its action)
    if lay.has("last_action"):
        k[:, lay.slice("last_action")] += 0.1 * np.eye(4)
    mean, std = rng.normal(0.0, 0.1, lay.size), rng.uniform(1.0, 3.0, lay.size)
    w = k * std  # on (obs - mean) / std
    layers = [(np.concatenate([w, -w]).T, np.concatenate([k @ mean, -(k @ mean)])),
              (np.concatenate([np.eye(4), -np.eye(4)]), np.zeros(4))]  # fmt: skip
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return pe.Policy([(f32(w), f32(b)) for w, b in layers], f32(mean), f32(std))


TWO = ("paper", "crazyflie")
STATEFUL = {  # memory, preview and reference integral (robust, cf2: omega); and for two vehicles, the
    # world frame, the error to p_d,k+1, q as integrated, a reference integral at its limit
    "robust": lambda: sp.preset("robust").task,
    "cf2": lambda: sp.preset("cf2").task,
    "cf2_history": lambda: sp.preset("cf2").task.replace(action_history_s=(0.05, 0.2)),
    "two_vehicles_world": lambda: make_config(
        "practical", hover_centered_thrust=True, vehicles=TWO, obs_memory=True, preview_s=(0.2,),
        obs_frame="world", err_ref="next", canonical_q_obs=False, ref_integral_gain=3.0,
        ref_integral_band=0.05, ref_integral_limit=1e-4),
}  # fmt: skip


@no_cc
@pytest.mark.parametrize("name", list(STATEFUL))
def test_ttd3_step_builds_the_envs_observation_and_keeps_its_state_step_after_step(tmp_path, name):
    cfg = STATEFUL[name]()
    vehicles = pe.vehicles_spec(cfg)
    flown = vm.pin_vehicle(cfg, TWO[1]) if vehicles else cfg  # the vehicle the C shim names
    api = pe.c_api(flown)
    policy = tracking_policy(flown)
    header = ch.c_header(policy, "test", vehicles, api)
    history = ["action_history"] if cfg.observation.action_history_s else []
    assert api["state"] == ["last_action", "error_integral", "ref_int", *history]
    assert ("omega" in api["parts"]) == name.startswith("cf2") and "float ref_int[3];" in header
    state = fly_against_c(flown, api, header, lambda o: pe.forward(policy, o), tmp_path,
                          vehicle=TWO[1] if vehicles else None)  # fmt: skip
    ps = state.pipeline_state
    assert np.all(np.asarray(ps.err_int) != 0) and np.all(np.isfinite(np.asarray(ps.quad.p)))
    if history:  # it kept the history (the observation and the action checked it at every step)
        size = 4 * len(cfg.observation.action_history_s)
        assert f"float action_history[{size}];" in header and np.all(np.asarray(ps.act_hist) != 0)
    o, ref_int = cfg.observation, np.asarray(ps.ref_int)
    assert np.any(ref_int != 0)  # it integrated within the band; the last config's shift at its limit
    assert np.any(o.ref_integral_gain * np.abs(ref_int) > o.ref_integral_limit) == (
        name == "two_vehicles_world"
    )
    e = np.linalg.norm(np.asarray(ps.quad.p) - np.asarray(tr.position(ps.track, ps.k, cfg.dt)))
    assert e < 1.0, e  # near the track


def test_a_part_the_header_cannot_build_is_refused_by_name():
    with pytest.raises(
        ValueError, match=r"policy.h cannot build the observation part 'wind': only the critics"
    ):
        pe.c_api(make_config("practical", obs_privileged=True))
    api = pe.c_api(make_config("practical", err_ref="next", lookahead_k=1, obs_frame="world"))
    assert api["reference_points"] == {"ahead": 1} and api["error_reference"] == "ahead"
