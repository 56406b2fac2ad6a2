"""Diagnostic: can the ``fast_dpg`` preset's actor represent a precise tracker at all?

Behaviour-clones the geometric controller (ttd3_jax/control/geometric.py) into the same actor the
``fast_dpg`` preset trains (64-64 ReLU MLP, tanh output, running-statistics input
normalisation) and the same observation (the ``practical`` env, track frame).  No RL is
involved: this separates what the observation and the network can express from what the
T-TD3 critic can teach them (docs/results.md).

Data: ``--envs`` episodes of the geometric controller on training-mixture tracks (random
initial states, no wind); the executed action gets N(0, ``--action-noise``) so that the
data covers small deviations, the label is the controller's clean action.  The actor is
fitted by mean squared error with Adam (cosine-decayed from ``--lr``) and evaluated on
Spiral-RT and LOS-RT (seed 0) after each round of ``--steps-per-round`` steps.

    python experiments/bc_geometric.py               # about 1 min on 2 CPU cores
    python experiments/bc_geometric.py --then-ttd3 3 7   # then T-TD3 from the clone (4 min)
    python experiments/bc_geometric.py --quick       # smoke run (CI)

``--then-ttd3 F A`` then hands the clone to the ``fast_dpg`` T-TD3 trainer (the paper's
actor update), after its usual random warm-up: ``F`` epochs with the actor frozen (actor
learning rate 0, so the critics learn the clone's own values on the clone's own data),
then ``A`` epochs of normal T-TD3, with an evaluation after each epoch.  The input
normalisation is frozen at the demonstration data's statistics, so that only the actor
updates can change the policy.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import optax

from ttd3_jax.control.closed_loop import evaluate_on_tracks, policy_controller, test_tracks
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.control.paper import PAPER_TTD3
from ttd3_jax.run import spec as sp
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.td3 import networks
from ttd3_jax.td3.networks import make_networks
from ttd3_jax.td3.trainer import seed_keys, with_actor


def collect(env: TrackingEnv, key: jax.Array, n_envs: int, noise: float):
    """Observations (n_envs·T, 17) and the geometric controller's actions (n_envs·T, 4)."""
    geo = geometric_controller(env.config)

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
        out.append(float(evaluate_on_tracks(env, controller, test_tracks(env))["tracking_error"][i]))
    return out[0], out[1]


def clone_controller(nets, params, stats):
    """The cloned actor as a controller (raw observations, normalised by ``stats``)."""
    return policy_controller(lambda obs: networks.policy(nets, params, stats, obs))


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
    ap.add_argument("--then-ttd3", type=int, nargs=2, metavar=("FROZEN", "ACTOR"), default=None,
                    help="then train the clone with the fast_dpg T-TD3 preset: FROZEN epochs critic-only, "
                    "ACTOR epochs in full")  # fmt: skip
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    args = ap.parse_args(argv)
    if args.quick:
        args.envs, args.rounds, args.steps_per_round = 8, 1, 50
        args.then_ttd3 = (1, 1) if args.then_ttd3 else None
    if args.then_ttd3 and min(args.then_ttd3) < 0:
        ap.error(f"--then-ttd3 epochs must be >= 0, got {args.then_ttd3}")
    for name in ("envs", "rounds", "steps_per_round", "batch"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.action_noise < 0 or args.lr <= 0:
        ap.error("--action-noise must be >= 0 and --lr > 0")

    t0 = time.perf_counter()
    cfg = make_config("practical", hover_centered_thrust=True, wind_sigma=0.0)
    key_data, key_init, key_fit = jax.random.split(jax.random.PRNGKey(args.seed), 3)
    obs, act = collect(TrackingEnv(cfg), key_data, args.envs, args.action_noise)
    stats = networks.update_obs_stats(networks.init_obs_stats(obs.shape[-1]), obs)
    x = networks.normalize(stats, obs)
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

    geo = test_errors(cfg, geometric_controller(cfg))
    print(f"geometric controller (the teacher): Spiral-RT {geo[0]:.2f}  LOS-RT {geo[1]:.2f}")
    print(f"{'round':>5} {'fit steps':>9} {'MSE':>9} {'Spiral-RT':>10} {'LOS-RT':>9} {'wall s':>7}")
    for r, k in enumerate(jax.random.split(key_fit, args.rounds)):
        params, opt_state, loss = fit(params, opt_state, k)
        spiral, los = test_errors(cfg, clone_controller(nets, params, stats))
        steps, wall = (r + 1) * args.steps_per_round, time.perf_counter() - t0
        print(f"{r + 1:>5} {steps:>9} {float(loss):>9.2e} {spiral:>10.2f} {los:>9.2f} {wall:>7.1f}")
    paper = PAPER_TTD3["spiral_tracking_error"], PAPER_TTD3["los_tracking_error"]
    print(f"paper T-TD3: Spiral-RT {paper[0]}  LOS-RT {paper[1]}")
    if args.then_ttd3:
        then_ttd3(params, stats, tuple(args.hidden), *args.then_ttd3, quick=args.quick, t0=t0)
    return 0


def then_ttd3(actor, stats, hidden, frozen: int, full: int, quick: bool, t0: float) -> None:
    """The clone as the starting actor of the ``fast_dpg`` T-TD3 trainer (see the docstring)."""
    over = dict(hidden=hidden)
    if quick:
        over.update(num_envs=16, total_transitions=16 * 40, warmup_transitions=16 * 8, buffer_size=16 * 64,
                    batch_size=64, updates_per_step=2, epochs=2)  # fmt: skip
    s = sp.preset("fast_dpg", **over)
    t = sp.trainer_for(s)
    ts = jax.jit(t.init)(seed_keys(s.seed, s.num_seeds)[0], s.hp)
    big = 1e12  # a count this large freezes the running statistics
    frozen_stats = networks.ObsStats(count=jnp.asarray(big), mean=stats.mean, m2=stats.m2 / stats.count * big)
    ts = with_actor(t.setup, ts, actor, s.hp).replace(obs_stats=frozen_stats)
    evaluate, epoch = jax.jit(t.evaluate), jax.jit(t.epoch)
    no_actor = s.hp.replace(lr_actor=0.0)
    print(f"T-TD3 (fast_dpg preset) from the clone: {frozen} epoch(s) critic-only, then {full} in full")
    print(f"{'epoch':>5} {'actor':>6} {'σ':>9} {'Spiral-RT':>10} {'LOS-RT':>9} {'val':>9} {'wall s':>7}")

    def show(e, actor_state, sigma, m):
        errs = (float(m[f"{k}_tracking_error"]) for k in ("spiral", "los", "val"))
        print("{:>5} {:>6} {:>9.2e} {:>10.2f} {:>9.2f} {:>9.2f}".format(e, actor_state, float(sigma), *errs),
              f"{time.perf_counter() - t0:>7.1f}")  # fmt: skip

    show(0, "-", ts.noise.sigma, jax.device_get(evaluate(ts)))
    for e in range(frozen + full):
        learn = e >= frozen
        ts, mm = epoch(ts, s.hp if learn else no_actor)
        show(e + 1, "on" if learn else "frozen", mm["sigma"], jax.device_get(evaluate(ts)))


if __name__ == "__main__":
    raise SystemExit(main())
