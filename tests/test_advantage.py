"""Deep advantage updating (Tallec, Blier, Ollivier 2019; ``TrainConfig.advantage_dt``): the
critics Q = V(s) + δ (Ā(s, a) − Ā(s, π(s))), their loss, the actor's objective, the
hyperparameters at the env's step, and that a run trains."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.tiny import tiny
from ttd3_jax import spec as sp
from ttd3_jax.td3 import buffer as rb
from ttd3_jax.td3.config import Hyper, TrainConfig
from ttd3_jax.td3.dpg import step_hyper
from ttd3_jax.td3.losses import advantage_actor_loss, advantage_critic_loss, critic_loss
from ttd3_jax.td3.networks import AdvantageCritic, init_params, make_networks, twin_adv, twin_q_adv, twin_v
from ttd3_jax.td3.trainer import seed_keys

OBS, ACT = 5, 2


def _nets(dt=0.01):
    nets = make_networks(ACT, (16, 16), advantage_dt=dt)
    actor, critic = init_params(nets, jax.random.PRNGKey(0), OBS, ACT)
    return nets, actor, critic


def _batch(n=32, terminated=None):
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    z = jnp.zeros(n)
    return rb.Transition(
        obs=jax.random.normal(k[0], (n, OBS)), action=jax.random.uniform(k[1], (n, ACT), minval=-1, maxval=1),
        reward=jax.random.normal(k[2], (n,)), next_obs=jax.random.normal(k[0], (n, OBS)) + 1.0,
        terminated=z if terminated is None else terminated, done=z,
    )  # fmt: skip


def test_the_policy_action_has_advantage_zero_so_q_is_v_there():
    nets, actor, critic = _nets()
    assert isinstance(nets.critic, AdvantageCritic) and nets.dt == 0.01
    b = _batch()
    pi = nets.actor.apply(actor, b.obs)
    q_pi = twin_q_adv(nets, critic, None, b.obs, pi, pi)
    np.testing.assert_array_equal(q_pi, twin_v(nets, critic, None, b.obs))  # exactly, both critics
    q = twin_q_adv(nets, critic, None, b.obs, b.action, pi)
    adv = twin_adv(nets, critic, None, b.obs, b.action) - twin_adv(nets, critic, None, b.obs, pi)
    np.testing.assert_allclose(q, twin_v(nets, critic, None, b.obs) + 0.01 * adv, rtol=1e-6, atol=1e-7)
    assert float(jnp.max(jnp.abs(adv))) > 1e-3  # the actions' advantages are not all 0
    assert not np.allclose(q[0], q[1])  # two critics


def test_the_critic_loss_is_the_td_error_per_second_with_a_v_target():
    """Σ_i mean ((r + γ (1 − terminated) min_i V'_i(s') − Q_i(s, a)) / δ)²: a terminated row
    drops its bootstrap; no target action enters."""
    nets, actor, critic = _nets(dt=0.02)
    hp = Hyper(gamma=0.9)
    b = _batch(terminated=(jnp.arange(32) % 2).astype(jnp.float32))
    loss, q_mean = advantage_critic_loss(critic, nets=nets, actor=actor, target_critic=critic, stats=None,
                                         batch=b, hp=hp)  # fmt: skip
    y = b.reward + 0.9 * (1 - b.terminated) * jnp.min(twin_v(nets, critic, None, b.next_obs), axis=0)
    q = twin_q_adv(nets, critic, None, b.obs, b.action, nets.actor.apply(actor, b.obs))
    assert float(loss) == pytest.approx(float(jnp.sum(jnp.mean(((q - y) / 0.02) ** 2, -1))), rel=1e-5)
    assert float(q_mean) == pytest.approx(float(jnp.mean(q[0])), rel=1e-5)


def test_the_actor_follows_dq_da_over_delta():
    """The gradient of −mean Ā_1(s, π(s)) is that of −mean Q_1(s, π(s)) / δ with the
    normalising action held fixed: the paper's ∂Q₁/∂a direction, δ-free in size."""
    nets, actor, critic = _nets(dt=0.005)
    obs = _batch().obs
    g = jax.grad(advantage_actor_loss)(actor, nets=nets, critic=critic, stats=None, obs=obs)
    pi0 = jax.lax.stop_gradient(nets.actor.apply(actor, obs))

    def q_over_dt(p):
        q = twin_q_adv(nets, critic, None, obs, nets.actor.apply(p, obs), pi0)
        return -jnp.mean(q[0]) / 0.005

    want = jax.grad(q_over_dt)(actor)
    for a, w in zip(jax.tree.leaves(g), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, w, rtol=2e-3, atol=1e-6)
    assert max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(g)) > 1e-4


def test_hyperparameters_keep_their_meaning_per_second_at_a_smaller_step():
    hp = Hyper(gamma=0.99, lr_actor=3e-4, lr_critic=1e-3, tau=0.005)
    c = TrainConfig(num_envs=4, total_transitions=4096, warmup_transitions=256, buffer_size=1024,
                    epochs=2, advantage_dt=0.01)  # fmt: skip

    class S:
        config = c

        def __init__(self, dt):
            self.nets = make_networks(ACT, (8,), advantage_dt=dt)

    same = step_hyper(S(0.01), hp)
    for f in ("gamma", "lr_actor", "lr_critic", "tau"):
        assert float(getattr(same, f)) == pytest.approx(getattr(hp, f), rel=1e-6)
    fine = step_hyper(S(0.001), hp)
    assert float(fine.gamma) ** 10 == pytest.approx(0.99, rel=1e-6)  # 10 steps of 1 ms: one of 10 ms
    assert (float(fine.lr_actor), float(fine.lr_critic)) == pytest.approx((3e-5, 1e-4), rel=1e-6)
    assert (1 - float(fine.tau)) ** 10 == pytest.approx(0.995, rel=1e-6)
    assert float(fine.sigma) == hp.sigma and float(fine.reward_scale) == hp.reward_scale


def test_one_epoch_with_advantage_and_n_step_trains_and_stays_finite():
    s = tiny(advantage_dt=0.01, n_step=3)
    s = sp.replace(s, task=dataclasses.replace(s.task, action_repeat=1))
    t = sp.trainer_for(s)
    assert t.nets.dt == pytest.approx(s.task.control_dt) and s.task.control_dt == pytest.approx(1e-3)
    ts = jax.jit(t.init)(seed_keys(0, 1)[0], s.hp)
    ts, m = jax.jit(t.epoch)(ts, s.hp)
    assert all(np.isfinite(float(m[k])) for k in ("critic_loss", "actor_loss", "q_mean"))
    assert set(ts.critic["params"]) == {"v_net", "a_net"}


def test_a_q_critic_and_the_model_based_actor_refuse_what_they_cannot_do():
    with pytest.raises(ValueError, match=r"advantage_dt must be a finite number in \[0, 10\], got -0.01"):
        TrainConfig(advantage_dt=-0.01)
    with pytest.raises(ValueError, match="advantage_dt must be 0 with model_horizon > 0"):
        TrainConfig(advantage_dt=0.01, model_horizon=5)
    nets = make_networks(ACT, (16, 16))
    actor, critic = init_params(nets, jax.random.PRNGKey(0), OBS, ACT)
    kw = dict(nets=nets, target_actor=actor, target_critic=critic, stats=None, batch=_batch())
    loss = critic_loss(critic, **kw, key=jax.random.PRNGKey(0), hp=Hyper(), target_std=0.2)[0]
    assert np.isfinite(float(loss)) and nets.dt == 0.0
