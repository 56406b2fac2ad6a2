"""TD3 trainer throughput against rejax, sbx and Stable-Baselines3, side by side in one run.

Equal settings for every framework: TD3, 1 env, 1 gradient update per env step (policy
delay 2), batch 256, the same MLP widths for actor and critics (ReLU), a 100k replay
buffer, 1000 uniform-random warm-up steps (not timed).  Then ``--steps`` env steps, each
followed by one update, are timed; best of ``--repeats``, the frameworks interleaved.
Each peer runs in its own worker process (``_peers.py``); ours runs in this process.

    python benchmarks/peer_trainer_throughput.py           # the study in docs/performance.md
    python benchmarks/peer_trainer_throughput.py --quick   # smoke run (CI): small nets, ~2k steps

Envs:
  pendulum   Pendulum-v1.  rejax: gymnax's; sbx and SB3: Gymnasium's; ours: a Brax-style
             port of the same equations (``PendulumV1`` below, actions in [-1, 1] scaled
             to +-2 N m), given to our trainer in place of a Brax env.
  quadrotor  our tracking env (``paper`` preset: 1 kHz, OU wind).  rejax gets it through a
             thin gymnax adapter (gymnax's ``step`` computes a reset every step and selects
             it where done: that is how gymnax envs auto-reset); sbx and SB3 through a
             Gymnasium adapter (one jitted single-env step per call, arrays to numpy).

What is timed: ours, one compiled epoch (``Trainer.epoch``); rejax, its compiled ``train``
continued from the warmed-up state with evaluation switched off; sbx and SB3,
``model.learn(steps, reset_num_timesteps=False)`` after the warm-up and a first short
``learn`` that triggers sbx's JIT compilation.

Rows at the end (``design``) show what our design adds in the same units: many envs per
update (64 envs x 16 updates per vector step, as the ``fast_dpg`` preset), and the ``fast``
preset's model-based actor update (a 50-step differentiable rollout of the 64 envs per
vector step, whose 3200 transitions all enter the buffer, then 16 critic updates).
"""

from __future__ import annotations

import argparse
import os
import sys

import _peers

WARMUP = 1_000
BUFFER = 100_000
FIRST = 20  # sbx / SB3: env steps of the first, untimed learn() with updates (JIT compile)


# --------------------------------------------------------------------------- envs


def pendulum_v1():
    """Pendulum-v1 (Gymnasium / gymnax equations) as a Brax-style env for our trainer."""
    import jax
    import jax.numpy as jnp
    from brax.envs.base import State

    class PendulumV1:
        max_speed, max_torque, dt, g, m, l, horizon = 8.0, 2.0, 0.05, 10.0, 1.0, 1.0, 200  # noqa: E741
        observation_size, action_size = 3, 1

        def _obs(self, th, thd):
            return jnp.stack([jnp.cos(th), jnp.sin(th), thd])

        def reset(self, key):
            high = jnp.array([jnp.pi, 1.0])
            th, thd = jax.random.uniform(key, (2,), minval=-high, maxval=high)
            z = jnp.zeros(())
            ps = dict(th=th, thd=thd, t=jnp.zeros((), jnp.int32))
            return State(ps, self._obs(th, thd), z, z, {}, {"truncation": z, "terminated": z})

        def step(self, s, action):
            th, thd, t = s.pipeline_state["th"], s.pipeline_state["thd"], s.pipeline_state["t"]
            u = jnp.clip(action[0] * self.max_torque, -self.max_torque, self.max_torque)
            norm = ((th + jnp.pi) % (2 * jnp.pi)) - jnp.pi
            reward = -(norm**2 + 0.1 * thd**2 + 0.001 * u**2)
            acc = 3 * self.g / (2 * self.l) * jnp.sin(th) + 3.0 / (self.m * self.l**2) * u
            thd = jnp.clip(thd + acc * self.dt, -self.max_speed, self.max_speed)
            th = th + thd * self.dt
            t = t + 1
            trunc = (t >= self.horizon).astype(jnp.float32)
            return s.replace(
                pipeline_state=dict(th=th, thd=thd, t=t),
                obs=self._obs(th, thd),
                reward=reward,
                done=trunc,
                info={"truncation": trunc, "terminated": jnp.zeros_like(trunc)},  # time limit only
            )

    return PendulumV1()


def quadrotor_gymnax():
    """Our tracking env (``paper`` preset) behind gymnax's Environment interface (for rejax)."""
    import jax.numpy as jnp
    from flax import struct
    from gymnax.environments import environment, spaces

    from ttd3_jax.sim.config import make_config
    from ttd3_jax.sim.env import TrackingEnv

    @struct.dataclass
    class Params(environment.EnvParams):
        max_steps_in_episode: int = 3000

    class QuadrotorGymnax(environment.Environment):
        def __init__(self):
            super().__init__()
            self.env = TrackingEnv(make_config("paper"))

        @property
        def default_params(self):
            return Params(max_steps_in_episode=self.env.episode_length)

        def step_env(self, key, state, action, params):
            s = self.env.step(state, action)
            return s.obs, s, s.reward, s.done > 0, {}

        def reset_env(self, key, params):
            s = self.env.reset(key)
            return s.obs, s

        def observation_space(self, params):
            return spaces.Box(-jnp.inf, jnp.inf, (self.env.observation_size,), jnp.float32)

        def action_space(self, params):
            return spaces.Box(-1.0, 1.0, (self.env.action_size,), jnp.float32)

    return QuadrotorGymnax()


def quadrotor_gymnasium():
    """Our tracking env (``paper`` preset) as a Gymnasium env (for sbx and SB3)."""
    import gymnasium as gym
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ttd3_jax.sim.config import make_config
    from ttd3_jax.sim.env import TrackingEnv

    class QuadrotorGym(gym.Env):
        def __init__(self):
            self.env = TrackingEnv(make_config("paper"))
            n, m = self.env.observation_size, self.env.action_size
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (n,), np.float32)
            self.action_space = gym.spaces.Box(-1.0, 1.0, (m,), np.float32)
            self._reset, self._step = jax.jit(self.env.reset), jax.jit(self.env.step)
            self._key = jax.random.PRNGKey(0)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            if seed is not None:
                self._key = jax.random.PRNGKey(seed)
            self._key, k = jax.random.split(self._key)
            self.s = self._reset(k)
            return np.asarray(self.s.obs, np.float32), {}

        def step(self, action):
            self.s = self._step(self.s, jnp.asarray(action, jnp.float32))
            obs, r, d, tr = jax.device_get(
                (self.s.obs, self.s.reward, self.s.done, self.s.info["truncation"])
            )
            return np.asarray(obs, np.float32), float(r), bool(d > 0 and tr == 0), bool(tr > 0), {}

    return QuadrotorGym()


# --------------------------------------------------------------------------- frameworks


def build_ours(env: str, hidden: int, steps: int, num_envs: int = 1, utd: int = 1, preset: str | None = None):
    import time

    import jax

    from ttd3_jax.run import spec as sp
    from ttd3_jax.run import tasks
    from ttd3_jax.sim.config import make_config
    from ttd3_jax.td3.config import Hyper, TrainConfig
    from ttd3_jax.td3.env_spec import EnvSpec
    from ttd3_jax.td3.trainer import make_trainer

    if preset:  # a training preset as it is (64 envs x 16 updates, 64-64); `steps` vector steps
        s = sp.preset(preset, epochs=1, warmup_transitions=4096, buffer_size=BUFFER)
        s = sp.replace(s, total_transitions=4096 + s.train.num_envs * s.train.env_steps_per_step * steps)
        c, hp = s.train, s.hp
        t0 = time.perf_counter()
        tr = sp.trainer_for(s)
    else:
        c = TrainConfig(
            algo="td3",
            num_envs=num_envs,
            updates_per_step=utd,
            batch_size=256,
            hidden=(hidden, hidden),
            warmup_transitions=WARMUP,
            buffer_size=BUFFER,
            total_transitions=-(-WARMUP // num_envs) * num_envs + steps * num_envs,
            epochs=1,
            policy_delay=2,
        )
        hp = Hyper(tau=0.005, sigma=0.1, target_sigma=0.2, target_clip=0.5)
        t0 = time.perf_counter()
        if env == "pendulum":  # in place of a Brax env (never evaluated here)
            spec = EnvSpec(
                pendulum_v1(), 3, 1, 200, evaluate=lambda policy: {}, differentiable=False, actor_obs_size=3
            )
        else:  # the paper preset's env
            spec = tasks.quadrotor(make_config("paper"))
        tr = make_trainer(c, spec)
    ts = jax.block_until_ready(jax.jit(tr.init)(jax.random.PRNGKey(0), hp))
    setup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    epoch = jax.jit(tr.epoch).lower(ts, hp).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(epoch(ts, hp))  # warm-up
    n = c.steps_per_epoch
    info = dict(
        setup_s=setup_s,
        compile_s=compile_s,
        env_steps=n * c.num_envs * c.env_steps_per_step,
        updates=n * c.updates_per_step,
        num_envs=c.num_envs,
        utd=c.updates_per_step,
        hidden=list(c.hidden),
        jax=jax.__version__,
    )
    return (lambda: jax.block_until_ready(epoch(ts, hp))), info


def build_rejax(env: str, hidden: int, steps: int):
    import time

    import jax
    import jax.numpy as jnp
    from flax import linen as nn
    from rejax import TD3
    from rejax.networks import DeterministicPolicy, QNetwork

    env_kw = dict(env="Pendulum-v1") if env == "pendulum" else dict(env=quadrotor_gymnax())

    def make(total):
        algo = TD3.create(
            **env_kw,
            num_envs=1,
            total_timesteps=total,
            eval_freq=total,
            skip_initial_evaluation=True,
            batch_size=256,
            buffer_size=BUFFER,
            fill_buffer=WARMUP,
            num_epochs=1,
            policy_delay=2,
            polyak=0.995,
            exploration_noise=0.1,
            target_noise=0.2,
            target_noise_clip=0.5,
            learning_rate=3e-4,
        )
        space = algo.env.action_space(algo.env_params)
        return algo.replace(
            actor=DeterministicPolicy(space.shape[0], (space.low, space.high), (hidden, hidden), nn.relu),
            critic=QNetwork((hidden, hidden), nn.relu),
            eval_callback=lambda algo, ts, rng: jnp.zeros(()),  # no evaluation inside the timed run
        )

    t0 = time.perf_counter()
    warm = make(WARMUP + 2)  # fills the buffer (uniform actions), then one update
    ts = jax.jit(warm.init_state)(jax.random.PRNGKey(0))
    ts, _ = jax.block_until_ready(jax.jit(lambda ts: warm.train(train_state=ts))(ts))
    setup_s = time.perf_counter() - t0
    algo = make(steps)
    t0 = time.perf_counter()
    train = jax.jit(lambda ts: algo.train(train_state=ts)).lower(ts).compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(train(ts))
    done = int(out[0].global_step - ts.global_step)
    info = dict(
        setup_s=setup_s,
        compile_s=compile_s,
        env_steps=done,
        updates=done,
        num_envs=1,
        utd=1,
        hidden=[hidden, hidden],
        jax=jax.__version__,
    )
    return (lambda: jax.block_until_ready(train(ts))), info


def build_sb(framework: str, env: str, hidden: int, steps: int):
    import time

    import numpy as np
    from stable_baselines3.common.noise import NormalActionNoise

    if framework == "sbx":
        import jax
        from sbx import TD3

        extra = dict(jax=jax.__version__)
    else:
        import torch
        from stable_baselines3 import TD3

        extra = dict(torch=torch.__version__, torch_threads=torch.get_num_threads())
    import gymnasium as gym

    t0 = time.perf_counter()
    e = gym.make("Pendulum-v1") if env == "pendulum" else quadrotor_gymnasium()
    n_act = e.action_space.shape[0]
    kw = dict(
        learning_starts=WARMUP,
        batch_size=256,
        buffer_size=BUFFER,
        train_freq=1,
        gradient_steps=1,
        policy_delay=2,
        tau=0.005,
        target_policy_noise=0.2,
        target_noise_clip=0.5,
        action_noise=NormalActionNoise(np.zeros(n_act), 0.1 * np.ones(n_act)),
        policy_kwargs=dict(net_arch=[hidden, hidden]),
        seed=0,
        verbose=0,
    )
    if framework == "sb3":
        kw["device"] = "cpu"
    model = TD3("MlpPolicy", e, **kw)
    model.learn(WARMUP)  # uniform-random warm-up, no updates
    setup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.learn(FIRST, reset_num_timesteps=False)  # first updates (sbx: JIT compilation)
    first_s = time.perf_counter() - t0
    info = dict(
        setup_s=setup_s,
        first_s=first_s,
        first_steps=FIRST,
        env_steps=steps,
        updates=steps,
        num_envs=1,
        utd=1,
        hidden=[hidden, hidden],
        **extra,
    )
    return (lambda: model.learn(steps, reset_num_timesteps=False)), info


def build(framework: str, **kw):
    if framework == "ours":
        return build_ours(**kw)
    if framework == "rejax":
        return build_rejax(**kw)
    return build_sb(framework, **kw)


BUILDERS = {"td3": build}
MODULES = {"rejax": "rejax", "sbx": "sbx", "sb3": "stable_baselines3"}
LABEL = {"ours": "ours", "rejax": "rejax", "sbx": "sbx", "sb3": "SB3"}


def plan(quick: bool, steps: int | None):
    """Groups of cases: (group, case name, framework, builder kwargs)."""
    if quick:
        n = steps or 2_000
        return [
            ("pendulum h32", fw, dict(env="pendulum", hidden=32, steps=n))
            for fw in ("ours", "rejax", "sbx", "sb3")
        ] + [
            (
                "design pendulum",
                "ours",
                dict(env="pendulum", hidden=32, steps=max(1, n // 64), num_envs=64, utd=16),
            )
        ]
    n256, n64 = steps or 2_000, steps or 4_000
    out = []
    for fw in ("ours", "rejax", "sbx", "sb3"):
        out.append(("pendulum h256", fw, dict(env="pendulum", hidden=256, steps=n256)))
    for fw in ("ours", "rejax", "sbx", "sb3"):
        out.append(("quadrotor h256", fw, dict(env="quadrotor", hidden=256, steps=n256)))
    for fw in ("ours", "rejax", "sbx", "sb3"):
        out.append(("pendulum h64", fw, dict(env="pendulum", hidden=64, steps=n64)))
    out += [
        ("design pendulum", "ours", dict(env="pendulum", hidden=256, steps=100, num_envs=64, utd=16)),
        ("design quadrotor", "ours", dict(env="quadrotor", hidden=256, steps=100, num_envs=64, utd=16)),
        ("design fast_dpg", "ours", dict(env="quadrotor", hidden=64, steps=300, preset="fast_dpg")),
        ("design fast", "ours", dict(env="quadrotor", hidden=64, steps=20, preset="fast")),
    ]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--steps", type=int, default=None, help="timed env steps per call (default 2000 / 4000)")
    ap.add_argument("--quick", action="store_true", help="32-32 nets, Pendulum only, ~2k steps (CI)")
    ap.add_argument("--no-peer", action="store_true", help="our cases only")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default="benchmarks/results/peer_trainer_throughput.jsonl")
    args = ap.parse_args(argv)
    if args.worker:
        return _peers.serve(BUILDERS)
    if args.repeats < 1 or (args.steps is not None and args.steps < 1):
        ap.error("--repeats and --steps must be >= 1")
    if args.quick:
        args.repeats = 1

    record = _peers.machine_record(argv)
    local = _peers.Local(BUILDERS)
    workers, peer_versions = {}, {}
    cases = plan(args.quick, args.steps)
    for fw in sorted({fw for _, fw, _ in cases} - {"ours"}):
        if args.no_peer:
            continue
        py = _peers.find_python(MODULES[fw])
        if py is None:
            print(_peers.missing(MODULES[fw]))
            continue
        workers[fw] = _peers.Worker(py, os.path.abspath(__file__), fw)
        mods = (
            ["jax", MODULES[fw]] + (["gymnax"] if fw == "rejax" else []) + (["torch"] if fw == "sb3" else [])
        )
        peer_versions[fw] = {"python": py, **workers[fw].versions(mods + ["gymnasium"])}
        print(f"{fw} worker: {peer_versions[fw]}")

    built = {}
    try:
        for i, (group, fw, kw) in enumerate(cases):
            backend = local if fw == "ours" else workers.get(fw)
            if backend is None:
                continue
            cid = f"{i}:{group}:{fw}"
            try:
                built[cid] = (group, fw, kw, backend, backend.build(cid, "td3", framework=fw, **kw))
            except RuntimeError as e:
                print(f"[{group} {fw}] build failed: {str(e).splitlines()[0]}", file=sys.stderr)
        best = {cid: float("inf") for cid in built}
        for _ in range(args.repeats):
            for cid, (*_, backend, _) in built.items():
                best[cid] = min(best[cid], backend.time(cid))
    finally:
        for w in workers.values():
            w.close()

    rows = []
    for cid, (group, fw, kw, backend, info) in built.items():
        run_s = best[cid]
        row = dict(group=group, framework=fw, env=kw["env"], where=backend.where, run_s=run_s, **info)
        row["env_steps_per_s"] = info["env_steps"] / run_s
        row["updates_per_s"] = info["updates"] / run_s
        if "first_s" in info:  # sbx / SB3: compile time = first learn() less its steady-state share
            row["compile_s"] = max(0.0, info["first_s"] - info["first_steps"] * run_s / info["env_steps"])
        rows.append(row)
    ours = {r["group"]: r for r in rows if r["framework"] == "ours" and not r["group"].startswith("design")}
    for r in rows:
        o = ours.get(r["group"])
        r["ours_vs_this"] = (
            o["updates_per_s"] / r["updates_per_s"] if o and r["framework"] != "ours" else None
        )

    _peers.print_machine(record)
    print(
        f"{'group':<15} {'framework':<9} {'envs':>4} {'UTD':>3} {'hidden':>7} {'setup s':>7} "
        f"{'compile s':>9} {'run s':>6} {'env-steps/s':>11} {'updates/s':>9} {'ours/this':>9}"
    )
    for r in rows:
        ratio = f"{r['ours_vs_this']:.2f}" if r["ours_vs_this"] else "-"
        print(
            f"{r['group']:<15} {LABEL[r['framework']]:<9} {r['num_envs']:>4} {r['utd']:>3} "
            f"{'-'.join(map(str, r['hidden'])):>7} {r['setup_s']:>7.1f} {r['compile_s']:>9.1f} "
            f"{r['run_s']:>6.2f} {r['env_steps_per_s']:>11.3g} {r['updates_per_s']:>9.3g} {ratio:>9}"
        )
    print("ours/this: our updates/s over this framework's, same group (same env, nets, batch, UTD)")
    goals = {}
    for r in rows:
        if r["group"] == "pendulum h256" and r["framework"] in ("rejax", "sb3"):
            target = 3 if r["framework"] == "rejax" else 20
            goals[f"vs_{r['framework']}_ge_{target}x"] = dict(
                value=r["ours_vs_this"], met=r["ours_vs_this"] >= target
            )
    _peers.print_goals(goals, "{:.2f}", " (pendulum, 256-256)")
    record.update(
        versions=_peers.versions(["jax", "jaxlib", "flax", "optax", "ttd3_jax"]),
        peers=peer_versions,
        quick=args.quick,
        repeats=args.repeats,
        warmup=WARMUP,
        buffer=BUFFER,
        rows=rows,
        goals=goals,
    )
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
