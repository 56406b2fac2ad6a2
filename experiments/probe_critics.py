"""What a quadrotor run's twin critics say at an evaluation's start state, and what
follows from it in closed loop (docs/results.md).

    python experiments/probe_critics.py RUN_DIR [--epoch N] [--seed-index I] [--track spiral_rt]

Loads the run's checkpoint (default: the latest), resets the evaluation env of ``--track``
(on the track, at rest and level, as every evaluation starts; ``validation`` is the first
validation track drawn with ``PRNGKey(0)``, which is stationary for runs trained on
stationary references), and prints both critics' values, in the run's reward scale
(``hp.reward_scale``), for the policy's action and for the hover action, and the largest
change of each critic when one component of the policy's action moves by ``±--delta``
(clipped to [-1, 1]).  Compare that change with the critic loss in the run's
``metrics.csv``: a change below the fitting error is a difference the critics cannot
resolve, and an actor that follows ∂Q/∂a cannot learn from it.  Then it flies the episode
from that state twice, with the policy and with the hover action held, and prints Σ‖e‖ (m,
over the physics steps, as every evaluation) and the final error of each.
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.control.closed_loop import closed_loop, hover_controller, metrics, policy_controller
from ttd3_jax.run.rundir import load_train_state
from ttd3_jax.sim.env import TrackingEnv, hover_action
from ttd3_jax.td3 import networks
from ttd3_jax.td3.networks import twin_q
from ttd3_jax.td3.trainer import act

TRACKS = ("spiral_rt", "los_rt", "validation")


def probe(run_dir: str, epoch: int | None = None, seed_index: int = 0, track: str = "spiral_rt",
          delta: float = 0.5) -> dict:  # fmt: skip
    """``{"policy": a, "hover": a, "q_policy": (Q1, Q2), "q_hover": (Q1, Q2),
    "max_dq": (max |ΔQ1|, max |ΔQ2|)}`` at the start state of ``track``, and the closed-loop
    ``"error_policy"`` / ``"error_hover"`` (Σ‖e‖, m) and ``"final_error_policy"`` /
    ``"final_error_hover"`` (m) from there (host floats)."""
    loaded = load_train_state(run_dir, epoch)
    spec, trainer = loaded.spec, loaded.trainer
    if not spec.is_quadrotor:
        raise ValueError(f"{run_dir!r} is a {spec.env!r} run; the probe reads quadrotor runs")
    if not 0 <= seed_index < spec.num_seeds:
        raise ValueError(f"seed_index must be in [0, {spec.num_seeds}), got {seed_index}")
    cfg = spec.task
    env = TrackingEnv(cfg.for_eval(track))
    s0 = env.reset(jax.random.PRNGKey(0))
    st = jax.tree.map(lambda x: x[seed_index], loaded.state)
    stats = st.obs_stats if spec.train.normalize_obs else None
    nets = trainer.nets
    a_pi = networks.policy(nets, st.actor, stats, s0.obs)
    a_hover = hover_action(cfg).astype(a_pi.dtype)

    def q(a):
        return twin_q(nets, st.critic, stats, s0.obs, a)

    steps = jnp.concatenate([delta * jnp.eye(4), -delta * jnp.eye(4)])
    moved = jnp.clip(a_pi[None] + steps, -1.0, 1.0)
    dq = jnp.abs(jax.vmap(q)(moved) - q(a_pi)[None])  # (8, 2)
    out = dict(policy=a_pi, hover=a_hover, q_policy=q(a_pi), q_hover=q(a_hover), max_dq=dq.max(0))
    policy = policy_controller(lambda o: act(trainer.setup, st.actor, stats, o))
    controllers = {"policy": policy, "hover": hover_controller(cfg)}
    for name, ctrl in controllers.items():
        r = jax.jit(lambda s, ctrl=ctrl: closed_loop(env, ctrl, s))(s0)
        out[f"error_{name}"] = metrics(env, r)["tracking_error"]
        out[f"final_error_{name}"] = jnp.linalg.norm(r.pos[-1] - r.ref[-1])
    return {k: np.asarray(v).tolist() for k, v in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir")
    ap.add_argument("--epoch", type=int, default=None)
    ap.add_argument("--seed-index", type=int, default=0)
    ap.add_argument("--track", default="spiral_rt", choices=TRACKS)
    ap.add_argument("--delta", type=float, default=0.5, help="action-component step (default 0.5)")
    args = ap.parse_args(argv)
    if not args.delta > 0:
        ap.error(f"--delta must be > 0, got {args.delta}")
    try:
        r = probe(args.run_dir, args.epoch, args.seed_index, args.track, args.delta)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

    def vec(x):
        return "(" + ", ".join(f"{v:.3f}" for v in x) + ")"

    print(f"{args.run_dir} seed index {args.seed_index}, {args.track} start state")
    print(f"{'action':<26} {'a':<34} {'Q1':>8} {'Q2':>8}")
    print(f"{'policy':<26} {vec(r['policy']):<34} {r['q_policy'][0]:>8.3f} {r['q_policy'][1]:>8.3f}")
    print(f"{'hover':<26} {vec(r['hover']):<34} {r['q_hover'][0]:>8.3f} {r['q_hover'][1]:>8.3f}")
    label = f"max |dQ|, one a_i ± {args.delta:g}"
    print(f"{label:<26} {'':<34} {r['max_dq'][0]:>8.3f} {r['max_dq'][1]:>8.3f}")
    for name in ("policy", "hover"):
        print(f"closed loop, {name + ' action':<13} Σ‖e‖ {r['error_' + name]:.2f} m, "
              f"final error {100 * r['final_error_' + name]:.1f} cm")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
