"""experiments/sigma_schedule.py: σ under each reading, from known rewards (no training)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from experiment_scripts import experiment

from ttd3_jax.run import spec as sp

ss = experiment("sigma_schedule")


def test_delta_of_sum_and_mean_on_known_rewards():
    # rewards 0 and 1 in equal parts: each minibatch's normalised mean is about 1/2
    d = ss.delta_samples(np.tile([0.0, 1.0], 5000))
    assert np.median(d["mean"]) == pytest.approx(0.5, abs=0.05)
    np.testing.assert_allclose(d["sum"], ss.BATCH * d["mean"], rtol=1e-6)


def test_sigma_curve_matches_the_formula_for_each_time_unit():
    spec = sp.preset("mujoco")  # 1 env, 1 update per step, warm-up 25k, β 0.08, λ 0.01
    n = np.array([25_000.0, 125_000.0])
    ep = ss.sigma_curve(spec, n, "sum", "episode", 300.0, 1000)
    np.testing.assert_allclose(ep, 0.08 * np.exp(-0.01 * n / 1000), rtol=1e-6)  # e^-300 term is 0
    upd = ss.sigma_curve(spec, n, "mean", "update", 0.5, 1000)
    want = 0.08 * np.exp(-0.01 * (n - 25_000)) + 0.92 * math.exp(-0.5)
    np.testing.assert_allclose(upd, want, rtol=1e-6)
    assert ss.sigma_curve(spec, n, "sum", "env_step", 300.0, 1000)[0] < 1e-100
