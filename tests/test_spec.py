"""The run spec: presets, validation before anything compiles, and config.json round trips."""

from __future__ import annotations

import dataclasses
import json

import pytest
from tiny import tiny

from ttd3_jax import spec as sp
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.td3.config import Hyper, TrainConfig


def test_presets_are_what_the_docs_say():
    fast, dpg, paper, mujoco = (sp.preset(n) for n in ("fast", "fast_dpg", "paper", "mujoco"))
    assert fast.train.model_horizon == 50 and dpg.train.model_horizon == 0
    back = dict(model_horizon=0, total_transitions=450_000, epochs=15, updates_per_step=16)
    assert dataclasses.replace(fast.train, **back) == dpg.train
    assert fast.hp == dpg.hp.replace(lr_actor=1e-2)
    assert fast.task == dpg.task == make_config("practical", hover_centered_thrust=True)
    assert paper == sp.RunSpec() and paper.task == make_config("paper") and paper.train == TrainConfig()
    assert mujoco.env == "hopper" and mujoco.train.num_envs == 1 and mujoco.hp.target_clip == 0.5
    with pytest.raises(ValueError, match="unknown preset 'quick'"):
        sp.preset("quick")


def test_preset_changes_route_to_the_train_config_or_the_spec():
    s = sp.preset("fast", num_envs=8, seed=3, algo="td3", hp=Hyper(tau=0.01))
    assert s.train.num_envs == 8 and s.seed == 3 and s.algo == "td3" and s.hp.tau == 0.01
    assert sp.replace(s, epochs=4).train.epochs == 4 and sp.replace(s) is s
    with pytest.raises(ValueError, match=r"unknown run spec field\(s\) \['n_quantiles'\]"):
        sp.preset("fast", n_quantiles=3)


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(env="cartpole3d"), "env must be 'quadrotor' or one of"),
        (dict(seed=-1), "seed must be an integer >= 0"),
        (dict(num_seeds=0), "num_seeds must be an integer >= 1"),
        (
            dict(env="hopper", model_horizon=4, total_transitions=16 * 100),
            "model_horizon > 0 back-propagates",
        ),
        (dict(task=make_config("practical", track="spiral_rt")), "task.tracks.track must be 'train'"),
        (dict(task={"e_max": 1.0}), "task must be a EnvConfig"),
    ],
)
def test_run_spec_errors(changes, match):
    with pytest.raises(ValueError, match=match):
        tiny(**changes)


def test_brax_settings_errors():
    with pytest.raises(ValueError, match="brax.backend must be one of"):
        sp.BraxSettings(backend="bullet")
    with pytest.raises(ValueError, match="brax.episode_length must be an integer >= 1"):
        sp.BraxSettings(episode_length=0)


@pytest.mark.parametrize(
    "fields, match",
    [
        (dict(e_max="big"), r"EnvConfig.reward.e_max must be a finite number > 0, got 'big'"),
        (dict(e_max=-1.0), r"EnvConfig.reward.e_max must be a finite number > 0, got -1.0"),
        (dict(obs_frame="heading"), r"obs_frame must be one of \('world', 'track'\)"),
        (dict(crash_penalty=-1.0), r"crash_penalty must be a finite number >= 0 or None, got -1.0"),
        (dict(terminate="no"), "terminate must be true or false"),
        (dict(episode_steps=3001, action_repeat=10), "multiple of action_repeat"),
        (dict(quad=QuadParams(mass=0.0)), "QuadParams.mass must be > 0"),
    ],
)
def test_env_config_errors_name_the_field(fields, match):
    with pytest.raises(ValueError, match=match):
        EnvConfig().replace(**fields)


def test_crash_cost_follows_e_max_unless_set():
    assert make_config("paper").crash_cost == pytest.approx(400.0)  # ρ₁ r_e(2) / (1 − 0.99)
    assert make_config("practical").crash_cost == pytest.approx(1000.0)  # 10 steps per action, e_max 1
    assert make_config("practical", e_max=0.5).crash_cost == pytest.approx(500.0)
    assert make_config("practical", e_max=1.5).crash_cost == pytest.approx(2250.0)  # r_e = e² above 1 m
    assert make_config("paper", crash_penalty=7.0).crash_cost == 7.0


def test_config_json_round_trip_keeps_every_field():
    s = tiny(num_seeds=2, task=make_config("practical", e_max=1.5, quad=QuadParams(mass=1.8)),
             hp=Hyper(lr_actor=1e-3, lam=0.02))  # fmt: skip
    d = json.loads(json.dumps(sp.to_dict(s)))
    assert sp.from_dict(d) == s
    assert sp.from_dict({**d, "hp": {**d["hp"], "u_max": 1}}).hp.u_max == 1.0  # an int where a float goes
    assert isinstance(sp.from_dict({**d, "hp": {**d["hp"], "u_max": 1}}).hp.u_max, float)
    with pytest.raises(ValueError, match=r"fields \"train\", \"hp\", .* are missing"):  # no defaults
        sp.from_dict({"env": "quadrotor"})


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d["train"].update(n_quantiles=3), 'can not match "n_quantiles" to any data class field'),
        (
            lambda d: d["task"]["reward"].update(e_max="big"),
            'field "task.reward.e_max" - should be "float" instead of value "big"',
        ),
        (lambda d: d["task"]["vehicle"]["quad"].update(mass=-1), "QuadParams.mass must be > 0"),
        (lambda d: d.update(hp=[1, 2]), 'field "hp" - should be "Hyper"'),
        (lambda d: d.update(colour="red"), 'can not match "colour"'),
    ],
)
def test_config_json_errors_name_the_field(edit, match):
    d = json.loads(json.dumps(sp.to_dict(tiny())))
    edit(d)
    with pytest.raises(ValueError, match=match):
        sp.from_dict(d)
