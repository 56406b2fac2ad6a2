"""TD3 losses (Fujimoto et al. 2018; spec §2.4).

Critic: y = r + γ (1 − terminated) min_i Q'_i(s', clip(π'(s') + clip(σ̃ ξ, −c, c), −1, 1)),
loss Σ_i mean (y − Q_i(s, a))².  Actor: −mean Q_1(s, π(s)).  With n-step returns
(``TrainConfig.n_step``, not in the paper) y = Σ_{j<m} γ^j r_j + γ^m (1 − terminated) min_i Q'_i
at the observation m ≤ n steps on.

With the ``advantage`` critic (networks.py) the baseline action is the current policy's
π(s) for Q_i(s, a) and for the actor, and the target policy's π'(s') (before the
smoothing noise) for Q'_i.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax.buffer import NStep, Transition
from ttd3_jax.networks import Networks, twin_q


def critic_loss(critic_params, nets: Networks, target_actor, target_critic, batch: Transition,
                key: jax.Array, hp, target_std, actor=None, nstep: NStep | None = None
                ) -> tuple[jax.Array, dict]:  # fmt: skip
    """Twin-critic TD loss; ``target_std`` is σ̃ (or the shared σ under ``target_noise``);
    ``actor``: the current actor's params (needed by the ``advantage`` critic only);
    ``nstep``: n-step returns (buffer.sample_nstep), y = G + discount · min_i Q'_i."""
    if nstep is None:
        disc = hp.gamma * (1.0 - batch.terminated)
        nstep = NStep(reward=batch.reward, next_obs=batch.next_obs, discount=disc)
    pi_next = nets.actor.apply(target_actor, nstep.next_obs)
    eps = jnp.clip(target_std * jax.random.normal(key, pi_next.shape), -hp.target_clip, hp.target_clip)
    a_next = jnp.clip(pi_next + eps, -1.0, 1.0)
    base = nets.actor.apply(actor, batch.obs) if nets.needs_base else None
    q_next = jnp.min(twin_q(nets, target_critic, nstep.next_obs, a_next, pi_next), axis=0)
    y = jax.lax.stop_gradient(nstep.reward + nstep.discount * q_next)
    q = twin_q(nets, critic_params, batch.obs, batch.action, base)
    loss = jnp.sum(jnp.mean((q - y) ** 2, axis=-1))
    return loss, {"q_mean": jnp.mean(q[0])}


def actor_loss(
    actor_params, nets: Networks, critic_params, batch: Transition, key: jax.Array, hp, caps: bool = True
) -> jax.Array:
    """Deterministic policy gradient objective through the first critic, plus the optional
    CAPS smoothness terms (Mysore et al. 2021): ``hp.smooth_time`` · mean ||π(s) − π(s')||²
    and ``hp.smooth_space`` · mean ||π(s) − π(s + ``hp.smooth_sigma`` ξ)||².  ``caps`` is
    static: ``False`` leaves out the two extra actor passes (plain TD3, a third of the
    actor's work)."""
    obs = batch.obs
    a = nets.actor.apply(actor_params, obs)
    q1 = twin_q(nets, jax.tree.map(lambda p: p[:1], critic_params), obs, a, a)[0]
    if not caps:
        return -jnp.mean(q1)
    a_next = nets.actor.apply(actor_params, batch.next_obs)
    a_near = nets.actor.apply(actor_params, obs + hp.smooth_sigma * jax.random.normal(key, obs.shape))
    smooth_t = jnp.mean(jnp.sum((a - a_next) ** 2, -1))
    smooth_s = jnp.mean(jnp.sum((a - a_near) ** 2, -1))
    return -jnp.mean(q1) + hp.smooth_time * smooth_t + hp.smooth_space * smooth_s
