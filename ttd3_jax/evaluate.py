"""Closed-loop evaluation of a controller on the test tracks (spec §2.5).

A controller is a pair of pure functions ``init(env_state) -> carry`` and
``act(carry, env_state) -> (action, carry)`` returning a normalised action (4,).
:func:`closed_loop` runs it for a whole episode as one ``lax.scan``.

CLI::

    python -m ttd3_jax.evaluate --controller geometric        # Spiral-RT and LOS-RT seed 0
    python -m ttd3_jax.evaluate --controller nmpc --nmpc-solve-every 10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from ttd3_jax import trajectories as tr
from ttd3_jax.env import PRESETS, EnvConfig, TrackingEnv, control_to_action, hover_action, make_config
from ttd3_jax.geometric import GeometricGains, geometric_control

CONTROLLERS = ("geometric", "hover", "nmpc")


class Controller(NamedTuple):
    init: Callable  # env State -> carry
    act: Callable  # (carry, env State) -> (action (4,), carry)


@struct.dataclass
class Rollout:
    """One episode, per control step i = 0 … T-1 (T = episode_length)."""

    pos: jax.Array  # (T, 3) m, position after step i
    ref: jax.Array  # (T, 3) m, reference at the same time
    action: jax.Array  # (T, 4) applied normalised action
    error_sum: jax.Array  # (T,) m, Σ ||e|| over the physics steps of control step i
    crashed: jax.Array  # (T,) 1.0 once the tracking error exceeded e_max or went non-finite


def hover_controller(cfg: EnvConfig) -> Controller:
    """Constant hover thrust and zero rates: the do-nothing baseline."""
    a = hover_action(cfg)
    return Controller(init=lambda s: (), act=lambda c, s: (a.astype(s.obs.dtype), c))


def geometric_controller(cfg: EnvConfig, gains: GeometricGains | None = None) -> Controller:
    """:mod:`ttd3_jax.geometric` fed with the analytic reference at the current step."""
    gains = gains or GeometricGains()

    def act(carry, state):
        ps = state.pipeline_state
        p_ref, v_ref, a_ref = tr.evaluate(ps.track, ps.k, cfg.dt)
        u = geometric_control(cfg.quad, gains, ps.quad, p_ref, v_ref, a_ref)
        return control_to_action(cfg, u), carry

    return Controller(init=lambda s: (), act=act)


def closed_loop(env: TrackingEnv, controller: Controller, state) -> Rollout:
    """Run ``env.episode_length`` control steps from ``state`` (pure; jit/vmap it)."""
    c = env.config

    def body(carry, _):
        s, ctrl = carry
        a, ctrl = controller.act(ctrl, s)
        s = env.step(s, a)
        ps = s.pipeline_state
        out = (
            ps.quad.p,
            tr.position(ps.track, ps.k, c.dt),
            jnp.clip(a, -1.0, 1.0),
            s.metrics["tracking_error"],
            s.metrics["crashed"],
        )
        return (s, ctrl), out

    _, (pos, ref, act, err, crash) = jax.lax.scan(
        body, (state, controller.init(state)), None, length=env.episode_length
    )
    return Rollout(pos=pos, ref=ref, action=act, error_sum=err, crashed=jnp.maximum.accumulate(crash))


def metrics(env: TrackingEnv, r: Rollout) -> dict[str, jax.Array]:
    """Spec §2.5: Σ||e|| over physics steps 1…N, RMSE and max error (sampled per control
    step), crash flag, energy Σ||a|| and Σaᵀa over physics steps 0…N-1."""
    rep = env.config.action_repeat
    e = jnp.linalg.norm(r.pos - r.ref, axis=-1)
    a2 = jnp.sum(r.action**2, -1)
    return {
        "tracking_error": jnp.sum(r.error_sum),
        "rmse": jnp.sqrt(jnp.mean(e**2)),
        "max_error": jnp.max(e),
        "crashed": r.crashed[-1],
        "energy": rep * jnp.sum(jnp.sqrt(a2)),
        "energy_sq": rep * jnp.sum(a2),
    }


def test_tracks(env: TrackingEnv, los_seeds=(0,)) -> tr.Track:
    """Spiral-RT followed by the LOS-RT test instances ``los_seeds``, stacked on a leading
    axis with the table size of ``env`` (so one ``vmap`` evaluates them all)."""
    c = env.config
    n = env.num_segments
    tracks = [tr.spiral_rt(c.tracks, n)] + [
        tr.los_test_track(s, c.tracks, num_segments=n, dt=c.dt, horizon_steps=c.horizon_steps)
        for s in los_seeds
    ]
    return jax.tree.map(lambda *x: jnp.stack(x), *tracks)


def evaluate_on_tracks(env: TrackingEnv, controller: Controller, tracks: tr.Track) -> dict:
    """Metrics (each with a leading track axis) of ``controller`` on a batch of tracks,
    with the evaluation start state (on p_d(0), at rest, level)."""
    key = jax.random.PRNGKey(0)

    def one(track):
        return metrics(env, closed_loop(env, controller, env.reset_with_track(key, track)))

    return jax.vmap(one)(tracks)


def make_controller(name: str, cfg: EnvConfig, **options) -> Controller:
    """Controller ``name`` for env config ``cfg``; ``options`` go to the controller's
    config (``nmpc``: fields of :class:`ttd3_jax.nmpc.NMPCConfig`)."""
    if name == "nmpc":
        from ttd3_jax.nmpc import NMPCConfig, nmpc_controller  # nmpc imports this module

        return nmpc_controller(cfg, NMPCConfig(**options))
    if options:
        raise ValueError(f"controller {name!r} takes no options, got {sorted(options)}")
    if name == "geometric":
        return geometric_controller(cfg)
    if name == "hover":
        return hover_controller(cfg)
    raise ValueError(f"unknown controller {name!r}; allowed: {CONTROLLERS}")


def evaluate_track(cfg: EnvConfig, controller_name: str, track: str, los_seed: int = 0, **options):
    """Compile and run one evaluation episode; returns (metrics dict, compile s, run s).
    ``options`` are passed to :func:`make_controller`."""
    env = TrackingEnv(cfg.for_eval(track, los_seed=los_seed, wind_sigma=0.0))
    ctrl = make_controller(controller_name, env.config, **options)

    def run(key):
        r = closed_loop(env, ctrl, env.reset(key))
        return metrics(env, r)

    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(key).compile()
    t_compile = time.perf_counter() - t0
    jax.block_until_ready(compiled(key))
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(key))
    t_run = time.perf_counter() - t0
    return {k: float(v) for k, v in out.items()}, t_compile, t_run


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m ttd3_jax.evaluate",
        description="Run a controller in closed loop on Spiral-RT and LOS-RT and print tracking metrics.",
    )
    ap.add_argument("--controller", default="geometric", choices=CONTROLLERS)
    ap.add_argument("--preset", default="paper", choices=PRESETS, help="environment preset")
    ap.add_argument("--track", default="all", choices=("all", *tr.TEST_TRACKS))
    ap.add_argument("--los-seed", type=int, default=0, help="LOS-RT test instance (0 = headline)")
    ap.add_argument("--json", default=None, help="also write the metrics to this JSON file")
    ap.add_argument("--nmpc-horizon", type=int, default=None, help="NMPC nodes N (nmpc only)")
    ap.add_argument(
        "--nmpc-solve-every", type=int, default=None, help="NMPC control steps between re-solves (nmpc only)"
    )
    ap.add_argument("--nmpc-weight-scale", type=float, default=None, help="NMPC state-weight scale")
    args = ap.parse_args(argv)
    if args.los_seed < 0:
        ap.error(f"--los-seed must be >= 0, got {args.los_seed}")
    options = {
        name: value
        for name, value in (
            ("horizon", args.nmpc_horizon),
            ("solve_every", args.nmpc_solve_every),
            ("weight_scale", args.nmpc_weight_scale),
        )
        if value is not None
    }
    if options and args.controller != "nmpc":
        ap.error("--nmpc-* options need --controller nmpc")
    if options:
        from ttd3_jax.nmpc import NMPCConfig

        try:
            NMPCConfig(**options)
        except ValueError as e:
            ap.error(str(e))
    cfg = make_config(args.preset)
    tracks = tr.TEST_TRACKS if args.track == "all" else (args.track,)
    opts = "".join(f" {k}={v}" for k, v in options.items())
    print(f"controller={args.controller}{opts} preset={args.preset} device={jax.devices()[0].platform}")
    header = f"{'track':<10} {'Σ||e|| [m]':>11} {'RMSE [m]':>9} {'max [m]':>8} {'crash':>5} "
    header += f"{'Σ||a||':>8} {'Σaᵀa':>8} {'compile s':>9} {'run ms':>7}"
    print(header)
    results = {}
    for name in tracks:
        m, tc, trun = evaluate_track(cfg, args.controller, name, args.los_seed, **options)
        results[name] = dict(m, compile_s=tc, run_s=trun)
        print(
            f"{name:<10} {m['tracking_error']:>11.2f} {m['rmse']:>9.4f} {m['max_error']:>8.4f} "
            f"{int(m['crashed']):>5} {m['energy']:>8.1f} {m['energy_sq']:>8.1f} {tc:>9.2f} {1e3 * trun:>7.2f}"
        )
    print("paper T-TD3: Spiral-RT 25.99, LOS-RT 398.74 (Σ||e||); MPC: 78.47, 542.92")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(
                {
                    "controller": args.controller,
                    "options": options,
                    "preset": args.preset,
                    "results": results,
                },
                fh,
                indent=2,
            )
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
