"""The run spec: one object that says everything a training run is (the env, the static
``TrainConfig``, the ``Hyper`` pytree, the seeds).  The CLI parses it with tyro,
``config.json`` stores it whole, and resume and evaluation rebuild the run from it alone.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated

import dacite
import tyro

from ttd3_jax import checks
from ttd3_jax.run import tasks
from ttd3_jax.sim import vehicles
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.track_families import WIDE_MIX
from ttd3_jax.td3.buffer import transition_bytes
from ttd3_jax.td3.config import Hyper, TrainConfig, validate_hyper
from ttd3_jax.td3.env_spec import EnvSpec
from ttd3_jax.td3.trainer import Trainer, make_trainer

QUADROTOR = "quadrotor"
PRESETS = ("fast", "robust", "cf2", "fast_dpg", "fast_model_free", "paper", "mujoco")
SEED_LIMIT = 2**32  # seeds are uint32 PRNG keys: seed + num_seeds - 1 must stay below this
# config.json's "format": the layout of the run spec this version reads, and the only one.  A
# file of another format was written by an older ttd3_jax, and is refused with one line.
CONFIG_FORMAT = 16


# The ``robust`` preset's task on top of ``fast``'s (EnvConfig fields by name): what each
# training episode draws about the plant (sim.randomization; factors on the nominal vehicle,
# latency in s), the disturbances it flies in, the observation's memory and preview of the
# reference, integral action (the observed reference shifted by 3/s x the integral of the
# error within 5 mm, up to 1 cm), and the wide track mixture.  Each range is half as wide as
# the robustness rows (control.robustness) reach: mass ±15 %, thrust gain ±2 %, rate lag
# x/÷ √2, latency 0-10 ms, noise x0-0.75, bias ±1 cm, mean wind ±0.15 m/s², OU wind
# 0.25 m/s².  The full widths (mass ±30 %, latency 0-20 ms, ...) met fewer rows on every seed
# and cost more precision
# (docs/results.md, "A robust controller").
ROBUST_TASK = dict(
    mass=(0.85, 1.15), thrust_gain=(0.98, 1.02), tau_rate=(0.707, 1.414), latency=(0.0, 0.01),
    obs_noise=(0.0, 0.75), pos_bias=0.01, wind_mean=0.15,
    wind_sigma=0.25, obs_noise_pos=0.01, obs_noise_vel=0.05, obs_noise_quat=0.005,
    obs_memory=True, preview_s=(0.1, 0.25, 0.5, 1.0), ref_integral_gain=3.0, wide_mix=WIDE_MIX,
)  # fmt: skip


# The ``cf2`` preset's task: ``robust``'s, flying the ``cf2`` vehicle through its firmware's rate
# loop and motors (sim.inner_loop), with what a vehicle never tells exactly drawn per episode
# around the identified values: rotor time constants and rate-PID gains x0.7-1.4, drag x0.5-1.5,
# inertia x0.8-1.25 per axis; but neither a bias of the observed position nor observation noise
# (under a bias it cannot see the policy's error cost is flat within a centimetre of the track:
# Spiral-RT 12.1 / 13.3 / 11.4 with them, 7.8 / 9.1 / 8.5 without, and the noise row better);
# a heading cost 0.1 ψ² and an action-rate cost 0.3 ||Δa||² per physics step (without the
# heading cost a seed drifts off; at 1.0 the seeds are less precise, without any the transfer
# to crazyflow is worse: experiments/transfer_recipes.py, results/transfer/README.md);
# the applied action averaged over 0.05, 0.1 and 0.2 s (what the rotors are doing: without it the
# thrust limit-cycles, ±7 mm in z on Spiral-RT) and integral action within 3 mm of the track, up
# to a 2 cm shift (within 1 cm the integral winds up in the first second's transient and takes
# 2 s to unwind: Spiral-RT 7.8 / 8.2 / 7.3 against 5.6 / 5.4 / 5.6 for the last policies).
CF2_TASK = dict(ROBUST_TASK, quad=vehicles.CF2, tau_rate=(0.7, 1.4), rate_gains=(0.7, 1.4), drag=(0.5, 1.5),
                inertia=(0.8, 1.25), pos_bias=0.0, obs_noise=(0.0, 0.0), rho_yaw=0.1, rho_rate=0.3,
                action_history_s=(0.05, 0.1, 0.2), ref_integral_band=0.003,
                ref_integral_limit=0.02)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class BraxSettings:
    """A Brax/MJX task's settings (``env`` other than ``"quadrotor"``)."""

    backend: str = "mjx"  # Brax physics backend
    episode_length: int = 1000  # steps per episode (L_nom)
    eval_episodes: int = 10  # deterministic episodes per evaluation

    def __post_init__(self):
        checks.one_of("brax.backend", self.backend, tasks.BACKENDS)
        for name in ("episode_length", "eval_episodes"):
            checks.integer(f"brax.{name}", getattr(self, name), 1)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """Everything a training run is. Validated on construction, before anything compiles."""

    env: str = QUADROTOR  # "quadrotor" or a Brax env name
    train: Annotated[TrainConfig, tyro.conf.arg(name="")] = TrainConfig()  # (flat on the command line)
    hp: Hyper = Hyper()
    task: EnvConfig = make_config("paper")  # the quadrotor env (env "quadrotor")
    brax: BraxSettings = BraxSettings()  # the Brax env (any other env)
    seed: int = 0
    num_seeds: int = 1  # seeds run side by side with vmap: seed, seed+1, ...

    def __post_init__(self):
        if self.env != QUADROTOR and self.env not in tasks.BRAX_ENVS:
            raise ValueError(f"env must be {QUADROTOR!r} or one of {tasks.BRAX_ENVS}, got {self.env!r}")
        checks.integer("num_seeds", self.num_seeds, 1)
        checks.integer("seed", self.seed, 0)
        if self.seed + self.num_seeds > SEED_LIMIT:
            raise ValueError(
                f"seed must be an integer in [0, {SEED_LIMIT - self.num_seeds}] (seeds seed .. seed + "
                f"num_seeds - 1 are 32-bit PRNG seeds), got {self.seed}"
            )
        for name, kind in (
            ("train", TrainConfig),
            ("hp", Hyper),
            ("task", EnvConfig),
            ("brax", BraxSettings),
        ):
            checks.instance(name, getattr(self, name), kind)
        validate_hyper(self.hp)  # (model_horizon's env is checked where the trainer is made)
        if self.task.tracks.track != "train" or self.task.tracks.los_seed != 0:
            raise ValueError(
                "task.tracks.track must be 'train' and task.tracks.los_seed 0 (training draws the training "
                "mixture; the test and validation tracks are never trained on), got "
                f"{self.task.tracks.track!r}, {self.task.tracks.los_seed}"
            )

    @property
    def algo(self) -> str:
        return self.train.algo

    @property
    def is_quadrotor(self) -> bool:
        return self.env == QUADROTOR


def env_spec(spec: RunSpec, track_rows: int | None = None) -> EnvSpec:
    """The env the run trains on, with its evaluation (``track_rows``: see :func:`trainer_for`)."""
    if spec.is_quadrotor:
        return tasks.quadrotor(spec.task, track_rows)
    b = spec.brax
    return tasks.brax(spec.env, b.backend, b.episode_length, b.eval_episodes)


def trainer_for(spec: RunSpec, track_rows: int | None = None) -> Trainer:
    """The run's :class:`~ttd3_jax.td3.trainer.Trainer` (see ``make_trainer``).  ``track_rows``
    (a reader of a run, :func:`ttd3_jax.run.rundir.reader_trainer`): the training envs' track
    tables have this many rows and users' training tracks are not read (see
    :class:`~ttd3_jax.sim.env.TrackingEnv`)."""
    return make_trainer(spec.train, env_spec(spec, track_rows))


def buffer_bytes(spec: RunSpec, obs_size: int, action_size: int) -> int:
    """Replay memory of the whole run (all seeds, float32), in bytes."""
    return spec.num_seeds * spec.train.buffer_capacity * transition_bytes(obs_size, action_size)


def preset(name: str, **changes) -> RunSpec:
    """A named run spec, with ``changes`` on top: :class:`RunSpec` fields, or
    :class:`~ttd3_jax.td3.config.TrainConfig` fields (routed into ``train``).

    ``paper``: the published quadrotor settings (spec §2.4), 3e6 transitions.
    ``fast``: the ``practical`` env (10 ms actions, 50 ms look-ahead, track-frame
    observation) with hover-centred thrust, running observation normalisation, 64-64
    networks, rewards scaled by 0.01, and (not in the paper) a model-based actor update: 0.5 s
    rollouts (``model_horizon=50``) of 16 envs through the simulator, actor lr 1e-2 falling to
    0, 480k transitions in 12 epochs, no critic: σ moves with the rollouts' rewards.
    ``fast_dpg``: ``fast`` with the paper's actor update (∂Q₁/∂a through the critic), 450k
    transitions, 16 updates per 64-env step; it plateaus (docs/results.md).
    ``fast_model_free``: ``fast_dpg`` with the observation's memory (last action, error
    integral) and the critics' privileged inputs (wind, 1 s of preview): the best model-free
    recipe of ``experiments/model_free.py``, still short of the paper (docs/results.md).
    ``robust``: ``fast``'s model-based actor (as it was when ``robust`` was trained: lr 1e-2,
    10 epochs, 2 TD3 critic updates per rollout) against what a real vehicle never tells
    exactly (:data:`ROBUST_TASK`): each episode draws the mass, thrust gain, body-rate lag,
    latency, observation noise level and position bias, and a mean wind, and flies a track of
    the wide mixture (``sim.track_families``); the policy also observes its last action, the
    leaky integral of the tracking error and the reference 0.1, 0.25, 0.5 and 1 s ahead, and
    tracks a reference shifted by the integral of its error (integral action).  Three seeds
    side by side; each seed's policy is selected on the wide validation tracks.
    ``cf2``: ``robust`` on the ``cf2`` vehicle, a Crazyflie flown through its firmware's rate PID,
    mixer and motors (:data:`CF2_TASK`): the policy that flies a real vehicle's inner loop.
    ``mujoco``: the MuJoCo protocol (spec §2.7) on hopper: 1 env, 1 update per step,
    τ = 0.005, c = 0.5, 1e6 steps, L_nom = 1000.
    """
    if name == "paper":
        base = RunSpec()
    elif name in ("fast", "robust", "cf2", "fast_dpg", "fast_model_free"):
        train = TrainConfig(num_envs=64, total_transitions=450_000, warmup_transitions=10_000,
                            buffer_size=450_000, batch_size=256, updates_per_step=16, hidden=(64, 64),
                            normalize_obs=True, epochs=15)  # fmt: skip
        hp = Hyper(tau=0.005, reward_scale=0.01)
        if name in ("fast", "robust", "cf2"):
            train = dataclasses.replace(train, model_horizon=50, total_transitions=1_600_000, epochs=10,
                                        updates_per_step=2)  # fmt: skip
            hp = hp.replace(lr_actor=1e-2)
        if name == "fast":  # no critics; 16 envs, 480k transitions in 12 epochs; lr 1e-2 falling to 0
            train = dataclasses.replace(train, updates_per_step=0, num_envs=16, total_transitions=480_000,
                                        warmup_transitions=3_200, epochs=12)  # fmt: skip
            hp = hp.replace(lr_actor=1e-2, lr_decay=1.0)
        memory = name == "fast_model_free"
        task = make_config("practical", hover_centered_thrust=True, obs_memory=memory, obs_privileged=memory)
        base = RunSpec(train=train, hp=hp, task=task)
        if name == "robust":
            base = RunSpec(train=train, hp=hp, task=task.replace(**ROBUST_TASK), num_seeds=3)
        if name == "cf2":  # twice the transitions; the actor's lr 6e-3 falling to 0 (its last policy)
            train = dataclasses.replace(train, total_transitions=3_200_000, epochs=20, selection="last")
            hp = hp.replace(lr_actor=6e-3, lr_decay=1.0)
            base = RunSpec(train=train, hp=hp, task=task.replace(**CF2_TASK), num_seeds=3)
    elif name == "mujoco":
        train = TrainConfig(num_envs=1, total_transitions=1_000_000, warmup_transitions=25_000,
                            buffer_size=1_000_000, updates_per_step=1, epochs=200)  # fmt: skip
        base = RunSpec(env="hopper", train=train, hp=Hyper(tau=0.005, target_clip=0.5))
    else:
        raise ValueError(f"unknown preset {name!r}; allowed: {PRESETS}")
    return replace(base, **changes)


def replace(spec: RunSpec, **changes) -> RunSpec:
    """``spec`` with ``changes``: RunSpec fields, or TrainConfig fields (into ``train``)."""
    own = {f.name for f in dataclasses.fields(RunSpec)}
    train_fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(changes) - own - train_fields)
    if unknown:
        raise ValueError(f"unknown run spec field(s) {unknown}; allowed: {sorted(own | train_fields)}")
    train = {k: v for k, v in changes.items() if k not in own}
    if train:
        changes = {**{k: v for k, v in changes.items() if k in own}, "train": dataclasses.replace(
            changes.get("train", spec.train), **train)}  # fmt: skip
    return dataclasses.replace(spec, **changes) if changes else spec


def to_dict(spec: RunSpec) -> dict:
    """The spec as plain JSON values (``config.json``), with its ``format``."""
    return {"format": CONFIG_FORMAT, **dataclasses.asdict(spec)}


def check_format(d) -> dict:
    """``config.json``'s object without its ``format``; a file of another format is refused."""
    if not isinstance(d, dict):
        raise ValueError(f"run spec: the file must hold a JSON object, got {type(d).__name__}")
    version = d.get("format")
    if version != CONFIG_FORMAT:
        raise ValueError(
            f"run spec: config.json is format {version!r}, written by an older ttd3_jax; this version "
            f"reads format {CONFIG_FORMAT} only: train the run again, or evaluate it with the ttd3_jax "
            "commit that wrote it (git log)"
        )
    return {k: v for k, v in d.items() if k != "format"}


def missing_fields(cls, d: dict, path: str = "") -> list[str]:
    """The fields of ``cls`` (nested ones as ``group.field``) that ``d`` lacks.  Refuses a
    nested value of the wrong kind (not an object where a dataclass goes, not a list where a
    tuple goes), naming the field; dacite checks the rest."""
    hints, out = typing.get_type_hints(cls), []
    for f in dataclasses.fields(cls):
        where, kind = f"{path}{f.name}", hints[f.name]
        if f.name not in d:
            out.append(where)
            continue
        v = d[f.name]
        if dataclasses.is_dataclass(kind):
            if not isinstance(v, dict):
                raise ValueError(f'run spec: field "{where}" - should be "{kind.__name__}" (an object of its '
                                 f"fields), got {v!r}")  # fmt: skip
            out += missing_fields(kind, v, where + ".")
        elif typing.get_origin(kind) is tuple and not isinstance(v, list):
            raise ValueError(f'run spec: field "{where}" - should be a list, got {v!r}')
    return out


# JSON lists are tuples here, and an integer is a float where a float goes (``"u_max": 1``)
_DACITE = dacite.Config(
    strict=True, cast=[tuple], type_hooks={float: lambda x: float(x) if type(x) is int else x}
)


def task_from_dict(d: dict) -> EnvConfig:
    """An :class:`EnvConfig` stored as ``dataclasses.asdict`` (config.json's ``task``,
    policy.json's ``env_config``), rebuilt as :func:`from_dict` rebuilds the spec: every field
    given, each value's type checked; ``ValueError`` names what is wrong."""
    if not isinstance(d, dict):
        raise ValueError(f"env config: must be a JSON object, got {type(d).__name__}")
    missing = missing_fields(EnvConfig, d)
    if missing:
        raise ValueError(f"env config: field(s) {', '.join(missing)} missing")
    try:
        return dacite.from_dict(EnvConfig, d, config=_DACITE)
    except dacite.DaciteError as e:
        raise ValueError(f"env config: {e}") from None


def from_dict(d: dict) -> RunSpec:
    """The spec stored by :func:`to_dict` (dacite builds the nested dataclasses and checks every
    value's type).  Raises ``ValueError`` for another format (:func:`check_format`), or naming
    a field that is missing, does not exist or holds a value of the wrong type: no field takes
    a default."""
    d = check_format(d)
    missing = missing_fields(RunSpec, d)
    if missing:
        names, many = ", ".join(f'"{m}"' for m in missing), len(missing) > 1
        raise ValueError(f"run spec: field{'s' * many} {names} {'are' if many else 'is'} missing "
                         "(config.json must hold every field)")  # fmt: skip
    try:
        return dacite.from_dict(RunSpec, d, config=_DACITE)
    except dacite.DaciteError as e:
        raise ValueError(f"run spec: {e}") from None
