"""Brax's own PPO and SAC train the tracking env (with ttd3_jax.interop.brax_compat's shim for
jax.device_put_replicated), and the env is in Brax's registry."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import envs as brax_envs
from brax.training.agents.ppo import train as ppo
from brax.training.agents.sac import train as sac

from ttd3_jax.interop import brax_compat
from ttd3_jax.sim import env_api
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv

brax_compat.install()
# 20 control steps of 10 ms on Spiral-RT: a fixed track keeps the reset small to compile
CFG = make_config("practical", episode_steps=200, track="spiral_rt")
PPO_ARGS = dict(episode_length=CFG.episode_length, num_envs=8, batch_size=8, num_minibatches=2,
                unroll_length=5, num_updates_per_batch=1, num_eval_envs=4, seed=3)  # fmt: skip
SAC_ARGS = dict(episode_length=CFG.episode_length, num_envs=8, batch_size=32, min_replay_size=64,
                max_replay_size=1024, num_eval_envs=4, seed=3)  # fmt: skip


def finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


def changed(a, b) -> bool:
    return any(not np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def check_policy(make_policy, params):
    """The deterministic inference fn maps observations the env emits (and wild ones) to
    4-D actions in [-1, 1]."""
    env = TrackingEnv(CFG)
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 3)).obs
    obs = jnp.concatenate([obs, 100.0 * jax.random.normal(jax.random.PRNGKey(1), (2, 17))])
    fn = make_policy(params, deterministic=True)
    for o in obs:
        a, _ = fn(o, jax.random.PRNGKey(2))
        assert a.shape == (4,) and bool(jnp.all(jnp.isfinite(a)))
        assert bool(jnp.all(jnp.abs(a) <= 1.0)), a


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_ppo_trains_the_tracking_env():
    steps, seen = [], []
    make_policy, params, metrics = ppo.train(
        TrackingEnv(CFG),
        num_timesteps=640,
        num_evals=1,
        progress_fn=lambda s, m: steps.append(s),
        policy_params_fn=lambda s, mp, p: seen.append((s, p)),
        **PPO_ARGS,
    )
    assert steps[-1] >= 640 and seen[0][0] == 0, (steps, [s for s, _ in seen])
    assert finite(params) and changed(params, seen[0][1])  # trained away from the initial params
    assert np.isfinite(float(metrics["eval/episode_reward"]))
    assert float(metrics["eval/episode_tracking_error"]) > 0  # the env's metric, summed by Brax's evaluator
    check_policy(make_policy, params)


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_sac_trains_the_tracking_env():
    steps = []
    make_policy, params, metrics = sac.train(
        TrackingEnv(CFG),
        num_timesteps=512,
        num_evals=1,
        progress_fn=lambda s, m: steps.append((s, m)),
        **SAC_ARGS,
    )
    assert steps[-1][0] >= 512, [s for s, _ in steps]
    assert finite(params)
    assert np.isfinite(float(metrics["eval/episode_reward"]))
    m = steps[-1][1]
    # gradient steps were taken on transitions collected after the prefill (the metric is a mean)
    assert np.isfinite(float(m["training/critic_loss"]))
    assert float(m["training/buffer_current_size"]) > SAC_ARGS["min_replay_size"]
    check_policy(make_policy, params)


def test_install_adds_a_replicating_device_put_only_when_missing():
    assert brax_compat.install() is False  # installed at import of this file, or JAX has its own
    assert jax.device_put_replicated is not None
    x = {"a": jnp.arange(3.0), "b": 2}
    r = brax_compat.device_put_replicated(x, jax.local_devices()[:1])
    assert r["a"].shape == (1, 3) and r["b"].shape == (1,)
    np.testing.assert_array_equal(r["a"][0], x["a"])
    with pytest.raises(ValueError, match="at least one device"):
        brax_compat.device_put_replicated(x, [])


def test_device_put_replicated_shards_one_copy_per_device():
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np
        from ttd3_jax.interop.brax_compat import device_put_replicated
        devs = jax.local_devices()
        assert len(devs) == 2, devs
        r = device_put_replicated(jnp.arange(4.0), devs)
        assert r.shape == (2, 4) and {s.device for s in r.addressable_shards} == set(devs)
        for s in r.addressable_shards:
            np.testing.assert_array_equal(np.asarray(s.data)[0], np.arange(4.0))
        out = jax.pmap(lambda v: v * 2.0)(r)
        np.testing.assert_array_equal(np.asarray(out), 2.0 * np.stack([np.arange(4.0)] * 2))
        print("OK")
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "OK" in p.stdout, p.stdout + p.stderr


def test_the_envs_api_is_braxs_and_brax_compat_makes_it_a_brax_env():
    """sim.env_api (Brax's interface, imported without Brax) has the fields and abstract methods of
    Brax's, and importing brax_compat makes the tracking env a ``brax.envs.Env``, which Brax's SAC
    and ARS check for before they wrap it."""
    fields = lambda cls: [f.name for f in dataclasses.fields(cls)]
    assert fields(env_api.State) == fields(brax_envs.State)
    assert env_api.Env.__abstractmethods__ == brax_envs.Env.__abstractmethods__
    assert isinstance(TrackingEnv(CFG), brax_envs.Env)


def test_the_env_is_registered_with_brax():
    env = brax_envs.get_environment(brax_compat.ENV_NAME, preset="practical", e_max=0.5)
    assert isinstance(env, TrackingEnv) and env.config.reward.e_max == 0.5 and env.config.action_repeat == 10
    assert brax_envs.get_environment(brax_compat.ENV_NAME, config=CFG).config == CFG
    batched = brax_envs.create(
        brax_compat.ENV_NAME, episode_length=CFG.episode_length, batch_size=2, config=CFG
    )
    s = jax.jit(batched.reset)(jax.random.PRNGKey(0))  # Brax's VmapWrapper splits the key
    s = jax.jit(batched.step)(s, jnp.zeros((2, 4)))
    assert s.obs.shape == (2, 17) and s.reward.shape == (2,)
    with pytest.raises(ValueError, match="not both"):
        brax_compat.make_env("practical", config=CFG)
    with pytest.raises(ValueError, match="unknown env preset"):
        brax_compat.make_env("nope")
