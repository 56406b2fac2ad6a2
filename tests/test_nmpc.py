"""NMPC baseline (``ttd3_jax.control.nmpc``, spec §2.6): closed-loop hover and line tracking on a
tiny horizon, one Gauss-Newton step lowers the cost, warm-start shift, config checks.

Everything runs on CPU with N = 5 nodes so that each test compiles in a few seconds.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import experiment

from ttd3_jax.control.closed_loop import Controller, closed_loop, metrics
from ttd3_jax.control.evaluator import CONTROLLERS, make_controller
from ttd3_jax.control.nmpc import NMPC, NMPCConfig, nmpc_controller, tilt_quaternion
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.dynamics import QuadParams, QuadState, body_z
from ttd3_jax.sim.env import TrackingEnv, action_to_control

# 5 nodes 0.1 s apart: a 0.5 s horizon (the default is 20 × 0.05 s)
SMALL = NMPCConfig(horizon=5, dt_node=0.1, sqp_iters_first=10)
HOVER_OFFSET = (0.2, -0.1, 0.15)  # m


def line_env(episode_steps: int = 1000) -> TrackingEnv:
    """Paper-preset evaluation env, 1 s episodes; tracks come from :func:`line_track`."""
    return TrackingEnv(make_config("paper", episode_steps=episode_steps).for_eval("los_rt"))


def line_track(env: TrackingEnv, speed: float) -> tr.Track:
    """A LOS track with one heading (θ = 0) and one speed: a straight line along x from
    the origin (speed 0: a hover point), built with the public track config.  (Built
    here rather than by ``env.reset``: TrackingEnv sizes LOS tables for 3000-step
    episodes only.)"""
    c = env.config
    tracks = tr.TrackConfig(
        los_speed=(speed, speed), los_theta_max=0.0, los_literal_init=False, los_climb_rate=0.0
    )
    return tr.los_rt(jax.random.PRNGKey(0), tracks, dt=c.dt, horizon_steps=c.horizon_steps)


def start_at(env: TrackingEnv, speed: float, offset=(0.0, 0.0, 0.0)):
    """Evaluation start state on ``line_track(speed)``, moved by ``offset`` m."""
    s = env.reset_with_track(jax.random.PRNGKey(0), line_track(env, speed))
    ps = s.pipeline_state
    quad = ps.quad.replace(p=ps.quad.p + jnp.asarray(offset, ps.quad.p.dtype))
    return s.replace(pipeline_state=ps.replace(quad=quad))


@pytest.fixture(scope="module")
def hover_and_line():
    """Closed loops of the small NMPC (one compile, vmapped over the two cases): a hover
    point with a 0.27 m initial offset, and a 1 m/s line started at rest on p_d(0)."""
    env = line_env()
    ctrl = nmpc_controller(env.config, SMALL)
    starts = [start_at(env, 0.0, HOVER_OFFSET), start_at(env, 1.0)]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *starts)

    def run(s):
        r = closed_loop(env, ctrl, s)
        return r, metrics(env, r)

    r, m = jax.jit(jax.vmap(run))(batch)
    out = {}
    for i, name in enumerate(("hover", "line")):
        e = np.linalg.norm(np.asarray(r.pos[i] - r.ref[i]), axis=-1)
        out[name] = (e, {k: float(v[i]) for k, v in m.items()}, np.asarray(r.action[i]))
    return out


def test_nmpc_recovers_and_holds_hover(hover_and_line):
    e, m, a = hover_and_line["hover"]
    e0 = float(np.linalg.norm(HOVER_OFFSET))
    assert m["crashed"] == 0 and np.all(np.isfinite(e))
    assert e.max() <= e0 + 0.01  # no overshoot beyond the start offset
    assert e[-1] < e[750] < e[500] < e[250] < e0  # converges
    assert e[750:].max() < 0.03
    assert e[-1] < 0.01
    assert np.all(np.abs(a) <= 1.0)


def test_nmpc_tracks_straight_line(hover_and_line):
    e, m, _ = hover_and_line["line"]
    # the reference starts at 1 m/s while the vehicle is at rest: a lag transient, then tight tracking
    assert m["crashed"] == 0
    assert e.max() < 0.2
    assert e[750:].max() < 0.03
    assert e[-1] < 0.01
    assert m["tracking_error"] < 100.0  # Σ over 1000 steps: a mean error below 10 cm


def test_single_solve_decreases_cost_and_respects_bounds():
    env = line_env()
    mpc = NMPC(env.config, SMALL)
    s = start_at(env, 1.0, (0.1, 0.05, -0.1))
    ps = s.pipeline_state

    @jax.jit
    def one_and_many(x0, track, k):
        ref = mpc.references(track, k)
        U0 = ref.u
        c0 = mpc.cost(x0, ref, U0)
        U1, c1 = mpc.gn_step(x0, ref, U0)
        U10, c10 = mpc.solve(x0, ref, U0, 10)
        return c0, U1, c1, mpc.cost(x0, ref, U1), U10, c10

    c0, U1, c1, c1_true, U10, c10 = one_and_many(ps.quad, ps.track, ps.k)
    assert float(c1) < float(c0)  # one Gauss-Newton step (from the warm start U_ref)
    assert float(c10) <= float(c1)
    np.testing.assert_allclose(float(c1), float(c1_true), rtol=1e-5)
    q = env.config.vehicle.quad
    for U in (np.asarray(U1), np.asarray(U10)):
        assert U.shape == (5, 4)
        assert np.all(U[:, 0] >= q.thrust_min - 1e-5) and np.all(U[:, 0] <= q.thrust_max + 1e-5)
        assert np.all(np.abs(U[:, 1:]) <= q.rate_max + 1e-5)


def test_references_follow_flatness():
    env = TrackingEnv(make_config("paper").for_eval("spiral_rt"))
    mpc = NMPC(env.config, NMPCConfig(horizon=4, dt_node=0.05))
    track = env.sample_track(jax.random.PRNGKey(0))
    ref = jax.jit(mpc.references)(track, jnp.asarray(1000, jnp.int32))
    ks = 1000 + 50 * np.arange(5)  # node times: physics steps k + i·dt_node/dt
    p, v, a = (np.asarray(x, np.float64) for x in tr.evaluate(track, ks, 1e-3))
    np.testing.assert_allclose(ref.pos, p[1:], atol=1e-6)
    np.testing.assert_allclose(ref.vel, v[1:], atol=1e-6)
    thrust_acc = a + np.array([0.0, 0.0, 9.81])
    z = thrust_acc / np.linalg.norm(thrust_acc, axis=-1, keepdims=True)
    np.testing.assert_allclose(body_z(ref.quat), z[1:], atol=1e-6)
    assert np.all(np.asarray(ref.quat)[:, 3] == 0)  # zero heading: no rotation about z
    f0 = 1.5 * np.linalg.norm(thrust_acc[:-1], axis=-1)
    np.testing.assert_allclose(ref.u[:, 0], f0, rtol=1e-6)  # newton units: m‖a_ref + g‖
    np.testing.assert_allclose(ref.u[:, 1:], 0.0)
    np.testing.assert_allclose(body_z(tilt_quaternion(jnp.array([0.0, 0.0, 1.0]))), [0, 0, 1], atol=1e-7)


def test_warm_start_shift_and_plan_hold():
    mpc = NMPC(make_config("paper"), NMPCConfig(horizon=4, dt_node=0.05))
    U = jnp.arange(16.0).reshape(4, 4)
    np.testing.assert_allclose(mpc.shift(U, 0.0), U)
    np.testing.assert_allclose(mpc.shift(U, 0.05), jnp.concatenate([U[1:], U[-1:]]), atol=1e-6)
    np.testing.assert_allclose(mpc.shift(U, 0.025)[0], 0.5 * (U[0] + U[1]), atol=1e-6)
    np.testing.assert_allclose(mpc.plan_input(U, 0.049), U[0])
    np.testing.assert_allclose(mpc.plan_input(U, 0.05), U[1])
    np.testing.assert_allclose(mpc.plan_input(U, 10.0), U[-1])


def test_solve_every_holds_the_plan_between_solves():
    env = line_env(episode_steps=20)
    ctrl = nmpc_controller(env.config, dataclasses.replace(SMALL, solve_every=5, sqp_iters_first=2))
    s = start_at(env, 0.0, (0.1, 0.0, 0.0))
    act, step = jax.jit(ctrl.act), jax.jit(env.step)
    carry = ctrl.init(s)
    solves, actions = [], []
    for _ in range(12):
        a, carry = act(carry, s)
        s = step(s, a)
        solves.append(int(carry.solves))
        actions.append(np.asarray(a))
    assert solves == [1] * 5 + [2] * 5 + [3] * 2
    # between solves the first node's input is held (its interval is 100 steps long)
    np.testing.assert_allclose(actions[1], actions[0])
    u = action_to_control(env.config, jnp.asarray(actions[-1]))
    np.testing.assert_allclose(u, carry.plan[0], rtol=1e-5, atol=1e-5)  # applied = first node of the plan


def test_registered_in_evaluate():
    assert "nmpc" in CONTROLLERS
    cfg = make_config("paper")
    assert isinstance(make_controller("nmpc", cfg, horizon=5), Controller)
    with pytest.raises(ValueError, match="takes no options"):
        make_controller("geometric", cfg, horizon=5)
    with pytest.raises(ValueError, match="horizon"):
        make_controller("nmpc", cfg, horizon=0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(horizon=0), r"horizon must be an integer in \[1, 500\]"),
        (dict(horizon=2.5), "horizon"),
        (dict(horizon=True), "horizon"),
        (dict(dt_node=0.0), r"dt_node must be a finite number in \(0, 1\], got 0.0"),
        (dict(dt_node=float("nan")), "dt_node"),
        (dict(w_pos=(200.0, 200.0)), "w_pos must be 3 finite numbers > 0"),
        (dict(w_pos=(200.0, 0.0, 500.0)), "w_pos"),
        (dict(w_vel=(-1.0, 10.0, 10.0)), "w_vel must be 3 finite numbers >= 0"),
        (dict(w_att=(50.0, 50.0, float("inf"))), "w_att"),
        (dict(w_input=(0.1, 0.1, 0.1)), "w_input must be 4"),
        (dict(weight_scale=0.0), "weight_scale"),
        (dict(weight_scale=-1.0), "weight_scale"),
        (dict(sqp_iters_first=0), "sqp_iters_first"),
        (dict(sqp_iters=0), "sqp_iters"),
        (dict(qp_iters=0), "qp_iters"),
        (dict(solve_every=0), "solve_every"),
        (dict(node_substeps=0), "node_substeps"),
        (dict(loop_substeps=0), "loop_substeps"),
        (dict(regularization=-1e-6), "regularization"),
        (dict(line_search="yes"), "line_search"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NMPCConfig(**kwargs)


def test_default_config_matches_spec():
    c = NMPCConfig()
    assert (c.horizon, c.dt_node) == (20, 0.05)
    assert c.w_pos == (200.0, 200.0, 500.0) and c.w_vel == (10.0, 10.0, 10.0)
    assert c.w_att == (50.0, 50.0, 5.0) and c.w_input == (0.1, 0.1, 0.1, 0.1)
    assert (c.sqp_iters_first, c.sqp_iters, c.qp_iters) == (30, 1, 8)
    assert c.solve_every == 1 and c.line_search
    assert c.weight_scale == 4.0  # tuned on the validation tracks (experiments/tune_nmpc.py)


def test_cost_is_zero_on_an_exact_hover_plan():
    env = line_env()
    mpc = NMPC(env.config, SMALL)
    ps = start_at(env, 0.0).pipeline_state
    ref = mpc.references(ps.track, ps.k)
    assert float(mpc.cost(QuadState.hover(ref.pos[0]), ref, ref.u)) < 1e-8


def test_linearize_matches_jacfwd_through_the_rollout():
    env = line_env()
    mpc = NMPC(env.config, SMALL)
    ps = start_at(env, 1.0, (0.1, 0.05, -0.1)).pipeline_state
    ref = mpc.references(ps.track, ps.k)
    U = ref.u + 0.3 * jax.random.normal(jax.random.PRNGKey(1), ref.u.shape)
    r, J = jax.jit(mpc.linearize)(ps.quad, ref, U)
    res = lambda u: mpc.state_residual(ps.quad, ref, u.reshape(U.shape))
    np.testing.assert_allclose(r, res(U.reshape(-1)), atol=1e-5)
    J_ref = jax.jacfwd(res)(U.reshape(-1))
    assert J.shape == (45, 20)
    np.testing.assert_allclose(J, J_ref, atol=1e-5 * float(jnp.abs(J_ref).max()))


def _fista(H, g, lo, hi, iters=20_000):
    """Reference box-QP solution: plain projected gradient with momentum, float64."""
    L = np.linalg.eigvalsh(H).max()
    z = y = np.zeros_like(g)
    t = 1.0
    for _ in range(iters):
        z_new = np.clip(y - (H @ y + g) / L, lo, hi)
        t_new = 0.5 * (1 + np.sqrt(1 + 4 * t * t))
        y = z_new + (t - 1) / t_new * (z_new - z)
        z, t = z_new, t_new
    return z


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_box_qp_solves_random_box_qps(seed):
    """Projected Newton against a long FISTA run on a box QP with active bounds."""
    rng = np.random.default_rng(seed)
    n = 12
    M = rng.normal(size=(2 * n, n))
    H = M.T @ M + 0.1 * np.eye(n)
    g = rng.normal(size=n) * 20.0
    lo, hi = -rng.uniform(0.1, 1.0, n), rng.uniform(0.1, 1.0, n)
    z_ref = _fista(H, g, lo, hi)
    assert np.sum((z_ref <= lo + 1e-9) | (z_ref >= hi - 1e-9)) >= 3  # the bounds matter
    mpc = NMPC(make_config("paper"), NMPCConfig(horizon=3, qp_iters=20))
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    z = np.asarray(jax.jit(mpc._box_qp)(f32(H), f32(g), f32(lo), f32(hi)))
    assert np.all(z >= lo - 1e-6) and np.all(z <= hi + 1e-6)
    np.testing.assert_allclose(z, z_ref, atol=1e-4)
    obj = lambda x: 0.5 * x @ H @ x + g @ x
    assert obj(z.astype(np.float64)) <= obj(z_ref) + 1e-5 * abs(obj(z_ref))


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_tune_nmpc_on_the_wide_validation_tracks(tmp_path, capsys):
    """``--wide`` tunes on the robust preset's validation bank (its first family: the paper
    mixture's dynamics tracks), and --num-tracks is bounded by that bank's 18."""
    import json

    tune = experiment("tune_nmpc")
    out = tmp_path / "tune.json"
    args = ["--wide", "--num-tracks", "1", "--horizons", "5", "--scales", "1", "--json", str(out)]
    assert tune.main(args) == 0
    d = json.loads(out.read_text())
    assert d["wide"] is True and d["tracks"] == ["dynamics"]
    (row,) = d["rows"]
    assert row["crashes"] == 0 and 0 < row["mean_error"] < 100  # a 3000-step track, tracked
    with pytest.raises(SystemExit):
        tune.main(["--wide", "--num-tracks", "19"])
    assert "--num-tracks must be in [1, 18], got 19" in capsys.readouterr().err


def test_the_nmpc_models_a_firmware_vehicle_with_its_loop_and_senses_only_the_rigid_body():
    from ttd3_jax.control.nmpc import models_loop, rigid_body
    from ttd3_jax.sim.dynamics import model_state
    from ttd3_jax.sim.vehicles import CF2

    assert models_loop(CF2) and not models_loop(QuadParams())
    x = rigid_body(model_state(CF2, QuadState.hover((1.0, 2.0, 3.0))))
    assert type(x) is QuadState and tuple(np.asarray(x.p)) == (1.0, 2.0, 3.0)
