"""Actor and twin-critic MLPs (flax.linen), spec row A7: 256-256 ReLU, tanh actor.

The two critics share one module definition; their parameters are stacked on a
leading axis of size 2 and evaluated with ``vmap``, so both critics run as one
fused computation.

Critic kinds (``make_networks(critic=...)``):

- ``"mlp"`` (the paper): one MLP on ``[s, a]``.
- ``"advantage"`` (not in the paper): ``Q(s, a) = V(s) + A(s, a) − A(s, ā)``, two MLPs,
  where ``ā`` is a baseline action the caller passes (the current policy's action,
  gradient stopped).  With short control steps the action changes Q by a tiny amount
  next to V(s) (Tallec et al. 2019, "Making deep Q-learning methods robust to time
  discretization"); in one MLP the error of fitting V then swamps ∂Q/∂a.  Here ∂Q/∂a
  comes from A alone, and A cannot absorb any function of s alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """Dense ReLU layers, then a linear output (tanh-squashed if ``squash``); with
    ``layer_norm``, each hidden layer is Dense → LayerNorm → ReLU."""

    hidden: Sequence[int]
    out: int
    squash: bool = False
    layer_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.Dense(width)(x)
            x = nn.relu(nn.LayerNorm()(x) if self.layer_norm else x)
        x = nn.Dense(self.out)(x)
        return jnp.tanh(x) if self.squash else x


class AdvantageCritic(nn.Module):
    """Q(s, a) = V(s) + A(s, a) − A(s, base): a value MLP and an advantage MLP."""

    hidden: Sequence[int]
    layer_norm: bool = False

    @nn.compact
    def __call__(self, obs, action, base):
        adv = MLP(self.hidden, 1, name="advantage", layer_norm=self.layer_norm)
        value = MLP(self.hidden, 1, name="value", layer_norm=self.layer_norm)(obs)[..., 0]
        base = jax.lax.stop_gradient(base)
        a_taken = adv(jnp.concatenate([obs, action], -1))[..., 0]
        return value + a_taken - adv(jnp.concatenate([obs, base], -1))[..., 0]


CRITICS = ("mlp", "advantage")


class Networks(NamedTuple):
    actor: MLP  # obs (..., n_obs) -> action (..., n_act) in [-1, 1]
    critic: nn.Module  # mlp: [obs, action] -> Q (..., 1); advantage: (obs, action, base) -> Q (...)

    @property
    def needs_base(self) -> bool:
        """Whether the critic takes a baseline action (the ``advantage`` kind)."""
        return isinstance(self.critic, AdvantageCritic)


def make_networks(
    action_size: int, hidden: Sequence[int] = (256, 256), critic: str = "mlp", critic_layer_norm: bool = False
) -> Networks:
    """``critic_layer_norm``: LayerNorm after each hidden Dense of the critics (not in the
    paper; Ball et al. 2023 and Nauman et al. 2024 use it to steady TD learning)."""
    if critic not in CRITICS:
        raise ValueError(f"unknown critic kind {critic!r}; allowed: {CRITICS}")
    h, ln = tuple(hidden), critic_layer_norm
    q = MLP(h, 1, layer_norm=ln) if critic == "mlp" else AdvantageCritic(h, layer_norm=ln)
    return Networks(actor=MLP(tuple(hidden), action_size, squash=True), critic=q)


def init_params(nets: Networks, key: jax.Array, obs_size: int, action_size: int):
    """Actor params and twin-critic params (leading axis 2)."""
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, obs_size))
    act = jnp.zeros((1, action_size))
    actor = nets.actor.init(k_actor, obs)
    if nets.needs_base:
        init = lambda k: nets.critic.init(k, obs, act, act)  # noqa: E731
    else:
        init = lambda k: nets.critic.init(k, jnp.concatenate([obs, act], -1))  # noqa: E731
    critic = jax.vmap(init)(jax.random.split(k_critic, 2))
    return actor, critic


def twin_q(nets: Networks, critic_params, obs: jax.Array, action: jax.Array, base: jax.Array | None = None):
    """Both critics' values, shape (2, ...) for obs (..., n_obs) and action (..., n_act).

    ``base`` (..., n_act): the baseline action of the ``advantage`` critic (required
    there, ignored by the ``mlp`` critic)."""
    if not nets.needs_base:
        x = jnp.concatenate([obs, action], -1)
        return jax.vmap(lambda p: nets.critic.apply(p, x)[..., 0])(critic_params)
    if base is None:
        raise ValueError("the advantage critic needs a baseline action (base=...)")
    return jax.vmap(lambda p: nets.critic.apply(p, obs, action, base))(critic_params)
