"""Exploration-noise schedules: TD3's constant std and T-TD3's time-attenuating std.

T-TD3 (spec §2.4, rows A1-A3, A5): after every critic update, with the minibatch
rewards r_j,

    δ = Σ_j (r_j − r_min) / (r_max − r_min)        (``delta_reduce="mean"`` divides by B)
    σ = β·u_max·exp(−λ t) + (1 − β)·u_max·exp(−δ)

where t counts episode-equivalents of collected transitions (``t_unit``), and σ is
kept unchanged when r_max − r_min ≤ 1e-8.  TD3 is the same code with σ ≡ ``hp.sigma``
(``time_attenuating=False``, ``TrainConfig.algo = "td3"``).  ``hp`` is the trainer's
:class:`~ttd3_jax.td3.config.Hyper`; the static readings are
:class:`~ttd3_jax.td3.config.NoiseConfig`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ttd3_jax.td3.config import Hyper, NoiseConfig


@struct.dataclass
class NoiseState:
    sigma: jax.Array  # current exploration σ (std unless sigma_is_variance)
    r_min: jax.Array  # running reward extremes (r_range="running")
    r_max: jax.Array


def init(hp: Hyper, time_attenuating: bool) -> NoiseState:
    """σ starts at u_max for T-TD3 (Alg. 1), at ``hp.sigma`` for TD3."""
    sigma = hp.u_max if time_attenuating else hp.sigma
    f = jnp.float32
    return NoiseState(
        sigma=jnp.asarray(sigma, f), r_min=jnp.asarray(jnp.inf, f), r_max=jnp.asarray(-jnp.inf, f)
    )


def update(ns: NoiseState, *, cfg: NoiseConfig, time_attenuating: bool, hp: Hyper, rewards: jax.Array,
           n_tr: jax.Array, n_upd: jax.Array, episode_length: int) -> NoiseState:  # fmt: skip
    """σ after one critic update on a minibatch with ``rewards`` (B,).

    ``n_tr``: transitions collected so far; ``n_upd``: updates done; ``episode_length``:
    L_nom, transitions per nominal episode of the training env (t_unit="episode")."""
    if not time_attenuating:
        return ns.replace(sigma=jnp.asarray(hp.sigma, ns.sigma.dtype))
    b_min, b_max = jnp.min(rewards), jnp.max(rewards)
    if cfg.r_range == "running":
        r_min, r_max = jnp.minimum(ns.r_min, b_min), jnp.maximum(ns.r_max, b_max)
    else:
        r_min, r_max = b_min, b_max
    span = r_max - r_min
    norm = (rewards - r_min) / jnp.maximum(span, 1e-8)
    delta = jnp.sum(norm) if cfg.delta_reduce == "sum" else jnp.mean(norm)
    t = {"episode": n_tr / episode_length, "env_step": n_tr, "update": n_upd}[cfg.t_unit]
    t = jnp.asarray(t, jnp.float32)
    new = hp.beta * hp.u_max * jnp.exp(-hp.lam * t) + (1.0 - hp.beta) * hp.u_max * jnp.exp(-delta)
    sigma = jnp.where(span > 1e-8, new, ns.sigma).astype(ns.sigma.dtype)
    return NoiseState(sigma=sigma, r_min=r_min, r_max=r_max)


def std(cfg: NoiseConfig, sigma: jax.Array) -> jax.Array:
    """Standard deviation of the Gaussian exploration noise for a given σ."""
    return jnp.sqrt(sigma) if cfg.sigma_is_variance else sigma
