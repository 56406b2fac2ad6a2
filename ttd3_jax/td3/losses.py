"""TD3 losses (Fujimoto et al. 2018; spec §2.4).

Critic: y = r + γ (1 − terminated) min_i Q'_i(s', clip(π'(s') + clip(σ̃ ξ, −c, c), −1, 1))
(with n-step returns, r is Σ_{k<m} γ^k r_k and γ is γ^m),
loss Σ_i mean (y − Q_i(s, a))².  Actor: −mean Q_1(s, π(s)).  Observations arrive raw; the
networks normalise them (:func:`~ttd3_jax.td3.networks.normalize`).

Deep advantage updating (Tallec et al. 2019; ``advantage_dt`` > 0, not in the paper): the
critics are Q_i = V_i(s) + δ (Ā_i(s, a) − Ā_i(s, π(s))), the target y = r + γ (1 − terminated)
min_i V'_i(s') (the next state's advantage is 0 under π), the loss Σ_i mean ((y − Q_i) / δ)²
(the TD error per second, O(1) whatever δ), and the actor follows −mean Ā_1(s, π(s)), whose
gradient is ∂Q_1/∂a / δ: the paper's direction.  γ, the learning rates and τ arrive already
scaled to δ (:func:`~ttd3_jax.td3.dpg.step_hyper`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax.td3.buffer import Transition
from ttd3_jax.td3.config import Hyper
from ttd3_jax.td3.networks import Networks, ObsStats, policy, twin_adv, twin_q, twin_q_adv, twin_v


def critic_loss(
    critic,
    *,
    nets: Networks,
    target_actor,
    target_critic,
    stats: ObsStats | None,
    batch: Transition,
    key: jax.Array,
    hp: Hyper,
    target_std,
    discount: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Twin-critic TD loss and mean Q_1 over the batch; ``target_std`` is σ̃ (or the shared
    σ under ``target_noise="shared_sigma"``), its noise clipped to ±``hp.target_clip``;
    ``discount`` (B,) replaces γ for n-step returns (γ^m of each row's m steps)."""
    disc = (hp.gamma if discount is None else discount) * (1.0 - batch.terminated)
    pi_next = policy(nets, target_actor, stats, batch.next_obs)
    eps = jnp.clip(target_std * jax.random.normal(key, pi_next.shape), -hp.target_clip, hp.target_clip)
    a_next = jnp.clip(pi_next + eps, -1.0, 1.0)
    q_next = jnp.min(twin_q(nets, target_critic, stats, batch.next_obs, a_next), axis=0)
    y = jax.lax.stop_gradient(batch.reward + disc * q_next)
    q = twin_q(nets, critic, stats, batch.obs, batch.action)
    return jnp.sum(jnp.mean((q - y) ** 2, axis=-1)), jnp.mean(q[0])


def actor_loss(actor, *, nets: Networks, critic, stats: ObsStats | None, obs: jax.Array) -> jax.Array:
    """Deterministic policy gradient objective through the first critic: −mean Q_1(s, π(s))."""
    a = policy(nets, actor, stats, obs)
    return -jnp.mean(twin_q(nets, jax.tree.map(lambda p: p[:1], critic), stats, obs, a)[0])


def advantage_critic_loss(critic, *, nets: Networks, actor, target_critic, stats: ObsStats | None,
                          batch: Transition, hp: Hyper,
                          discount: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """Deep advantage updating's twin loss Σ_i mean ((y − Q_i(s, a)) / δ)² with
    y = r + γ (1 − terminated) min_i V'_i(s'), and mean Q_1 (= V_1 at π(s)); ``actor`` (the
    current policy) gives the action whose advantage is 0; ``discount`` as in :func:`critic_loss`."""
    disc = (hp.gamma if discount is None else discount) * (1.0 - batch.terminated)
    v_next = jnp.min(twin_v(nets, target_critic, stats, batch.next_obs), axis=0)
    y = jax.lax.stop_gradient(batch.reward + disc * v_next)
    pi = jax.lax.stop_gradient(policy(nets, actor, stats, batch.obs))
    q = twin_q_adv(nets, critic, stats, batch.obs, batch.action, pi)
    return jnp.sum(jnp.mean(((q - y) / nets.dt) ** 2, axis=-1)), jnp.mean(q[0])


def advantage_actor_loss(actor, *, nets: Networks, critic, stats: ObsStats | None,
                         obs: jax.Array) -> jax.Array:  # fmt: skip
    """−mean Ā_1(s, π(s)) (the authors' actor objective): its gradient is ∂Q_1/∂a · ∂π / δ."""
    a = policy(nets, actor, stats, obs)
    return -jnp.mean(twin_adv(nets, jax.tree.map(lambda p: p[:1], critic), stats, obs, a)[0])
