"""The trainer's parts: config errors, noise schedules, replay buffer, networks, losses, and
the pure training functions (one transition's path, seed vmap, sweeps, model-based actor)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny import tiny

from ttd3_jax.run import spec as sp
from ttd3_jax.td3 import buffer as rb
from ttd3_jax.td3 import core, dpg, model_based, networks
from ttd3_jax.td3 import noise as nz
from ttd3_jax.td3 import trainer as T
from ttd3_jax.td3.config import Hyper, NoiseConfig, TrainConfig, validate_hyper
from ttd3_jax.td3.core import critic_loss
from ttd3_jax.td3.dpg import actor_loss
from ttd3_jax.td3.networks import init_params, make_networks, twin_q

# --------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(batch_size=2048, buffer_size=1024), "batch_size"),
        (dict(num_envs=0), "num_envs must be an integer in"),
        (dict(epochs=-1), "epochs"),
        (dict(algo="sac"), "algo"),
        (dict(total_transitions=100), "total_transitions"),
        (dict(total_transitions=10**15), r"total_transitions must be an integer in \[1, 2,000,000,000\]"),
        (dict(warmup_transitions=10), "warmup_transitions"),
        (dict(target_noise="shared"), "target_noise"),
        (dict(model_horizon=-1), "model_horizon"),
        (dict(model_horizon=50), "total_transitions"),
        (dict(updates_per_step=0), r"updates_per_step must be .* \(0 needs model_horizon"),
        (dict(hidden=(32, 0)), "hidden"),
        (dict(normalize_obs="yes"), "normalize_obs"),
        (dict(num_envs=16.0), "num_envs must be an integer"),
    ],
)
def test_train_config_errors_are_raised_at_construction(kw, match):
    with pytest.raises(ValueError, match=match):
        tiny(**kw)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("beta", 1.5, r"hp.beta must be a finite number in \[0, 1\]"),
        ("gamma", 1.0, r"hp.gamma must be a finite number in \[0, 1\)"),
        ("lr_critic", 0.0, "hp.lr_critic"),
        ("lam", math.inf, "hp.lam must be a finite number"),
        ("tau", math.nan, "hp.tau"),
        ("sigma", -0.1, "hp.sigma"),
        ("model_grad_clip", "big", "hp.model_grad_clip must be a finite number.*'big'"),
    ],
)
def test_hyperparameter_errors(field, value, match):
    with pytest.raises(ValueError, match=match):
        validate_hyper(Hyper(**{field: value}))
    with pytest.raises(ValueError, match=match):  # and the run spec checks its own
        tiny(hp=Hyper(**{field: value}))


@pytest.mark.parametrize("field, value", [("delta_reduce", "max"), ("t_unit", "hour"), ("r_range", "all")])
def test_noise_config_errors(field, value):
    with pytest.raises(ValueError, match=field):
        NoiseConfig(**{field: value})


def test_loop_lengths_and_transitions_run():
    c = TrainConfig(num_envs=16, total_transitions=16 * 40, warmup_transitions=100, batch_size=64, epochs=3)
    assert c.warmup_steps == 7  # ceil(100 / 16)
    assert c.steps_per_epoch == (40 - 7) // 3 == 11
    assert c.transitions_run == (7 + 11 * 3) * 16
    assert dataclasses.replace(c, buffer_size=1000).buffer_capacity == 1008  # a multiple of num_envs
    assert dataclasses.replace(c, model_horizon=4, total_transitions=16 * 100).env_steps_per_step == 4


# --------------------------------------------------------------------------- noise


def _sigma_after(ns, rewards, cfg=None, hp=None, *, time_attenuating=True, n_tr=30_000, n_upd=7,
                 episode_length=3000) -> nz.NoiseState:  # fmt: skip
    """``noise.update`` on one minibatch of ``rewards`` (default config and ``Hyper``; 30k
    transitions, 7 updates, 3000-step episodes: t = 10 episodes)."""
    cfg, hp = NoiseConfig() if cfg is None else cfg, Hyper() if hp is None else hp
    return nz.update(ns, cfg=cfg, time_attenuating=time_attenuating, hp=hp, rewards=jnp.asarray(rewards),
                     n_tr=n_tr, n_upd=n_upd, episode_length=episode_length)  # fmt: skip


def test_time_attenuating_sigma_matches_formula():
    hp = Hyper(beta=0.08, lam=0.01, u_max=1.0)
    cfg = NoiseConfig()
    r = jnp.array([-1.0, -0.5, -0.25, 0.0])
    ns = nz.init(hp, True)
    assert float(ns.sigma) == 1.0  # Alg. 1 starts at u_max
    delta = float(np.sum((r - r.min()) / (r.max() - r.min())))  # 0 + 0.5 + 0.75 + 1
    expected = 0.08 * np.exp(-0.01 * 10.0) + 0.92 * np.exp(-delta)
    np.testing.assert_allclose(float(_sigma_after(ns, r, cfg, hp).sigma), expected, rtol=1e-6)
    mean = _sigma_after(ns, r, dataclasses.replace(cfg, delta_reduce="mean"), hp)
    np.testing.assert_allclose(float(mean.sigma), 0.08 * np.exp(-0.1) + 0.92 * np.exp(-delta / 4), rtol=1e-6)
    per_step = _sigma_after(ns, r, dataclasses.replace(cfg, t_unit="env_step"), hp)
    np.testing.assert_allclose(float(per_step.sigma), 0.92 * np.exp(-delta), rtol=1e-5)
    per_update = _sigma_after(ns, r, dataclasses.replace(cfg, t_unit="update"), hp)
    np.testing.assert_allclose(
        float(per_update.sigma), 0.08 * np.exp(-0.07) + 0.92 * np.exp(-delta), rtol=1e-6
    )


def test_sigma_kept_when_rewards_are_flat_and_running_range():
    cfg = NoiseConfig()
    ns = nz.NoiseState(sigma=jnp.float32(0.3), r_min=jnp.float32(jnp.inf), r_max=jnp.float32(-jnp.inf))
    assert float(_sigma_after(ns, jnp.full(8, -2.0), cfg, n_tr=1000, n_upd=1).sigma) == pytest.approx(0.3)
    run_cfg = dataclasses.replace(cfg, r_range="running")
    s1 = _sigma_after(ns, [-4.0, 0.0], run_cfg, n_tr=0, n_upd=1)
    s2 = _sigma_after(s1, [-1.0, -1.0], run_cfg, n_tr=0, n_upd=2)
    assert float(s2.r_min) == -4.0 and float(s2.r_max) == 0.0
    # a flat batch is still normalised by the running range: δ = 2 * 0.75
    np.testing.assert_allclose(float(s2.sigma), 0.08 + 0.92 * np.exp(-1.5), rtol=1e-6)


def test_td3_keeps_sigma_constant_and_sigma_as_variance():
    hp = Hyper(sigma=0.1)
    ns = nz.init(hp, False)
    assert float(ns.sigma) == pytest.approx(0.1)
    kept = _sigma_after(
        ns, jnp.arange(4.0), hp=hp, time_attenuating=False, n_tr=10, n_upd=1, episode_length=10
    )
    assert float(kept.sigma) == pytest.approx(0.1)
    assert float(nz.std(NoiseConfig(sigma_is_variance=True), jnp.float32(0.04))) == pytest.approx(0.2)
    assert TrainConfig(algo="td3").time_attenuating is False and TrainConfig().time_attenuating


# --------------------------------------------------------------------------- buffer, networks, losses


def test_ring_buffer_insert_wraps_and_samples_filled_rows():
    buf = rb.init(8, obs_size=2, action_size=1)

    def batch(v):
        n = 4
        return rb.Transition(
            obs=jnp.full((n, 2), v), action=jnp.full((n, 1), v), reward=jnp.arange(n) + v,
            next_obs=jnp.full((n, 2), v), terminated=jnp.zeros(n), done=jnp.zeros(n),
        )  # fmt: skip

    buf = rb.insert(buf, batch(0.0))
    assert int(buf.size) == 4 and int(buf.pos) == 4
    s = rb.sample(buf, jax.random.PRNGKey(0), 256)
    assert set(np.unique(np.asarray(s.reward))) <= {0.0, 1.0, 2.0, 3.0}
    buf = rb.insert(rb.insert(buf, batch(10.0)), batch(20.0))  # wraps: overwrites rows 0-3
    assert int(buf.size) == 8 and int(buf.pos) == 4
    np.testing.assert_array_equal(buf.data.reward, [20, 21, 22, 23, 10, 11, 12, 13])
    assert rb.transition_bytes(17, 4) == 4 * (2 * 17 + 4 + 3)


def _two_env_buffer(done, terminated, rows: int, capacity: int = 16):
    """A buffer of 2 envs: row r holds env r % 2's step r // 2, reward r, obs r, next_obs r + 0.5."""
    buf = rb.init(capacity, 1, 1)
    r = jnp.arange(rows, dtype=jnp.float32)
    for i in range(0, rows, 2):
        sl = slice(i, i + 2)
        tr = rb.Transition(obs=r[sl, None], action=r[sl, None], reward=r[sl], next_obs=r[sl, None] + 0.5,
                           terminated=terminated[sl], done=done[sl])  # fmt: skip
        buf = rb.insert(buf, tr)
    return buf


def test_n_step_returns_follow_one_env_and_stop_at_episode_ends_and_the_newest_row():
    """n = 3 over 2 envs: from row i the same env's rows i + 2, i + 4 follow.  The return stops
    after a step that ended its episode (truncation bootstraps from its next_obs, termination
    does not), and at the newest row written."""
    g = 0.5
    done = jnp.zeros(10).at[4].set(1.0).at[7].set(1.0)  # env 0 ends at row 4 (truncated), env 1 at 7
    term = jnp.zeros(10).at[7].set(1.0)  # row 7: a crash
    buf = _two_env_buffer(done, term, rows=10)
    draw = jax.jit(lambda k: rb.sample_n_step(buf, k, 6, n=3, num_envs=2, gamma=g))
    batch, disc, r1 = draw(jax.random.PRNGKey(0))
    # rows the sample drew
    drawn = np.asarray(batch.obs[:, 0]).astype(int)
    want = {0: (0 + g * 2 + g * g * 4, 4.5, 0.0, 3),  # ends at row 4 (truncated): bootstraps from 4.5
            1: (1 + g * 3 + g * g * 5, 5.5, 0.0, 3),
            3: (3 + g * 5 + g * g * 7, 7.5, 1.0, 3),  # row 7 terminated
            6: (6 + g * 8, 8.5, 0.0, 2),  # row 10 is not written yet
            7: (7.0, 7.5, 1.0, 1), 4: (4.0, 4.5, 0.0, 1), 2: (2 + g * 4, 4.5, 0.0, 2),
            5: (5 + g * 7, 7.5, 1.0, 2), 8: (8.0, 8.5, 0.0, 1), 9: (9.0, 9.5, 0.0, 1)}  # fmt: skip
    assert len(set(drawn)) > 3
    for i, row in enumerate(drawn):
        ret, nxt, terminated, m = want[int(row)]
        assert float(batch.reward[i]) == pytest.approx(ret), row
        assert float(batch.next_obs[i, 0]) == nxt and float(batch.terminated[i]) == terminated, row
        assert float(disc[i]) == pytest.approx(g**m) and float(r1[i]) == row, row


def test_n_step_returns_wrap_around_the_ring_and_start_at_the_oldest_row():
    """A full ring: the oldest row (at pos) has every later row after it; the newest has none."""
    done = jnp.zeros(20)
    buf = _two_env_buffer(done, jnp.zeros(20), rows=20, capacity=16)  # rows 16-19 overwrote 0-3
    assert int(buf.pos) == 4 and int(buf.size) == 16
    draw = jax.jit(lambda k: rb.sample_n_step(buf, k, 64, n=3, num_envs=2, gamma=0.5))
    batch, disc, _ = draw(jax.random.PRNGKey(1))
    for i in range(64):
        first = float(batch.obs[i, 0])  # the step number written in that row
        m = round(float(np.log(float(disc[i])) / np.log(0.5)))
        assert m == min(3, (19 - first) // 2 + 1), first  # the newest step is 19 (env 1), 18 (env 0)
        assert float(batch.next_obs[i, 0]) == first + 2 * (m - 1) + 0.5


def test_twin_critics_are_one_vmapped_apply_equal_to_two_separate_ones():
    nets = make_networks(4, (16, 16))
    _, critic = init_params(nets, jax.random.PRNGKey(0), 17, 4)
    obs, act = jax.random.normal(jax.random.PRNGKey(1), (8, 17)), jnp.zeros((8, 4))
    q = twin_q(nets, critic, None, obs, act)
    assert q.shape == (2, 8)
    for i in range(2):
        p = jax.tree.map(lambda x, i=i: x[i], critic)
        np.testing.assert_allclose(
            q[i], nets.critic.apply(p, jnp.concatenate([obs, act], -1))[..., 0], rtol=1e-5, atol=1e-6
        )
    assert not np.allclose(q[0], q[1])  # two independently initialised critics


def _batch(n=32, terminated=None):
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    z = jnp.zeros(n)
    return rb.Transition(
        obs=jax.random.normal(k[0], (n, 17)), action=jax.random.uniform(k[1], (n, 4), minval=-1, maxval=1),
        reward=jax.random.normal(k[2], (n,)), next_obs=jax.random.normal(k[0], (n, 17)) + 1.0,
        terminated=z if terminated is None else terminated, done=z,
    )  # fmt: skip


def _loss(critic, nets, actor, b, key, hp, target_std):
    kw = dict(nets=nets, target_actor=actor, target_critic=critic, stats=None, batch=b, key=key, hp=hp)
    return critic_loss(critic, **kw, target_std=target_std)


def _target(nets, actor, critic, b, hp, a_next):
    q_next = jnp.min(twin_q(nets, critic, None, b.next_obs, a_next), axis=0)
    return b.reward + hp.gamma * (1 - b.terminated) * q_next


def test_critic_target_is_the_td3_formula_and_stops_at_termination():
    """y = r + γ (1 − terminated) min_i Q'_i(s', clip(π'(s') + clip(σ̃ξ, −c, c), −1, 1)): with
    σ̃ = 0 the loss equals Σ_i mean (y − Q_i)² computed by hand, and a terminated row drops
    its bootstrap."""
    nets = make_networks(4, (16, 16))
    actor, critic = init_params(nets, jax.random.PRNGKey(0), 17, 4)
    hp, key = Hyper(gamma=0.9), jax.random.PRNGKey(2)
    b = _batch(terminated=(jnp.arange(32) % 2).astype(jnp.float32))
    loss, q_mean = _loss(critic, nets, actor, b, key, hp, 0.0)
    y = _target(nets, actor, critic, b, hp, jnp.clip(nets.actor.apply(actor, b.next_obs), -1, 1))
    q = twin_q(nets, critic, None, b.obs, b.action)
    assert float(loss) == pytest.approx(float(jnp.sum(jnp.mean((q - y) ** 2, -1))), rel=1e-5)
    assert float(q_mean) == pytest.approx(float(jnp.mean(q[0])), rel=1e-5)
    a_loss = actor_loss(actor, nets=nets, critic=critic, stats=None, obs=b.obs)
    pi = nets.actor.apply(actor, b.obs)
    assert float(a_loss) == pytest.approx(
        -float(jnp.mean(twin_q(nets, critic, None, b.obs, pi)[0])), rel=1e-5
    )


@pytest.mark.parametrize("clip", [0.05, 0.5])
def test_target_policy_noise_is_clipped_to_plus_minus_c(clip):
    """A huge σ̃ saturates the target noise at ±c (its sign is the Gaussian draw's): the loss
    equals the one computed with a_next = clip(π'(s') ± c, −1, 1), and not the unclipped one."""
    nets = make_networks(4, (16, 16))
    actor, critic = init_params(nets, jax.random.PRNGKey(0), 17, 4)
    hp, key, b = Hyper(gamma=0.9, target_clip=clip), jax.random.PRNGKey(2), _batch()
    loss, _ = _loss(critic, nets, actor, b, key, hp, 1e6)
    pi_next = nets.actor.apply(actor, b.next_obs)
    sign = jnp.sign(jax.random.normal(key, pi_next.shape))
    q = twin_q(nets, critic, None, b.obs, b.action)
    for a_next, equal in ((pi_next + clip * sign, True), (pi_next + 2 * clip * sign, False)):
        want = jnp.sum(jnp.mean((q - _target(nets, actor, critic, b, hp, jnp.clip(a_next, -1, 1))) ** 2, -1))
        assert (float(loss) == pytest.approx(float(want), rel=1e-5)) == equal


def test_running_obs_stats_match_numpy():
    x = np.random.default_rng(0).normal(3.0, 2.0, size=(300, 5)).astype(np.float32)
    s = networks.init_obs_stats(5)
    for chunk in np.split(x, [7, 100, 101, 250]):
        s = networks.update_obs_stats(s, jnp.asarray(chunk))
    np.testing.assert_allclose(s.mean, x.mean(0), rtol=1e-4)
    np.testing.assert_allclose(networks.obs_std(s), x.std(0), rtol=1e-3)
    z = networks.normalize(s, jnp.asarray(x))
    np.testing.assert_allclose(np.mean(np.asarray(z), 0), 0.0, atol=1e-3)
    assert np.array_equal(networks.normalize(None, x), x)


# --------------------------------------------------------------------------- trainer


def test_transitions_store_true_next_obs_and_terminated_apart_from_truncation():
    s = tiny(warmup_transitions=16 * 150, total_transitions=16 * 200, buffer_size=16 * 256)
    c, t = s.train, sp.trainer_for(s)
    ts = jax.jit(t.init)(T.seed_keys(0, 1)[0], s.hp)
    d = jax.device_get(ts.buffer.data)
    n = int(ts.buffer.size)
    assert n == c.warmup_steps * c.num_envs
    # within one env's consecutive rows, next_obs of step i is obs of step i+1 unless it ended
    obs = d.obs[:n].reshape(-1, c.num_envs, d.obs.shape[-1])
    nxt = d.next_obs[:n].reshape(obs.shape)
    term = d.terminated[:n].reshape(obs.shape[:2])
    same = np.all(np.isclose(nxt[:-1], obs[1:]), axis=-1)
    assert np.all(same | (term[:-1] > 0))
    assert np.any(term > 0)  # random actions crash some episodes: stored as terminated
    assert set(np.unique(term)) <= {0.0, 1.0}


@pytest.mark.slow  # .ci/run runs it (-m slow)
@pytest.mark.parametrize("horizon", [0, 4])
def test_vmapped_seed_equals_seed_run_alone(horizon):
    both, alone = tiny(num_seeds=2, seed=3, model_horizon=horizon), tiny(seed=4, model_horizon=horizon)
    tb, ta = sp.trainer_for(both), sp.trainer_for(alone)
    ts_b = jax.jit(jax.vmap(tb.init, in_axes=(0, None)))(T.seed_keys(3, 2), both.hp)
    ts_a = jax.jit(jax.vmap(ta.init, in_axes=(0, None)))(T.seed_keys(4, 1), alone.hp)
    for x, y in zip(jax.tree.leaves(ts_b.actor), jax.tree.leaves(ts_a.actor), strict=True):
        np.testing.assert_array_equal(x[1], y[0])
    assert any(not np.allclose(x[0], x[1]) for x in jax.tree.leaves(ts_b.actor))  # seeds differ
    _, mb = jax.jit(jax.vmap(tb.epoch, in_axes=(0, None)))(ts_b, both.hp)
    _, ma = jax.jit(jax.vmap(ta.epoch, in_axes=(0, None)))(ts_a, alone.hp)
    for k in ("critic_loss", "actor_loss", "q_mean", "sigma", "env_steps"):
        np.testing.assert_allclose(mb[k][1], ma[k][0], rtol=1e-4, atol=1e-6, err_msg=k)


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_sweep_over_hyperparameters_is_one_vmapped_program():
    s = tiny(epochs=1)
    t = sp.trainer_for(s)
    hps = Hyper(lr_critic=jnp.array([1e-4, 1e-3]), beta=jnp.array([0.05, 0.2]))
    none = {f.name: None for f in dataclasses.fields(Hyper)}
    hp_axes = Hyper(**{**none, "lr_critic": 0, "beta": 0})  # sweep two leaves, share the rest
    keys = jnp.stack([T.seed_keys(0, 1)[0]] * 2)
    ts, m, ev = jax.jit(jax.vmap(t.train, in_axes=(0, hp_axes)))(keys, hps)
    assert m["critic_loss"].shape == (2, 1)
    assert not np.allclose(m["critic_loss"][0], m["critic_loss"][1])
    assert ev["spiral_tracking_error"].shape == (2, 1)
    # each swept learning rate reached its critic optimiser
    np.testing.assert_allclose(ts.critic_opt.hyperparams["learning_rate"], [1e-4, 1e-3], rtol=1e-6)


@pytest.fixture(scope="module")
def tiny_trainer():
    """The ``tiny`` run's trainer and its state after warm-up (one init compile, shared)."""
    s = tiny()
    t = sp.trainer_for(s)
    return s, t, jax.jit(t.init)(T.seed_keys(0, 1)[0], s.hp)


def test_normalised_run_stores_stats_and_evaluates(tiny_trainer):
    s, t, ts = tiny_trainer
    c = s.train
    n0 = float(ts.obs_stats.count)
    assert c.normalize_obs and n0 == (c.warmup_steps + 1) * c.num_envs
    ts, m = jax.jit(t.epoch)(ts, s.hp)
    assert float(ts.obs_stats.count) == n0 + c.steps_per_epoch * c.num_envs
    assert np.isfinite(float(jax.jit(t.evaluate)(ts)["spiral_tracking_error"]))


# --------------------------------------------------------------------------- model-based actor


@pytest.fixture(scope="module")
def model_trainer():
    """A tiny model-based trainer (H = 3) and its state after warm-up, shared by the tests
    below (one init compile)."""
    s = tiny(model_horizon=3, epochs=1, total_transitions=16 * (8 + 3 * 6))
    t = sp.trainer_for(s)
    return s, t, jax.jit(t.init)(T.seed_keys(0, 1)[0], s.hp)


def test_model_rollout_stores_its_transitions_in_env_order(model_trainer):
    """With ``model_horizon`` H each vector step adds H·num_envs transitions; row r + num_envs
    is still env r's next step (next_obs of one row is the obs of that row unless it ended)."""
    s, t, ts0 = model_trainer
    c = s.train
    ts, m = jax.jit(t.epoch)(ts0, s.hp)
    added = c.steps_per_epoch * c.model_horizon * c.num_envs
    assert c.steps_per_epoch == 6 and int(ts.n_tr) == int(ts0.n_tr) + added
    assert float(m["env_steps"]) == int(ts0.n_tr) + added
    d, n = jax.device_get(ts.buffer.data), int(ts.buffer.size)
    assert n == int(ts.n_tr)
    obs = d.obs[:n].reshape(-1, c.num_envs, d.obs.shape[-1])
    nxt, done = d.next_obs[:n].reshape(obs.shape), d.done[:n].reshape(obs.shape[:2])
    same = np.all(np.isclose(nxt[:-1], obs[1:]), axis=-1)
    assert np.all(same | (done[:-1] > 0))
    assert np.isfinite(float(m["actor_loss"]))


def test_without_critics_the_warmup_is_the_first_rollouts_and_sigma_follows_the_rollouts():
    """G = 0 (the ``fast`` preset): no buffer, init collects nothing, the first
    ``warmup_rollouts`` rollouts act at random and leave the actor and its Adam state alone,
    the later ones move it; the critics and targets never move, and their metrics are nan.
    σ after a rollout is T-TD3's formula on the rollout's rewards, with t the transitions
    collected."""
    s = tiny(
        updates_per_step=0, model_horizon=3, epochs=1, total_transitions=16 * 3 * 6, warmup_transitions=100
    )
    c, t = s.train, sp.trainer_for(s)
    assert c.warmup_in_rollouts and c.warmup_steps == 0 and c.warmup_rollouts == 3  # ceil(100 / 48)
    ts0 = jax.jit(t.init)(T.seed_keys(0, 1)[0], s.hp)
    assert ts0.buffer.capacity == 0 and int(ts0.n_tr) == 0
    step = jax.jit(lambda ts: model_based.vector_step(t.setup, s.hp, ts))
    states, ts = [ts0], ts0
    for _ in range(c.warmup_rollouts + 1):
        ts, (m, _) = step(ts)
        states.append(ts)
    for before, after in zip(states[:-2], states[1:-1], strict=True):  # the warm-up's rollouts
        assert not changed(after.actor, before.actor) and not changed(after.actor_opt, before.actor_opt)
    assert changed(states[-1].actor, states[-2].actor)  # the first that learns
    assert int(ts.n_tr) == (c.warmup_rollouts + 1) * c.model_horizon * c.num_envs and int(ts.n_upd) == 0
    assert not changed(ts.critic, ts0.critic) and not changed(ts.target_actor, ts0.target_actor)
    assert np.isnan(float(m.critic_loss)) and np.isfinite(float(m.actor_loss))

    update = jax.jit(lambda ts: model_based.model_actor_update(t.setup, ts, s.hp, jax.random.PRNGKey(1)))
    ts1, _, _, rewards = update(ts)
    hp, r = s.hp, np.asarray(rewards)
    assert r.shape == (c.model_horizon * c.num_envs,)
    delta = np.sum((r - r.min()) / (r.max() - r.min()))
    t_ep = int(ts1.n_tr) / t.env.episode_length
    want = hp.beta * hp.u_max * np.exp(-hp.lam * t_ep) + (1 - hp.beta) * hp.u_max * np.exp(-delta)
    got = jax.jit(lambda ts: core.update_sigma(t.setup, ts, hp, rewards))(ts1).noise.sigma
    assert float(got) == pytest.approx(want, rel=1e-5)


def test_the_actor_learning_rate_falls_linearly_over_the_run():
    """``hp.lr_decay``: the actor's lr is ``lr_actor`` at the start, ``lr_actor (1 - decay)``
    at the run's last transition; 0 leaves it constant."""
    s = tiny(model_horizon=3, epochs=1, total_transitions=16 * (8 + 3 * 6))
    setup, n = sp.trainer_for(s).setup, s.train.transitions_run
    ts = jax.jit(sp.trainer_for(s).init)(T.seed_keys(0, 1)[0], s.hp)
    for decay, frac, want in ((0.0, 1.0, 1.0), (1.0, 0.0, 1.0), (1.0, 0.5, 0.5), (0.5, 1.0, 0.5)):
        hp = s.hp.replace(lr_actor=0.01, lr_decay=decay)
        lr = core.actor_lr(setup, ts.replace(n_tr=jnp.asarray(int(frac * n), jnp.int32)), hp)
        assert float(lr) == pytest.approx(0.01 * want, rel=1e-6)


def test_model_actor_loss_is_the_rollout_return_and_its_gradient_matches_finite_differences(model_trainer):
    """The model-based actor objective equals −mean Σ γ^k r_k of the same rollout stepped
    by hand (no exploration noise), and its gradient along a random direction matches a
    central difference."""
    s, t, ts = model_trainer
    hp = s.hp
    ts = ts.replace(noise=ts.noise.replace(sigma=jnp.zeros_like(ts.noise.sigma)))
    key = jax.random.PRNGKey(7)
    value_grad = jax.jit(jax.value_and_grad(lambda a: model_based.model_loss(a, t.setup, ts, hp, key)[0]))
    loss, g = value_grad(ts.actor)
    st, ret, alive = ts.env_state, jnp.zeros(s.train.num_envs), jnp.ones(s.train.num_envs)
    step = jax.jit(jax.vmap(t.env.env.step))
    for k in range(s.train.model_horizon):
        st = step(st, T.act(t.setup, ts.actor, ts.obs_stats, st.obs))
        ret = ret + alive * hp.gamma**k * hp.reward_scale * st.reward
        alive = alive * (1.0 - st.done)
    assert float(jnp.sum(alive)) == s.train.num_envs  # no episode ends this early
    assert float(loss) == pytest.approx(-float(jnp.mean(ret)), rel=1e-5)

    leaves, tree = jax.tree.flatten(ts.actor)
    ks = jax.random.split(jax.random.PRNGKey(3), len(leaves))
    d = jax.tree.unflatten(tree, [jax.random.normal(k, x.shape) for k, x in zip(ks, leaves, strict=True)])
    eps = 1e-3
    shift = lambda e: jax.tree.map(lambda x, y: x + e * y, ts.actor, d)  # noqa: E731
    fd = (float(value_grad(shift(eps))[0]) - float(value_grad(shift(-eps))[0])) / (2 * eps)
    an = sum(float(jnp.sum(x * y)) for x, y in zip(jax.tree.leaves(g), jax.tree.leaves(d), strict=True))
    assert an == pytest.approx(fd, rel=0.03), (an, fd)
    assert abs(an) > 1e-4  # a real gradient, not zero


def changed(a, b) -> bool:
    return any(not np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


@pytest.mark.parametrize("j, actor_moves", [(0, False), (1, True)])
def test_the_paper_update_moves_the_actor_and_targets_every_policy_delay_updates(
    tiny_trainer, j, actor_moves
):
    """With policy_delay d = 2 and G = 2, update j = 0 moves the critics and σ only; j = 1 also
    takes the ∂Q/∂a step (a finite actor loss) and moves the target networks."""
    s, t, ts = tiny_trainer
    assert s.train.policy_delay == 2 and s.train.updates_per_step == 2
    x = (jax.random.PRNGKey(5), j)
    out, (c_loss, a_loss, _) = jax.jit(lambda ts: dpg.update(t.setup, s.hp, ts, x))(ts)
    assert changed(out.critic, ts.critic) and np.isfinite(float(c_loss))
    assert changed(out.actor, ts.actor) == actor_moves == changed(out.target_critic, ts.target_critic)
    assert np.isfinite(float(a_loss)) == actor_moves
    assert int(out.n_upd) == int(ts.n_upd) + 1 and float(out.noise.sigma) < 1.0  # σ moved from u_max


def test_the_model_based_update_never_moves_the_actor(model_trainer):
    """The model-based path's critic updates leave the actor alone (it learns from the
    rollout); every d-th one moves the targets."""
    s, t, ts = model_trainer
    for j in (0, 1):
        x = (jax.random.PRNGKey(5), j)
        out, _ = jax.jit(lambda ts, x=x: model_based.update(t.setup, s.hp, ts, x))(ts)
        assert not changed(out.actor, ts.actor) and changed(out.critic, ts.critic)
        assert changed(out.target_critic, ts.target_critic) == (j == 1)


def test_the_model_based_update_needs_an_env_that_gradients_flow_through():
    """The one check of the rule, where the trainer is made: any env, named in its field."""
    s = tiny(model_horizon=2)
    rigid = sp.env_spec(s)._replace(differentiable=False)
    with pytest.raises(ValueError, match=r"model_horizon must be 0 for this env: .*, got 2"):
        T.make_trainer(s.train, rigid)
    assert T.make_trainer(dataclasses.replace(s.train, model_horizon=0), rigid).setup.env is rigid
