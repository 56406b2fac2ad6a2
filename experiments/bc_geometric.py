"""Diagnostic: can the ``fast`` preset's actor represent a precise tracker at all?

Behaviour-clones the geometric controller (ttd3_jax/geometric.py) into the same actor the
``fast`` preset trains (64-64 ReLU MLP, tanh output, running-statistics input
normalisation) and the same observation (the ``practical`` env, track frame).  No RL is
involved: this separates what the observation and the network can express from what the
T-TD3 critic can teach them (docs/results.md).

Data: ``--envs`` episodes of the geometric controller on training-mixture tracks (random
initial states, no wind); the executed action gets N(0, ``--action-noise``) so that the
data covers small deviations, the label is the controller's clean action.  The actor is
fitted by mean squared error with Adam (cosine-decayed from ``--lr``) and evaluated on
Spiral-RT and LOS-RT (seed 0) after each round of ``--steps-per-round`` steps.

    python experiments/bc_geometric.py               # about 1.5 min on 2 CPU cores
    python experiments/bc_geometric.py --quick       # smoke run (CI)
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import optax

from ttd3_jax import evaluate as E
from ttd3_jax import normalize as nrm
from ttd3_jax.env import TrackingEnv, make_config
from ttd3_jax.networks import make_networks
from ttd3_jax.train import policy_controller


def collect(env: TrackingEnv, key: jax.Array, n_envs: int, noise: float):
    """Observations (n_envs·T, 17) and the geometric controller's actions (n_envs·T, 4)."""
    geo = E.geometric_controller(env.config)

    def episode(k):
        k_reset, k_noise = jax.random.split(k)

        def body(s, kn):
            a = jnp.clip(geo.act((), s)[0], -1.0, 1.0)
            executed = jnp.clip(a + noise * jax.random.normal(kn, (4,)), -1.0, 1.0)
            return env.step(s, executed), (s.obs, a)

        keys = jax.random.split(k_noise, env.episode_length)
        return jax.lax.scan(body, env.reset(k_reset), keys)[1]

    obs, act = jax.jit(jax.vmap(episode))(jax.random.split(key, n_envs))
    return obs.reshape(-1, obs.shape[-1]), act.reshape(-1, act.shape[-1])


def test_errors(cfg, controller) -> tuple[float, float]:
    """Σ‖e‖ on Spiral-RT and on LOS-RT seed 0 (the paper's protocol)."""
    out = []
    for i, track in enumerate(("spiral_rt", "los_rt")):
        env = TrackingEnv(cfg.for_eval(track))
        out.append(float(E.evaluate_on_tracks(env, controller, E.test_tracks(env))["tracking_error"][i]))
    return out[0], out[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", type=int, default=512, help="episodes of demonstration data")
    ap.add_argument("--action-noise", type=float, default=0.1, help="std added to the executed action")
    ap.add_argument("--hidden", type=int, nargs="+", default=[64, 64])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps-per-round", type=int, default=10_000)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    args = ap.parse_args(argv)
    if args.quick:
        args.envs, args.rounds, args.steps_per_round = 8, 1, 50
    for name in ("envs", "rounds", "steps_per_round", "batch"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.action_noise < 0 or args.lr <= 0:
        ap.error("--action-noise must be >= 0 and --lr > 0")

    t0 = time.perf_counter()
    cfg = make_config("practical", hover_centered_thrust=True, wind_sigma=0.0)
    key_data, key_init, key_fit = jax.random.split(jax.random.PRNGKey(args.seed), 3)
    obs, act = collect(TrackingEnv(cfg), key_data, args.envs, args.action_noise)
    stats = nrm.update(nrm.init(obs.shape[-1]), obs)
    x = nrm.apply(stats, obs)
    nets = make_networks(4, tuple(args.hidden))
    params = nets.actor.init(key_init, x[:1])
    opt = optax.adam(optax.cosine_decay_schedule(args.lr, args.rounds * args.steps_per_round))
    opt_state = opt.init(params)
    print(f"{obs.shape[0]} demonstration steps collected in {time.perf_counter() - t0:.1f} s")

    @jax.jit
    def fit(params, opt_state, key):
        def step(carry, k):
            p, s = carry
            i = jax.random.randint(k, (args.batch,), 0, x.shape[0])
            loss, g = jax.value_and_grad(lambda p: jnp.mean((nets.actor.apply(p, x[i]) - act[i]) ** 2))(p)
            u, s = opt.update(g, s, p)
            return (optax.apply_updates(p, u), s), loss

        (p, s), losses = jax.lax.scan(step, (params, opt_state), jax.random.split(key, args.steps_per_round))
        return p, s, losses[-100:].mean()

    geo = test_errors(cfg, E.geometric_controller(cfg))
    print(f"geometric controller (the teacher): Spiral-RT {geo[0]:.2f}  LOS-RT {geo[1]:.2f}")
    print(f"{'round':>5} {'fit steps':>9} {'MSE':>9} {'Spiral-RT':>10} {'LOS-RT':>9} {'wall s':>7}")
    for r, k in enumerate(jax.random.split(key_fit, args.rounds)):
        params, opt_state, loss = fit(params, opt_state, k)
        sp, los = test_errors(cfg, policy_controller(nets, params, stats))
        steps, wall = (r + 1) * args.steps_per_round, time.perf_counter() - t0
        print(f"{r + 1:>5} {steps:>9} {float(loss):>9.2e} {sp:>10.2f} {los:>9.2f} {wall:>7.1f}")
    print("paper T-TD3: Spiral-RT 25.99  LOS-RT 398.74")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
