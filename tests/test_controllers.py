"""Classical controllers and the evaluation metrics (``ttd3_jax.control.geometric``,
``ttd3_jax.control.closed_loop``): the geometric controller holds hover and tracks a slow
circle-like spiral, and :func:`ttd3_jax.control.closed_loop.metrics` matches a hand-computed
:class:`Rollout`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttd3_jax.control.closed_loop import Rollout, closed_loop, metrics
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv


def eval_env(episode_steps: int = 2000, **kw) -> TrackingEnv:
    return TrackingEnv(make_config("paper", episode_steps=episode_steps, **kw).for_eval("spiral_rt"))


def spiral(gain: float, rate: float, climb: float = 0.0) -> tr.Track:
    """A spiral track ``(g t cos Ωt, g t sin Ωt, c t)`` (the Spiral-RT family), built as a
    :class:`Track` with the public fields; gain 0 gives a hover point at the origin."""
    f = jnp.float32
    return tr.Track(
        kind=jnp.asarray(tr.SPIRAL, jnp.int32),
        gain=jnp.asarray(gain, f),
        rate=jnp.asarray(rate, f),
        climb=jnp.asarray(climb, f),
        phase=jnp.zeros((), f),
        time_scale=jnp.ones((), f),
        seg_steps=jnp.ones((), jnp.int32),
        first_step=jnp.zeros((), jnp.int32),
        seg=jnp.zeros((1, 3, 3), f),
    )


@pytest.fixture(scope="module")
def geometric_runs():
    """Geometric controller, 2 s episodes at 1 kHz, one compile vmapped over: hover at
    the origin from rest, and a spiral of radius 0.2 m/s·t turning at π/2 rad/s
    (≤ 0.66 m/s, 0.4 m radius at the end), started at rest on p_d(0)."""
    env = eval_env()
    ctrl = geometric_controller(env.config)
    tracks = jax.tree.map(lambda *x: jnp.stack(x), spiral(0.0, 0.0), spiral(0.2, math.pi / 2, 0.05))

    def run(track):
        r = closed_loop(env, ctrl, env.reset_with_track(jax.random.PRNGKey(0), track))
        return r, metrics(env, r)

    r, m = jax.jit(jax.vmap(run))(tracks)
    out = {}
    for i, name in enumerate(("hover", "spiral")):
        e = np.linalg.norm(np.asarray(r.pos[i] - r.ref[i]), axis=-1)
        out[name] = (e, {k: float(v[i]) for k, v in m.items()}, np.asarray(r.ref[i]))
    return out


def test_geometric_holds_hover(geometric_runs):
    e, m, ref = geometric_runs["hover"]
    np.testing.assert_allclose(ref, 0.0)
    assert e.max() < 1e-4  # float32 trim error only
    assert m["crashed"] == 0
    # the controller commands hover thrust and zero rates: a0 = 0.4715 every step
    assert m["energy"] == pytest.approx(2000 * 0.4715, rel=1e-3)


def test_geometric_tracks_slow_spiral(geometric_runs):
    e, m, ref = geometric_runs["spiral"]
    assert np.linalg.norm(ref[-1, :2]) == pytest.approx(0.4, rel=0.01)  # the track really moves
    assert m["crashed"] == 0
    assert e.max() < 0.05
    assert e[1000:].max() < 0.02
    assert m["rmse"] < 0.02


def test_metrics_match_hand_computed_rollout():
    rep = 2  # physics steps per control step: energies are Σ over physics steps
    env = TrackingEnv(make_config("paper", action_repeat=rep).for_eval("spiral_rt"))
    ref = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [2.0, 0.0, -1.0]])
    err = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [1.0, 2.0, 2.0]])  # norms 5, 1, 3
    action = np.array([[0.0, 0.0, 0.0, 0.0], [0.3, 0.4, 0.0, 0.0], [1.0, 1.0, -1.0, 1.0]])  # norms 0, ½, 2
    error_sum = np.array([9.0, 2.5, 6.25])  # Σ‖e‖ over each control step's physics steps
    rollout = Rollout(
        pos=jnp.asarray(ref + err),
        ref=jnp.asarray(ref),
        action=jnp.asarray(action),
        error_sum=jnp.asarray(error_sum),
        crashed=jnp.asarray([0.0, 1.0, 1.0]),
        vel=jnp.zeros((3, 3)),
        quat=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (3, 1)),
    )
    m = {k: float(v) for k, v in metrics(env, rollout).items()}
    assert m["tracking_error"] == pytest.approx(9.0 + 2.5 + 6.25)
    assert m["rmse"] == pytest.approx(math.sqrt((25.0 + 1.0 + 9.0) / 3.0), rel=1e-6)
    assert m["max_error"] == pytest.approx(5.0)
    assert m["crashed"] == 1.0
    assert m["energy"] == pytest.approx(rep * (0.0 + 0.5 + 2.0))
    assert m["energy_sq"] == pytest.approx(rep * (0.0 + 0.25 + 4.0))
    assert set(m) == {"tracking_error", "rmse", "max_error", "crashed", "energy", "energy_sq"}

    ok = rollout.replace(crashed=jnp.zeros(3))
    assert float(metrics(env, ok)["crashed"]) == 0.0


def test_closed_loop_rollout_is_consistent_with_metrics(geometric_runs):
    """The per-step error sums that closed_loop records equal ‖p − p_ref‖ at 1 kHz."""
    e, m, _ = geometric_runs["spiral"]
    assert m["tracking_error"] == pytest.approx(float(e.sum()), rel=1e-4)
    assert m["rmse"] == pytest.approx(math.sqrt(float(np.mean(e**2))), rel=1e-4)
    assert m["max_error"] == pytest.approx(float(e.max()), rel=1e-5)
