"""Brax's own PPO (or SAC) on the tracking env, judged by the project's evaluator.

Trains ``brax.training.agents.ppo.train`` (``--algo sac``: ``sac.train``) on the env of the
``fast`` preset (``practical``: 10 ms actions, 50 ms look-ahead, track-frame observation,
hover-centred thrust; training-track mixture, OU wind 0.2 m/s²; 300 control steps per
episode), with ``ttd3_jax.interop.brax_compat.install()`` so that Brax 0.14 runs on JAX 0.10. The
deterministic policy (tanh of the Gaussian's mean) then becomes a controller through
``control.closed_loop.policy_controller`` and is evaluated as ``python -m ttd3_jax.evaluate``
evaluates one: Spiral-RT and LOS-RT seed 0 under the paper's protocol (3000 physics steps from
rest, no early termination), the usual table, and Σ‖e‖ mean ± std over LOS-RT seeds 1-20.

    python experiments/brax_trainers.py                  # PPO, 3M env steps
    python experiments/brax_trainers.py --algo sac       # SAC, 200k env steps
    python experiments/brax_trainers.py --quick          # a smoke run (tiny budget, ~1 min)
    python experiments/brax_trainers.py --steps 500000   # another budget

It writes ``{algo}.json`` (``{algo}_quick.json``) into ``--out`` (default
``results/brax_trainers``): command, device, date, the trainer's settings, its progress
(steps, eval reward) and the evaluation. Brax's trainers have their own networks, losses
and loops: this is a baseline of off-the-shelf RL on the same env, not T-TD3.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import sys
import time

import jax
from brax.training.agents.ppo import train as ppo
from brax.training.agents.sac import train as sac

from ttd3_jax.control.closed_loop import policy_controller
from ttd3_jax.control.evaluator import Evaluator, evaluate_controller, los_statistics
from ttd3_jax.interop import brax_compat
from ttd3_jax.run import report
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv

_COMMON = dict(discounting=0.99, reward_scaling=0.1, normalize_observations=True)
SETTINGS = {
    "ppo": dict(num_timesteps=3_000_000, num_envs=128, batch_size=128, num_minibatches=8, unroll_length=20,
                num_updates_per_batch=4, learning_rate=3e-4, entropy_cost=1e-3, num_evals=10,
                num_eval_envs=64, **_COMMON),
    "sac": dict(num_timesteps=200_000, num_envs=32, batch_size=256, grad_updates_per_step=8,
                min_replay_size=8192, max_replay_size=2**19, learning_rate=3e-4, num_evals=10,
                num_eval_envs=64, **_COMMON),
}  # fmt: skip
QUICK = {
    "ppo": dict(num_timesteps=4096, num_envs=16, batch_size=16, num_minibatches=4, unroll_length=8,
                num_updates_per_batch=1, num_evals=2, num_eval_envs=4),
    "sac": dict(num_timesteps=2048, num_envs=16, batch_size=64, grad_updates_per_step=1, min_replay_size=256,
                max_replay_size=8192, num_evals=2, num_eval_envs=4),
}  # fmt: skip
TRAINERS = {"ppo": lambda: ppo.train, "sac": lambda: sac.train}


def train(algo: str, quick: bool, seed: int, steps: int | None = None):
    """``(env config, make_policy, params, settings, progress)`` of one Brax training run."""
    cfg = make_config("practical", hover_centered_thrust=True)
    settings = SETTINGS[algo] | (QUICK[algo] if quick else {}) | dict(seed=seed)
    if steps is not None:
        settings["num_timesteps"] = steps
    brax_compat.install()  # Brax's trainers call jax.device_put_replicated
    progress, t0 = [], time.perf_counter()

    def log(step, metrics):
        reward, length = (
            float(metrics.get(f"eval/{k}", "nan")) for k in ("episode_reward", "avg_episode_length")
        )
        wall = time.perf_counter() - t0
        progress.append(dict(step=int(step), eval_reward=reward, eval_episode_length=length, wall_s=wall))
        print(
            f"  {algo} step {int(step):>9}  eval reward {reward:10.2f}  length {length:5.1f}  {wall:7.1f} s"
        )

    make_policy, params, _ = TRAINERS[algo]()(
        TrackingEnv(cfg), episode_length=cfg.episode_length, progress_fn=log, **settings
    )
    return cfg, make_policy, params, settings, progress


def evaluate(cfg, make_policy, params, los_seeds) -> tuple[dict, dict]:
    """The deterministic policy on the test tracks: ``(table results, LOS-RT statistics)``."""
    key = jax.random.PRNGKey(0)  # unused by the deterministic policy

    def build(theta):
        return policy_controller(lambda obs: make_policy(theta, deterministic=True)(obs, key)[0])

    ev = Evaluator(TrackingEnv(cfg.for_eval("los_rt")), build)
    results, _ = evaluate_controller(ev, params, timing=False)
    return results, los_statistics(ev, params, los_seeds)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algo", choices=sorted(TRAINERS), default="ppo", help="Brax trainer (default ppo)")
    ap.add_argument("--quick", action="store_true", help="tiny budget, to keep the script alive in CI")
    ap.add_argument("--out", default="results/brax_trainers", help="output directory")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=None, help="env steps (default: the algorithm's budget)")
    args = ap.parse_args(argv)
    if args.steps is not None and args.steps < 1:
        ap.error(f"--steps must be >= 1, got {args.steps}")
    command = "python experiments/brax_trainers.py " + " ".join(map(shlex.quote, argv or sys.argv[1:]))
    device = report.device_description()
    print(f"{command}\ndevice={device}")
    t0 = time.perf_counter()
    cfg, make_policy, params, settings, progress = train(args.algo, args.quick, args.seed, args.steps)
    train_s = time.perf_counter() - t0
    los_seeds = range(1, 4) if args.quick else range(1, 21)
    results, los = evaluate(cfg, make_policy, params, los_seeds)
    label = f"brax {args.algo}"
    print(f"trained in {train_s:.0f} s ({settings['num_timesteps']} env steps); evaluation:")
    print(report.format_results({label: results}, timing=False))
    e = los["los_rt"]["tracking_error"]
    print(f"LOS-RT seeds {los_seeds.start}-{los_seeds.stop - 1}: Σ||e|| {e['mean']:.2f} ± {e['std']:.2f}, "
          f"crashed {los['los_rt']['crashed']}")  # fmt: skip
    print(report.format_paper())
    out = dict(command=command, device=device, date=datetime.datetime.now().isoformat(timespec="seconds"),
               algo=args.algo, settings=settings, train_s=train_s, progress=progress, results=results,
               los_statistics=los)  # fmt: skip
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"{args.algo}{'_quick' if args.quick else ''}.json")
    with open(path, "w") as fh:
        json.dump(report.json_safe(out), fh, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
