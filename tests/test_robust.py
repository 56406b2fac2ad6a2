"""The ``robust`` preset end to end at a tiny budget (the CI's robust run): it trains on
randomised plants and the wide track mixture, selects each seed's policy on the wide
validation tracks, and its config.json holds what it was trained under."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest

from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim.env import TrackingEnv, num_validation_tracks

TINY = dict(num_envs=16, total_transitions=16 * 40, warmup_transitions=16 * 8, buffer_size=16 * 64,
            batch_size=64, updates_per_step=2, epochs=2, hidden=(32, 32), model_horizon=2)  # fmt: skip


def test_the_robust_preset_randomises_the_plant_and_the_tracks():
    spec = sp.preset("robust")
    assert rz.active(spec.task) and spec.task.tracks.wide_mix and spec.num_seeds == 3
    assert spec.train.model_horizon > 0  # the model-based actor, as fast
    assert spec.task.observation.preview_s and spec.task.observation.obs_memory  # what it observes
    assert spec.task.observation.ref_integral_gain > 0  # integral action around the policy
    state = TrackingEnv(spec.task).reset(jax.random.PRNGKey(0)).pipeline_state
    assert state.ref_int.shape == (3,)  # kept per env, beside the randomised plant
    assert (
        TrackingEnv(spec.task).actor_observation_size
        == TrackingEnv(sp.preset("fast").task).observation_size + 19
    )
    # two resets fly two different vehicles, each within the preset's mass range
    env = TrackingEnv(spec.task)
    masses = [float(env.reset(jax.random.PRNGKey(k)).pipeline_state.plant.quad.mass) for k in range(2)]
    lo, hi = spec.task.randomization.mass
    nominal = spec.task.vehicle.quad.mass
    assert masses[0] != masses[1] and all(lo * nominal <= m <= hi * nominal for m in masses)


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_a_tiny_robust_run_trains_and_selects_on_the_wide_validation_tracks(tmp_path):
    spec = sp.preset("robust", **TINY)
    summary = run(spec, out=str(tmp_path), verbose=False)
    rows = rundir.read_metrics(summary["run_dir"])
    assert len(rows) == spec.num_seeds * TINY["epochs"]
    for row in rows:
        assert np.isfinite(float(row["val_tracking_error"])) and np.isfinite(float(row["critic_loss"]))
    assert {r["seed"] for r in rundir.selected_policies(summary["run_dir"])} == {0, 1, 2}
    with open(os.path.join(summary["run_dir"], "config.json")) as f:
        saved = sp.from_dict(json.load(f))
    assert saved == spec and saved.task.randomization.mass == (0.85, 1.15)
    assert num_validation_tracks(saved.task) > 10  # the wide bank, not the paper's 10
