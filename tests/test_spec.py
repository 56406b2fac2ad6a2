"""The run spec: presets and their budgets, validation before anything compiles, and config.json
round trips."""

from __future__ import annotations

import dataclasses
import json

import pytest
from tiny import tiny

from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.sim.config import EnvConfig, make_config
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.td3.config import Hyper


def _changed(a, b) -> set[str]:
    """The fields in which two dataclasses of one kind differ (those of nested groups by
    their own names, as ``EnvConfig.replace`` takes them)."""
    out = set()
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if x != y:
            out |= _changed(x, y) if dataclasses.is_dataclass(x) and type(x) is type(y) else {f.name}
    return out


def test_the_presets_differ_where_their_docs_say():
    """``fast_dpg`` is ``fast`` with the paper's actor update (and the budget, env count,
    warm-up, update rate and constant learning rate that update needs), ``fast_model_free`` is ``fast_dpg``
    observing its memory and privileged critic inputs; ``paper`` is the defaults; unknown
    names are refused."""
    fast, dpg, free = (sp.preset(n) for n in ("fast", "fast_dpg", "fast_model_free"))
    assert fast.train.model_horizon > 0 and dpg.train.model_horizon == 0
    assert _changed(fast.train, dpg.train) <= {
        "model_horizon",
        "num_envs",
        "warmup_transitions",
        "total_transitions",
        "epochs",
        "updates_per_step",
    }
    assert _changed(fast.hp, dpg.hp) == {"lr_actor", "lr_decay"} and fast.task == dpg.task
    assert (free.train, free.hp) == (dpg.train, dpg.hp)
    assert _changed(dpg.task, free.task) == {"obs_memory", "obs_privileged"}
    assert sp.preset("paper") == sp.RunSpec() and sp.RunSpec().task == make_config("paper")
    with pytest.raises(ValueError, match="unknown preset 'quick'"):
        sp.preset("quick")


@pytest.mark.parametrize("name", sp.PRESETS)
def test_every_presets_budget_is_whole_epochs_within_its_total(name):
    """A preset's budget, computed from its own config: the warm-up, then ``epochs`` epochs
    of vector steps on every env, never past ``total_transitions`` and short of it by less
    than one more vector step per epoch; the warm-up fills a first minibatch (or, without
    critics, its rollouts hold ``warmup_transitions``)."""
    c = sp.preset(name).train
    vector = c.env_steps_per_step * c.num_envs  # transitions of one vector step
    assert c.transitions_run == c.warmup_steps * c.num_envs + c.epochs * c.steps_per_epoch * vector
    assert c.total_transitions - (c.epochs + 1) * vector < c.transitions_run <= c.total_transitions
    if c.warmup_in_rollouts:
        assert c.warmup_steps == 0 and c.warmup_rollouts * vector >= c.warmup_transitions > 0
    else:
        assert c.warmup_steps * c.num_envs >= c.warmup_transitions >= c.batch_size


def test_a_run_collects_the_budget_computed_from_its_config(tmp_path, capsys, shown_messages):
    """A budget that is not whole epochs is rounded down, the runner says so, and the run
    collects exactly that many transitions per seed: warm-up + epochs x vector steps x envs."""
    s = tiny()
    s = sp.replace(s, total_transitions=s.train.total_transitions + s.train.num_envs)  # one vector step more
    c = s.train
    assert c.transitions_run < c.total_transitions
    run_dir = run(s, out=str(tmp_path))["run_dir"]
    said = f"budget: {c.transitions_run:,} of total_transitions {c.total_transitions:,} per seed"
    assert said in capsys.readouterr().out
    last = rundir.read_metrics(run_dir)[-1]
    assert (
        last["env_steps"] == c.transitions_run == (c.warmup_steps + c.epochs * c.steps_per_epoch) * c.num_envs
    )


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
        sp.from_dict({"format": sp.CONFIG_FORMAT, "env": "quadrotor"})


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
