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

from ttd3_jax.run import spec as sp  # noqa: E402
from ttd3_jax.sim import trajectories as tr  # noqa: E402
from ttd3_jax.sim.env import (
    TrackingEnv,  # noqa: E402
    validation_tracks,  # noqa: E402
)


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_the_committed_files_equal_the_generator():
    want = pt.protocol_tracks()
    assert sorted(os.listdir(pt.OUT)) == sorted(f"{n}.csv" for n in want)
    assert len(want) == 1 + 21 + tr.NUM_VALIDATION_TRACKS
    rows = sp.preset("fast").task.horizon_steps  # the validation tracks: over fast's table
    for name, pos in want.items():
        t, got = pt.read_csv(os.path.join(pt.OUT, f"{name}.csv"))
        n = rows if name.startswith("validation") else pt.LAST_STEP + 1
        np.testing.assert_allclose(t, np.arange(n) * 1e-3, atol=1e-9, err_msg=name)
        np.testing.assert_array_equal(got, pos, err_msg=name)


def test_the_validation_files_are_what_fast_selects_on_and_other_tables_draw_others():
    """validation_XX.csv is the bank a `fast` run's evaluation flies (its closed loop's env,
    over the whole table).  The paper preset's table is shorter (a 1-step look-ahead), so the
    draws that follow the random-acceleration track's (whose size grows with the table) move:
    its spirals and LOS tracks differ from fast's, its random-acceleration tracks do not."""
    cfg = sp.preset("fast").task
    venv = TrackingEnv(cfg.for_eval("validation"))
    bank = validation_tracks(cfg, venv.num_segments)
    ks = jnp.arange(cfg.horizon_steps)
    paper = pt.validation_bank("paper")
    same = []
    for i in range(tr.NUM_VALIDATION_TRACKS):
        track = jax.tree.map(lambda x, i=i: x[i], bank)
        want = np.asarray(jax.vmap(lambda k, t=track: tr.position(t, k, cfg.dt))(ks))
        got = pt.read_csv(os.path.join(pt.OUT, f"validation_{i:02d}.csv"))[1]
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-6, err_msg=f"validation_{i:02d}")
        n = min(len(got), len(paper[f"validation_{i:02d}"]))
        same.append(np.array_equal(got[:n], paper[f"validation_{i:02d}"][:n]))
    spiral = np.asarray(bank.kind) == tr.SPIRAL
    assert spiral.any() and not any(np.asarray(same)[spiral]) and any(same)


@pytest.mark.parametrize("preset", ["fast", "paper", "robust"])
@pytest.mark.parametrize("track, seed", [("spiral_rt", 0), ("los_rt", 0), ("los_rt", 7)])
def test_a_presets_evaluation_flies_the_committed_reference(preset, track, seed):
    """Each preset's evaluation env reads p_d(k) from the file over its whole table: the
    look-ahead, and the robust preset's 1 s preview after it."""
    c = sp.preset(preset).task.for_eval(track, los_seed=seed)
    env = TrackingEnv(c)
    ks = jnp.arange(c.horizon_steps)
    assert len(ks) <= pt.LAST_STEP + 1
    want = np.asarray(jax.vmap(lambda k: tr.position(env.sample_track(None), k, c.dt))(ks))
    name = "spiral_rt" if track == "spiral_rt" else f"los_rt_seed{seed:02d}"
    got = pt.read_csv(os.path.join(pt.OUT, f"{name}.csv"))[1][: len(ks)]
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
