"""The committed protocol tracks (experiments/tracks/protocol/) are what the evaluation flies."""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "experiments"))
import protocol_tracks as pt  # noqa: E402

from ttd3_jax import spec as sp  # noqa: E402
from ttd3_jax.sim import trajectories as tr  # noqa: E402
from ttd3_jax.sim.env import TrackingEnv  # noqa: E402


def test_the_committed_files_equal_the_generator():
    want = pt.protocol_tracks()
    assert sorted(os.listdir(pt.OUT)) == sorted(f"{n}.csv" for n in want)
    assert len(want) == 1 + 21 + tr.NUM_VALIDATION_TRACKS
    for name, pos in want.items():
        t, got = pt.read_csv(os.path.join(pt.OUT, f"{name}.csv"))
        np.testing.assert_allclose(t, np.arange(pt.LAST_STEP + 1) * 1e-3, atol=1e-9, err_msg=name)
        np.testing.assert_array_equal(got, pos, err_msg=name)


@pytest.mark.parametrize("preset", ["fast", "paper"])
@pytest.mark.parametrize("track, seed", [("spiral_rt", 0), ("los_rt", 0), ("los_rt", 7)])
def test_a_presets_evaluation_flies_the_committed_reference(preset, track, seed):
    """Each preset's evaluation env reads p_d(k) from the file, look-ahead included."""
    c = sp.preset(preset).task.for_eval(track, los_seed=seed)
    env = TrackingEnv(c)
    ks = jnp.arange(c.episode_steps + c.observation.lookahead_k + 1)
    want = np.asarray(jax.vmap(lambda k: tr.position(env.sample_track(None), k, c.dt))(ks))
    name = "spiral_rt" if track == "spiral_rt" else f"los_rt_seed{seed:02d}"
    got = pt.read_csv(os.path.join(pt.OUT, f"{name}.csv"))[1][: len(ks)]
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
