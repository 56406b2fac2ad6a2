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

from ttd3_jax import checks, envs
from ttd3_jax.sim.config import FIELD_GROUP, GROUPS, PLANT_NEUTRAL, EnvConfig, make_config
from ttd3_jax.sim.track_families import WIDE_MIX
from ttd3_jax.td3.buffer import transition_bytes
from ttd3_jax.td3.config import Hyper, TrainConfig, validate_hyper
from ttd3_jax.td3.env_spec import EnvSpec
from ttd3_jax.td3.trainer import Trainer, make_trainer

QUADROTOR = "quadrotor"
PRESETS = ("fast", "robust", "fast_dpg", "fast_model_free", "paper", "mujoco")
SEED_LIMIT = 2**32  # seeds are uint32 PRNG keys: seed + num_seeds - 1 must stay below this
CONFIG_FORMAT = 9  # config.json's "format"; files without one were written before it (format 0)
GROUPED_TASK = 3  # the first format whose "task" holds EnvConfig's groups (before: flat, grouped below)
TIME_FIELDS = ("dt", "episode_steps", "action_repeat")  # EnvConfig's own fields besides the groups
FLAT_RENAMED = {"tracks": "generator"}  # the flat task's names that changed on grouping
# Fields added to the run spec after runs were first saved (2026-11-22): for each, the first
# format whose files hold it, and the value that reproduces what a run saved before it did
# (task fields by their name in EnvConfig's group; migrate puts them in that group).
ADDED_FIELDS = {
    ("train", "model_horizon"): (1, 0),  # 2026-12-01: the model-based actor update
    ("train", "critic_arch"): (1, "mlp"),  # 2026-12-03: residual critics
    ("task", "err_scale"): (1, 0.02),  # 2026-12-03: err_cost="log"
    ("task", "memory_tau"): (1, 1.0),  # 2026-12-03: the observation's memory
    ("task", "obs_memory"): (1, False),
    ("task", "obs_privileged"): (1, False),  # 2026-12-03: the critics' privileged inputs
    ("task", "train_tracks"): (1, []),  # 2026-12-03: users' tracks in the training mixture
    ("task", "train_tracks_weight"): (1, 0.25),
    ("train", "n_step"): (2, 1),  # 2026-12-05: n-step returns
    ("train", "advantage_dt"): (3, 0.0),  # 2026-12-05: deep advantage updating
    # 2026-12-06: domain randomisation drawn per episode (sim.randomization), neutral: the nominal plant
    **{("task", name): (4, list(v) if isinstance(v, tuple) else v) for name, v in PLANT_NEUTRAL.items()},
    ("task", "wide_mix"): (4, []),  # issue 37: the wide training mixture
    ("task", "observe_rates"): (5, False),  # issue 37: ω observed on an instant vehicle
    ("task", "curriculum"): (6, 0.0),  # issue 37: the randomisation's curriculum
    ("task", "vehicles"): (7, []),  # issue 37: one policy for the vehicles between two (sim.vehicle_mix)
    ("task", "preview_s"): (8, []),
    # 2026-12-05: integral action around the policy (off: gain 0)
    ("task", "ref_integral_gain"): (9, 0.0),
    ("task", "ref_integral_band"): (9, 0.005),
    ("task", "ref_integral_limit"): (9, 0.01),
}


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


@dataclasses.dataclass(frozen=True)
class BraxSettings:
    """A Brax/MJX task's settings (``env`` other than ``"quadrotor"``)."""

    backend: str = "mjx"  # Brax physics backend
    episode_length: int = 1000  # steps per episode (L_nom)
    eval_episodes: int = 10  # deterministic episodes per evaluation

    def __post_init__(self):
        checks.one_of("brax.backend", self.backend, envs.BACKENDS)
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
        if self.env != QUADROTOR and self.env not in envs.BRAX_ENVS:
            raise ValueError(f"env must be {QUADROTOR!r} or one of {envs.BRAX_ENVS}, got {self.env!r}")
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


def env_spec(spec: RunSpec) -> EnvSpec:
    """The env the run trains on, with its evaluation."""
    if spec.is_quadrotor:
        return envs.quadrotor(spec.task)
    b = spec.brax
    return envs.brax(spec.env, b.backend, b.episode_length, b.eval_episodes)


def trainer_for(spec: RunSpec) -> Trainer:
    """The run's :class:`~ttd3_jax.td3.trainer.Trainer` (see ``make_trainer``)."""
    return make_trainer(spec.train, env_spec(spec))


def buffer_bytes(spec: RunSpec, obs_size: int, action_size: int) -> int:
    """Replay memory of the whole run (all seeds, float32), in bytes."""
    return spec.num_seeds * spec.train.buffer_capacity * transition_bytes(obs_size, action_size)


def preset(name: str, **changes) -> RunSpec:
    """A named run spec, with ``changes`` on top: :class:`RunSpec` fields, or
    :class:`~ttd3_jax.td3.config.TrainConfig` fields (routed into ``train``).

    ``paper``: the published quadrotor settings (spec §2.4), 3e6 transitions.
    ``fast``: the ``practical`` env (10 ms actions, 50 ms look-ahead, track-frame
    observation) with hover-centred thrust, running observation normalisation, 64-64
    networks, 64 envs, rewards scaled by 0.01, and (not in the paper) a model-based actor
    update: 0.5 s rollouts (``model_horizon=50``) back-propagated through the simulator,
    actor lr 1e-2, 1.6M transitions.  The twin critics are still trained by TD3 (2 updates
    per rollout, which keep T-TD3's σ schedule running); the actor does not use them.
    ``fast_dpg``: ``fast`` with the paper's actor update (∂Q₁/∂a through the critic), 450k
    transitions, 16 updates per 64-env step; it plateaus (docs/results.md).
    ``fast_model_free``: ``fast_dpg`` with the observation's memory (last action, error
    integral) and the critics' privileged inputs (wind, 1 s of preview): the best model-free
    recipe of ``experiments/model_free.py``, still short of the paper (docs/results.md).
    ``robust``: ``fast`` (the model-based actor) trained against what a real vehicle never
    tells exactly (:data:`ROBUST_TASK`): each episode draws the mass, thrust gain, body-rate
    lag, latency, observation noise level and position bias, and a mean wind, and flies a
    track of the wide mixture (``sim.track_families``); the policy also observes its last
    action, the leaky integral of the tracking error and the reference 0.1, 0.25, 0.5 and 1 s
    ahead, and tracks a reference shifted by the integral of its error (integral action).
    Three seeds side by side; each seed's policy is selected on the wide validation tracks.
    ``mujoco``: the MuJoCo protocol (spec §2.7) on hopper: 1 env, 1 update per step,
    τ = 0.005, c = 0.5, 1e6 steps, L_nom = 1000.
    """
    if name == "paper":
        base = RunSpec()
    elif name in ("fast", "robust", "fast_dpg", "fast_model_free"):
        train = TrainConfig(num_envs=64, total_transitions=450_000, warmup_transitions=10_000,
                            buffer_size=450_000, batch_size=256, updates_per_step=16, hidden=(64, 64),
                            normalize_obs=True, epochs=15)  # fmt: skip
        hp = Hyper(tau=0.005, reward_scale=0.01)
        if name in ("fast", "robust"):
            train = dataclasses.replace(train, model_horizon=50, total_transitions=1_600_000, epochs=10,
                                        updates_per_step=2)  # fmt: skip
            hp = hp.replace(lr_actor=1e-2)
        memory = name == "fast_model_free"
        task = make_config("practical", hover_centered_thrust=True, obs_memory=memory, obs_privileged=memory)
        base = RunSpec(train=train, hp=hp, task=task)
        if name == "robust":
            base = RunSpec(train=train, hp=hp, task=task.replace(**ROBUST_TASK), num_seeds=3)
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


def grouped(flat: dict) -> dict:
    """A flat EnvConfig as ``config.json`` formats 0-2 stored it, in today's groups (the one
    conversion; field values are not checked here)."""
    out = {k: v for k, v in flat.items() if k in TIME_FIELDS}
    for group in GROUPS:
        out[group] = {}
    for name, value in flat.items():
        name = FLAT_RENAMED.get(name, name)
        if name in FIELD_GROUP:
            out[FIELD_GROUP[name]][name] = value
        elif name not in TIME_FIELDS:
            out[name] = value  # not a field: from_dict names it
    return out


def migrate(d) -> dict:
    """``config.json`` as any version wrote it, in the current layout (without ``format``).
    A file of an earlier format (0: no ``format``, written before 2026-12-04) may lack the
    fields :data:`ADDED_FIELDS` added in later formats, which take the value runs had before
    them; nothing else is filled.  Formats 0-2 hold the task flat: it is grouped by
    :func:`grouped` first, and task fields are filled in their group."""
    if not isinstance(d, dict):
        raise ValueError(f"run spec: the file must hold a JSON object, got {type(d).__name__}")
    version = d.get("format", 0)
    out = {k: v for k, v in d.items() if k != "format"}
    if version == CONFIG_FORMAT:
        return out
    if version not in range(CONFIG_FORMAT) or isinstance(version, bool):
        raise ValueError(f"run spec: format {version!r} is not one this version reads (0 to {CONFIG_FORMAT})")
    if version < GROUPED_TASK and isinstance(out.get("task"), dict):
        out["task"] = grouped(out["task"])
    for (part, name), (since, value) in ADDED_FIELDS.items():
        if version < since:
            out = _filled(out, part, name, value)
    return out


def _filled(d: dict, part: str, name: str, value) -> dict:
    """``d`` with field ``name`` of ``part`` (``"train"``, or ``"task"``: in the group of
    ``name``) set to ``value`` where it is missing; a part or group that is not an object is
    left for :func:`from_dict` to name."""
    where = d.get(part)
    if part == "task" and isinstance(where, dict):
        return {**d, part: _filled(where, FIELD_GROUP[name], name, value)}
    if isinstance(where, dict) and name not in where:
        return {**d, part: {**where, name: value}}
    return d


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


def from_dict(d: dict) -> RunSpec:
    """The spec stored by :func:`to_dict`, through :func:`migrate` (dacite builds the nested
    dataclasses and checks every value's type).  Raises ``ValueError`` naming a field that is
    missing, does not exist or holds a value of the wrong type: no field takes a default."""
    d = migrate(d)
    missing = missing_fields(RunSpec, d)
    if missing:
        names, many = ", ".join(f'"{m}"' for m in missing), len(missing) > 1
        raise ValueError(f"run spec: field{'s' * many} {names} {'are' if many else 'is'} missing "
                         "(config.json must hold every field)")  # fmt: skip
    try:
        return dacite.from_dict(RunSpec, d, config=_DACITE)
    except dacite.DaciteError as e:
        raise ValueError(f"run spec: {e}") from None
