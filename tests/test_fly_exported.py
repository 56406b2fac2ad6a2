"""experiments/fly_exported.py's observation (``observe``, ``Memory``), which
experiments/transfer_crazyflow.py reuses: from policy.json alone it rebuilds every part the env
emits (memory, preview, reference integral, body rates included) along a flown trajectory, and
it refuses a part it does not build, naming it.  No policy and no crazyflow needed."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from experiment_scripts import experiment

from ttd3_jax.interop import policy as pe
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv

fx = experiment("fly_exported")


def sidecar(cfg, size: int) -> dict:
    """The parts of policy.json that the observation reads."""
    return dict(
        observation_spec=pe.observation_spec(cfg, size),
        obs_size=size,
        evaluation_protocol=pe.PROTOCOL,
        rate_model=dict(name=cfg.vehicle.quad.rate_model),
    )


def test_every_part_is_rebuilt_from_policy_json_along_a_flight():
    """A first_order vehicle (the omega part) with the robust preset's memory, preview and
    reference integral and an action history, flown with random actions: the NumPy observation
    of each visited state (and the memory kept by ``Memory``) equals the env's to float32
    rounding."""
    cfg = make_config("practical", hover_centered_thrust=True, obs_memory=True, preview_s=(0.1, 0.5, 1.0),
                      ref_integral_gain=3.0, ref_integral_band=0.2, action_history_s=(0.05, 0.2),
                      ).for_eval("spiral_rt")  # fmt: skip
    cfg = cfg.replace(quad=cfg.vehicle.quad.replace(rate_model="first_order"))
    env = TrackingEnv(cfg)
    meta = sidecar(cfg, env.observation_size)
    parts = {p["name"] for p in meta["observation_spec"]["parts"]}
    assert parts >= {"omega", "last_action", "preview_1s", "action_history"}
    assert fx.check_observation(meta) is None
    state = env.reset(jax.random.PRNGKey(0))  # Spiral-RT, from rest on its first point
    ref = np.asarray(jax.vmap(lambda k: tr.position(state.pipeline_state.track, k, cfg.dt))(jnp.arange(5000)))
    step = jax.jit(env.step)
    actions = 0.2 * np.random.default_rng(0).normal(size=(40, 4)).astype(np.float32)
    memory, worst = fx.Memory(meta), 0.0
    for i, a in enumerate(actions):
        ps = state.pipeline_state
        quad, k = jax.device_get(ps.quad), int(ps.k)
        if i:
            memory.update(actions[i - 1], quad.p, ref[k])
        x = np.concatenate([quad.p, quad.v, quad.q, quad.w]).astype(np.float32)
        got = fx.observe(meta, x, ref, k, memory)
        worst = max(worst, float(np.max(np.abs(got - np.asarray(state.obs)))))
        state = step(state, jnp.asarray(a))
    assert np.abs(memory.shift()).max() > 0  # the reference integral was exercised
    assert worst < 1e-5, worst


def test_a_part_it_does_not_build_is_refused_by_name():
    cfg = make_config("practical", obs_memory=True)
    meta = sidecar(cfg, TrackingEnv(cfg).observation_size)
    assert fx.check_observation(meta) is None and fx.check(meta) is None
    meta["observation_spec"]["parts"].append({"name": "vehicle", "start": 24, "size": 3})
    meta["obs_size"] += 3
    assert "parts this script does not build: ['vehicle']" in fx.check_observation(meta)
    meta["rate_model"] = {"name": "torque"}
    meta["observation_spec"]["parts"].pop()
    meta["obs_size"] -= 3
    assert "rate model 'torque'" in fx.check(meta) and fx.check_observation(meta) is None
