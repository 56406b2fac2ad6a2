"""The trainer's configuration.  :class:`TrainConfig` (frozen) fixes shapes, loop lengths and
switches: changing it means a new compiled program.  :class:`Hyper` is a pytree of numbers
the program takes as an argument, so a sweep over them is a ``vmap`` of one program.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated

from flax import struct
from tyro.conf import Suppress  # (a field the command line does not show)

from ttd3_jax import checks
from ttd3_jax.td3.networks import CRITIC_ARCHS

ALGOS = ("ttd3", "td3")
TARGET_NOISES = ("fixed", "shared_sigma")
SELECTIONS = ("validation", "last")  # which policy a quadrotor run keeps in best/
MAX_TRANSITIONS = 2_000_000_000  # the transition counter is int32


@struct.dataclass
class Hyper:
    """Numeric hyperparameters: pytree leaves, so ``vmap`` sweeps over them (spec §2.4)."""

    gamma: float = 0.99  # discount per env step
    tau: float = 5e-4  # Polyak factor (A6: 1 - 0.9995)
    lr_actor: float = 3e-4  # Adam
    lr_decay: float = 0.0  # the actor's lr falls linearly by this fraction over the run (1: to 0 at its end)
    lr_critic: float = 3e-4  # Adam
    sigma: float = 0.1  # TD3's constant exploration std
    beta: float = 0.08  # T-TD3 weight of the time term
    lam: float = 0.01  # T-TD3 decay rate per unit of t
    u_max: Annotated[float, Suppress] = 1.0  # action bound used by the σ formula
    target_sigma: float = 0.2  # σ̃, target-policy smoothing std
    target_clip: float = 0.1  # c, target-policy smoothing clip
    reward_scale: float = 1.0  # rewards are stored times this (keeps Q values O(1..100))
    model_grad_clip: Annotated[float, Suppress] = 1.0  # global-norm clip of the model-based actor gradient


# (lower bound, lower bound included, upper bound, upper bound included) of each Hyper field
_HYPER_RANGES = {
    "gamma": (0.0, True, 1.0, False),
    "tau": (0.0, False, 1.0, True),
    **dict.fromkeys(("beta", "lr_decay"), (0.0, True, 1.0, True)),
    # an Adam step of more than the weights' own scale, or rewards scaled past 1e3, only diverge
    **dict.fromkeys(("lr_actor", "lr_critic"), (0.0, False, 1.0, True)),
    **dict.fromkeys(("u_max", "reward_scale"), (0.0, False, 1e3, True)),
    "model_grad_clip": (0.0, False, 1e6, True),
    **dict.fromkeys(("sigma", "lam", "target_sigma", "target_clip"), (0.0, True, 1e3, True)),
}  # fmt: skip


def validate_hyper(hp: Hyper) -> None:
    """Raise ``ValueError`` naming a field of ``hp`` that is not a finite number in range
    (for a run's own ``hp``; a sweep's arrays of values are the caller's to check)."""
    for f in dataclasses.fields(hp):
        lo, lo_in, hi, hi_in = _HYPER_RANGES[f.name]
        checks.number(f"hp.{f.name}", getattr(hp, f.name), lo, hi, lo_open=not lo_in, hi_open=not hi_in)


DELTA_REDUCES = ("sum", "mean")
R_RANGES = ("batch", "running")
T_UNITS = ("episode", "env_step", "update")


@dataclasses.dataclass(frozen=True)
class NoiseConfig:
    """Static readings of the T-TD3 schedule (spec A1-A3, A5; numeric values live in ``Hyper``)."""

    delta_reduce: str = "sum"  # A1
    r_range: str = "batch"  # A2: min/max of the minibatch, or running extremes
    t_unit: str = "episode"  # A3: t = transitions / episode_length, transitions, or updates
    sigma_is_variance: bool = False  # A5: N(0, σ) read as variance σ (std √σ)

    def __post_init__(self):
        for name, allowed in (("delta_reduce", DELTA_REDUCES), ("r_range", R_RANGES), ("t_unit", T_UNITS)):
            checks.one_of(f"NoiseConfig.{name}", getattr(self, name), allowed)
        checks.boolean("NoiseConfig.sigma_is_variance", self.sigma_is_variance)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration. Validated on construction."""

    algo: str = "ttd3"  # "ttd3" (time-attenuating σ) | "td3" (constant σ)
    num_envs: int = 20  # M, parallel training envs
    total_transitions: int = 3_000_000
    warmup_transitions: int = 25_000  # uniform-random actions before learning
    buffer_size: int = 1_000_000  # rounded up to a multiple of num_envs
    batch_size: int = 256
    # G, critic updates per vector env step; 0 (model_horizon > 0 only): no critics train, the
    # rollouts drive T-TD3's σ and nothing is stored (no replay buffer)
    updates_per_step: int = 20
    policy_delay: Annotated[int, Suppress] = 2  # d
    # 0: the actor follows ∂Q₁/∂a (TD3, the paper).  H >= 1 (quadrotor only, not in the paper):
    # every vector step rolls the envs H steps with the current policy (plus exploration
    # noise), back-propagates Σ γ^k r_k through the simulator into the actor, and stores the
    # H·num_envs transitions for the usual TD3 critic updates.
    model_horizon: int = 0
    hidden: tuple[int, ...] = (256, 256)  # widths of the hidden layers of the actor and of each critic
    critic_arch: Annotated[str, Suppress] = (
        "mlp"  # "mlp" (the paper's) | "residual" (SimBa-style LayerNorm blocks)
    )
    normalize_obs: bool = False  # running mean/std normalisation of observations (nets' input)
    epochs: int = 50  # progress / eval / checkpoint points
    noise: Annotated[NoiseConfig, Suppress] = NoiseConfig()
    target_noise: Annotated[str, Suppress] = "fixed"  # A4: σ̃ fixed, or "shared_sigma" (uses the current σ)
    # critic targets from n-step returns (not in the paper; FastTD3 uses 3), each cut where its
    # episode ended and bootstrapped through truncation; 1 is TD3's one-step target
    n_step: int = 1
    # which policy of each seed best/ keeps (quadrotor): "validation", the one with the lowest
    # validation error so far (spec T8); "last", the newest (a run whose lr falls to 0 ends there)
    selection: Annotated[str, Suppress] = "validation"

    def __post_init__(self):
        _validate(self)

    @property
    def time_attenuating(self) -> bool:
        """T-TD3's σ schedule (``algo="ttd3"``); TD3 keeps σ constant."""
        return self.algo == "ttd3"

    @property
    def env_steps_per_step(self) -> int:
        """Env steps per vector step after warm-up (``model_horizon``, or 1)."""
        return max(1, self.model_horizon)

    @property
    def warmup_in_rollouts(self) -> bool:
        """Whether the random warm-up is the first rollouts of the model-based actor (no critic
        needs a filled buffer before its first update; the init program then holds no env step)
        rather than collected before the epochs."""
        return self.model_horizon > 0 and not self.trains_critics

    @property
    def warmup_steps(self) -> int:
        """Vector env steps of random warm-up collected before the epochs (0 when the warm-up
        is in the rollouts)."""
        return 0 if self.warmup_in_rollouts else -(-self.warmup_transitions // self.num_envs)

    @property
    def warmup_rollouts(self) -> int:
        """The first rollouts that act at random and leave the actor alone (with
        :attr:`warmup_in_rollouts`; else 0): ``warmup_transitions`` in whole rollouts."""
        per = self.num_envs * self.model_horizon
        return -(-self.warmup_transitions // per) if self.warmup_in_rollouts else 0

    @property
    def steps_per_epoch(self) -> int:
        """Vector steps (each ``env_steps_per_step`` env steps, then G updates) per compiled epoch."""
        left = self.total_transitions // self.num_envs - self.warmup_steps
        return max(1, left // (self.env_steps_per_step * self.epochs))

    @property
    def trains_critics(self) -> bool:
        """Whether the twin critics train (and so a replay buffer is kept)."""
        return self.updates_per_step > 0

    @property
    def buffer_capacity(self) -> int:
        """Rows of the replay buffer: ``buffer_size`` rounded up to whole env batches (0 when no
        critic reads it)."""
        return -(-self.buffer_size // self.num_envs) * self.num_envs if self.trains_critics else 0

    @property
    def transitions_run(self) -> int:
        """Transitions a run collects per seed: the budget rounded down to whole epochs."""
        return (
            self.warmup_steps + self.steps_per_epoch * self.epochs * self.env_steps_per_step
        ) * self.num_envs


def _validate(c: TrainConfig) -> None:
    """Raise ``ValueError`` naming the bad field; runs before anything is compiled."""
    for name, allowed in (("algo", ALGOS), ("critic_arch", CRITIC_ARCHS), ("target_noise", TARGET_NOISES),
                          ("selection", SELECTIONS)):  # fmt: skip
        checks.one_of(name, getattr(c, name), allowed)
    for name in ("num_envs", "total_transitions", "buffer_size", "batch_size", "policy_delay", "epochs"):
        checks.integer(name, getattr(c, name), 1, MAX_TRANSITIONS)
    checks.integer("model_horizon", c.model_horizon, 0, 100_000)
    # 0 only where the actor learns from the simulator: the paper's actor update reads the critics
    lo = 0 if c.model_horizon > 0 else 1
    why = " (0 needs model_horizon > 0)" if lo else ""
    checks.integer("updates_per_step", c.updates_per_step, lo, MAX_TRANSITIONS, why)
    if not c.trains_critics and c.noise.t_unit == "update":
        why = "'episode' or 'env_step' when updates_per_step is 0 (no updates to count)"
        checks.fail("noise.t_unit", why, c.noise.t_unit)
    checks.integer("warmup_transitions", c.warmup_transitions, 0, MAX_TRANSITIONS)
    checks.integer("n_step", c.n_step, 1, 1000)
    checks.boolean("normalize_obs", c.normalize_obs)
    checks.instance("noise", c.noise, NoiseConfig)
    if len(c.hidden) < 1 or not all(checks.is_integer(h) and h >= 1 for h in c.hidden):
        checks.fail("hidden", "one or more layer widths >= 1", c.hidden)
    if c.trains_critics and c.batch_size > c.buffer_size:
        raise ValueError(f"batch_size ({c.batch_size}) must be <= buffer_size ({c.buffer_size})")
    if c.trains_critics and c.warmup_transitions < c.batch_size:
        raise ValueError(
            f"warmup_transitions ({c.warmup_transitions}) must be >= batch_size ({c.batch_size}) so the "
            "first minibatch is drawn from a filled buffer"
        )
    budget = (c.total_transitions // c.num_envs - c.warmup_steps) // c.env_steps_per_step
    if budget < c.epochs:
        raise ValueError(
            f"total_transitions ({c.total_transitions}) leaves {max(budget, 0)} vector steps after warm-up, "
            f"fewer than epochs ({c.epochs}); raise total_transitions or lower epochs"
        )
    rollouts = c.steps_per_epoch * c.epochs
    if c.warmup_rollouts >= rollouts:
        raise ValueError(
            f"warmup_transitions ({c.warmup_transitions}) fills all {rollouts} rollouts of total_transitions "
            f"({c.total_transitions}): nothing would learn; lower warmup_transitions"
        )
