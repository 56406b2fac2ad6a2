"""TD3 trainer throughput, and Pendulum-v1 time to a solved return, against rejax, sbx,
Stable-Baselines3 and RLtools, side by side in one run.

Equal settings for every framework: TD3, 1 env, 1 gradient update per env step (policy
delay 2), batch 256, the same MLP widths for actor and critics (ReLU), a 100k replay
buffer, 1000 uniform-random warm-up steps, Adam 3e-4, tau 0.005, exploration noise 0.1 and
target noise 0.2 clipped at 0.5 (in units of the action half-range).  Each peer runs in its
own worker process (``_peers.py``); ours runs in this process.

    python benchmarks/peer_trainer_throughput.py           # both studies of docs/performance.md
    python benchmarks/peer_trainer_throughput.py --study throughput   # (or --study solve)
    python benchmarks/peer_trainer_throughput.py --quick   # smoke run (CI): small nets, ~2k steps

Study 1, throughput: after the warm-up (not timed), ``--steps`` env steps, each followed by
one update, are timed; best of ``--repeats``, the frameworks interleaved.

Study 2, time to solved (Pendulum-v1 only): every framework trains ``--seeds`` seeds from
scratch; every ``EVAL_EVERY`` env steps after the warm-up it evaluates the deterministic
policy on ``EVAL_EPISODES`` fresh episodes (random starts, 200 steps); a run is
solved at the first evaluation whose mean return is >= ``SOLVED`` (-200: the usual
Pendulum threshold; a policy that swings up and holds from every start scores about -100
to -150, one that fails from some starts falls well below).  Time to solved = the warm-up plus the
training segments up to that evaluation, timed inside each framework around its own
call (compilation and the evaluations are not timed; compile time is reported apart).
The cases run round-robin, one segment each, so machine noise hits them alike.

Envs:
  pendulum   Pendulum-v1.  rejax: gymnax's; sbx, SB3 and ``rltools``: Gymnasium's (RLtools
             steps it through its Python bridge, a call into Python per env step, actions
             rescaled to [-1, 1]); ``rltools-cpp``: RLtools' own compiled C++ pendulum (the
             same equations); ours: a Brax-style port of the same equations
             (``PendulumV1`` below, actions in [-1, 1] scaled to +-2 N m), given to our
             trainer in place of a Brax env.
  quadrotor  our tracking env (``paper`` preset: 1 kHz, OU wind).  rejax gets it through a
             thin gymnax adapter (gymnax's ``step`` computes a reset every step and selects
             it where done: that is how gymnax envs auto-reset); sbx and SB3 through a
             Gymnasium adapter (one jitted single-env step per call, arrays to numpy).
             RLtools runs Pendulum only here (the task of the comparison).

What is timed: ours, one compiled epoch (``Trainer.epoch``); rejax, its compiled ``train``
continued from the warmed-up state with evaluation switched off; sbx and SB3,
``model.learn(steps, reset_num_timesteps=False)`` after the warm-up and a first short
``learn`` that triggers sbx's JIT compilation; RLtools, ``steps`` calls of its training
loop's ``State.step()`` (one env step and its updates each, compiled C++ via pybind11).

RLtools (``pip install rltools``) compiles its training loop for the env's sizes at run time
with the machine's C++ compiler (``-O3 -march=native -ffast-math``); that compile is its
compile time.  Its matrix products go to MKL where the ``mkl`` and ``mkl-include`` wheels are
installed (``rltools[mkl]``, as the ``peers`` extra pins it), to a system BLAS or else to its
own loops.  Its ``TD3()`` leaves two warm-up lengths at 100 steps (critic and actor updates
would start at step 100 while actions stay uniform until 1000); they are set to 1000 here
through its config template.

Rows at the end (``design``) show what our design adds in the same units: many envs per
update (64 envs x 16 updates per vector step, as the ``fast_dpg`` preset), and the ``fast``
preset's model-based actor update as the preset is now (a 50-step differentiable rollout of
its envs per vector step; 16 envs and no critic since issue 51, 64 envs and 16 critic updates
in the runs dated before 2026-12-07).
"""

from __future__ import annotations

import argparse
import os
import sys

import _peers

WARMUP = 1_000
BUFFER = 100_000
FIRST = 20  # sbx / SB3 / RLtools: env steps of the first, untimed learning call (sbx: JIT compile)
LR, TAU, GAMMA = 3e-4, 0.005, 0.99  # Adam (actor and critics), Polyak, discount
# exploration std, target-policy smoothing std and clip, in units of the action half-range
SIGMA, TARGET_SIGMA, TARGET_CLIP = 0.1, 0.2, 0.5
# time to solved: mean return over EVAL_EPISODES >= SOLVED, evaluated every EVAL_EVERY env steps
SOLVED, EVAL_EPISODES, EVAL_EVERY = -200.0, 10, 1_000
PENDULUM_STEPS = 200  # Pendulum-v1's episode length
# threads of RLtools' MKL unless MKL_NUM_THREADS is set: 1, its interface's own default (2 ran
# 20-65 % slower on the 2-core VM, shared, at 64-64 and 256-256); ours and rejax (XLA) and
# SB3 (torch) use every core
RLTOOLS_THREADS = 1


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


def our_hyper():
    from ttd3_jax.td3.config import Hyper

    return Hyper(
        gamma=GAMMA, tau=TAU, lr_actor=LR, lr_critic=LR, sigma=SIGMA,
        target_sigma=TARGET_SIGMA, target_clip=TARGET_CLIP,
    )  # fmt: skip


def pendulum_spec():
    """``PendulumV1`` as our trainer's env (its ``evaluate`` unused: the studies evaluate)."""
    from ttd3_jax.td3.env_spec import EnvSpec

    env = pendulum_v1()
    return EnvSpec(env, 3, 1, PENDULUM_STEPS, lambda policy: {}, differentiable=False, actor_obs_size=3)


def build_ours(env: str, hidden: int, steps: int, num_envs: int = 1, utd: int = 1, preset: str | None = None):
    import time

    import jax

    from ttd3_jax.run import spec as sp
    from ttd3_jax.run import tasks
    from ttd3_jax.sim.config import make_config
    from ttd3_jax.td3.config import TrainConfig
    from ttd3_jax.td3.trainer import make_trainer

    if preset:  # a training preset as it is; `steps` vector steps
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
        hp = our_hyper()
        t0 = time.perf_counter()
        if env == "pendulum":  # in place of a Brax env (never evaluated here)
            spec = pendulum_spec()
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


def rejax_td3(env: str, hidden: int, total: int):
    """rejax's TD3 at the equal settings, ``total`` env steps per ``train`` call, its own
    evaluation switched off; its noises act on actions in the env's range, so they are scaled
    by the half-range (2 N m for Pendulum-v1), as ours and RLtools apply them in [-1, 1]."""
    import jax.numpy as jnp
    from flax import linen as nn
    from rejax import TD3
    from rejax.networks import DeterministicPolicy, QNetwork

    algo = TD3.create(
        env="Pendulum-v1" if env == "pendulum" else quadrotor_gymnax(),
        num_envs=1,
        total_timesteps=total,
        eval_freq=total,
        skip_initial_evaluation=True,
        batch_size=256,
        buffer_size=BUFFER,
        fill_buffer=WARMUP,
        num_epochs=1,
        policy_delay=2,
        gamma=GAMMA,
        polyak=1.0 - TAU,
        learning_rate=LR,
    )
    space = algo.env.action_space(algo.env_params)
    half = float(jnp.max(space.high))
    return algo.replace(
        exploration_noise=SIGMA * half,
        target_noise=TARGET_SIGMA * half,
        target_noise_clip=TARGET_CLIP * half,
        actor=DeterministicPolicy(space.shape[0], (space.low, space.high), (hidden, hidden), nn.relu),
        critic=QNetwork((hidden, hidden), nn.relu),
        eval_callback=lambda algo, ts, rng: jnp.zeros(()),  # no evaluation inside the timed run
    )


def build_rejax(env: str, hidden: int, steps: int):
    import time

    import jax

    def make(total):
        return rejax_td3(env, hidden, total)

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
        learning_rate=LR,
        gamma=GAMMA,
        tau=TAU,
        target_policy_noise=TARGET_SIGMA,  # (SB3 adds both noises to actions scaled to [-1, 1])
        target_noise_clip=TARGET_CLIP,
        action_noise=NormalActionNoise(np.zeros(n_act), SIGMA * np.ones(n_act)),
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


# --------------------------------------------------------------------------- RLtools

_RLTOOLS = {}  # per worker process: (hidden, cpp) -> (compiled module, compile seconds)

# RLtools' own C++ pendulum (rl_tools::rl::environments::Pendulum, Pendulum-v1's equations,
# 200-step episodes) as the custom-environment header its Python interface includes
RLTOOLS_CPP_PENDULUM = """#include <rl_tools/rl/environments/pendulum/operations_cpu.h>
template <typename T, typename TI>
using ENVIRONMENT_FACTORY = rl_tools::rl::environments::Pendulum<
    rl_tools::rl::environments::pendulum::Specification<T, TI>>;
"""


def gym_pendulum(seed: int):
    """Gymnasium's Pendulum-v1 with actions rescaled to [-1, 1] (RLtools' convention)."""
    import gymnasium as gym
    from gymnasium.wrappers import RescaleAction

    env = RescaleAction(gym.make("Pendulum-v1"), -1.0, 1.0)
    env.reset(seed=seed)
    return env


def rltools_td3(hidden: int, cpp: bool):
    """RLtools' TD3 training loop for Pendulum at the equal settings, compiled once per worker
    and config into the worker's scratch directory; returns (module, compile seconds, info)."""
    import subprocess
    import time

    if (hidden, cpp) in _RLTOOLS:
        return _RLTOOLS[hidden, cpp]
    # read when MKL loads, with the first compiled module; RLtools sets 1 where it is unset
    os.environ.setdefault("MKL_NUM_THREADS", str(RLTOOLS_THREADS))
    import rltools
    import rltools.src.compile
    import rltools.src.link_blas
    import rltools.src.td3

    cache = os.path.abspath("rltools-cache")  # the worker's scratch directory, removed with it
    rltools.src.compile.CACHE_PATH = rltools.src.td3.CACHE_PATH = rltools.src.link_blas.CACHE_PATH = cache
    if cpp:
        os.makedirs(os.path.join(cache, "env"), exist_ok=True)
        with open(os.path.join(cache, "env", "environment.h"), "w") as fh:
            fh.write(RLTOOLS_CPP_PENDULUM)
        env = {"path": os.path.join(cache, "env"), "action_dim": 1, "observation_dim": 3}
    else:
        env = lambda: gym_pendulum(0)  # noqa: E731 (the factory is set again per seed)
    # its TD3() leaves the critic's and actor's warm-up at 100 steps (rl_tools' defaults, not
    # in its template): appended to N_WARMUP_STEPS's line of the template, both are 1000 too
    warmup = f"{WARMUP}; static constexpr TI N_WARMUP_STEPS_CRITIC = {WARMUP}; " + (
        f"static constexpr TI N_WARMUP_STEPS_ACTOR = {WARMUP}"
    )
    name = f"ttd3_bench_{hidden}_{'cpp' if cpp else 'gym'}"
    t0 = time.perf_counter()
    module = rltools.TD3(
        env,
        interface_name=name,
        force_recompile=True,
        enable_evaluation=False,  # the studies evaluate through State.action
        GAMMA=GAMMA,
        ACTOR_BATCH_SIZE=256,
        CRITIC_BATCH_SIZE=256,
        CRITIC_TRAINING_INTERVAL=1,
        ACTOR_TRAINING_INTERVAL=2,
        CRITIC_TARGET_UPDATE_INTERVAL=2,
        ACTOR_TARGET_UPDATE_INTERVAL=2,
        ACTOR_POLYAK=1.0 - TAU,
        CRITIC_POLYAK=1.0 - TAU,
        TARGET_NEXT_ACTION_NOISE_STD=TARGET_SIGMA,
        TARGET_NEXT_ACTION_NOISE_CLIP=TARGET_CLIP,
        N_ENVIRONMENTS=1,
        N_WARMUP_STEPS=warmup,
        STEP_LIMIT=10_000_000,  # the loop's "finished" flag only; the studies stop it
        REPLAY_BUFFER_CAP=BUFFER,
        ACTOR_HIDDEN_DIM=hidden,
        ACTOR_NUM_LAYERS=3,  # input, hidden, output: two hidden layers of `hidden` units
        ACTOR_ACTIVATION_FUNCTION="RELU",
        CRITIC_HIDDEN_DIM=hidden,
        CRITIC_NUM_LAYERS=3,
        CRITIC_ACTIVATION_FUNCTION="RELU",
        EXPLORATION_NOISE=SIGMA,
        OPTIMIZER_ALPHA=LR,
        OPTIMIZER_EPSILON=1e-8,  # optax's and torch's (RLtools' default: TensorFlow's 1e-7)
    )
    compile_s = time.perf_counter() - t0
    with open(os.path.join(cache, "template", f"rltools_td3_{name}", "loop_core_config.h")) as fh:
        assert f"N_WARMUP_STEPS_ACTOR = {WARMUP};" in fh.read(), "RLtools' TD3 template changed"
    compiler = rltools.src.compile.find_compiler()[0]
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout.splitlines()
    extra = dict(
        compiler=version[0] if version else compiler,
        mkl_threads=os.environ.get("MKL_NUM_THREADS"),
        rltools_env="C++ pendulum" if cpp else "Gymnasium bridge",
    )
    _RLTOOLS[hidden, cpp] = module, compile_s, extra
    return _RLTOOLS[hidden, cpp]


def rltools_state(hidden: int, cpp: bool, seed: int):
    module, compile_s, extra = rltools_td3(hidden, cpp)
    if not cpp:  # the training env of this seed (created when the State is)
        module.set_environment_factory(lambda: gym_pendulum(seed))
    return module.State(seed), compile_s, extra


def build_rltools(env: str, hidden: int, steps: int, cpp: bool = False):
    import time

    if env != "pendulum":
        raise ValueError("RLtools runs Pendulum-v1 only here")
    state, compile_s, extra = rltools_state(hidden, cpp, 0)
    t0 = time.perf_counter()
    for _ in range(WARMUP):  # uniform actions, no updates
        state.step()
    setup_s = time.perf_counter() - t0
    for _ in range(FIRST):  # the first updates (nothing to compile; caches warm)
        state.step()

    def run():
        for _ in range(steps):
            state.step()

    info = dict(
        setup_s=setup_s,
        compile_s=compile_s,
        env_steps=steps,
        updates=steps,
        num_envs=1,
        utd=1,
        hidden=[hidden, hidden],
        **extra,
    )
    return run, info


# --------------------------------------------------------------------------- time to solved

_SOLVE = {}  # per process: compiled programs of a (framework, hidden, interval, episodes)


def solve_ours(hidden: int, interval: int, seed: int, episodes: int):
    """Our trainer on ``PendulumV1``: ``run()`` does the warm-up first, then one epoch of
    ``interval`` env steps and an evaluation of ``episodes`` episodes per call."""
    import time

    import jax

    from ttd3_jax.td3 import core
    from ttd3_jax.td3.config import TrainConfig
    from ttd3_jax.td3.trainer import act, make_trainer

    hp, key = our_hyper(), jax.random.PRNGKey(seed)
    cfg = ("ours", hidden, interval, episodes)
    if cfg not in _SOLVE:
        c = TrainConfig(
            algo="td3", num_envs=1, updates_per_step=1, batch_size=256, hidden=(hidden, hidden),
            warmup_transitions=WARMUP, buffer_size=BUFFER, total_transitions=WARMUP + interval,
            epochs=1, policy_delay=2,
        )  # fmt: skip
        spec = pendulum_spec()
        tr, env = make_trainer(c, spec), spec.env

        def evaluate(ts, k):  # mean return of the deterministic policy, `episodes` random starts
            stats = core.obs_stats(tr.setup, ts)

            def body(s, _):
                s = jax.vmap(env.step)(s, act(tr.setup, ts.actor, stats, s.obs))
                return s, s.reward

            s0 = jax.vmap(env.reset)(jax.random.split(k, episodes))
            return jax.lax.scan(body, s0, None, length=PENDULUM_STEPS)[1].sum(0).mean()

        t0 = time.perf_counter()
        init = jax.jit(tr.init).lower(key, hp).compile()
        shape = jax.eval_shape(tr.init, key, hp)
        epoch = jax.jit(tr.epoch).lower(shape, hp).compile()
        ev = jax.jit(evaluate).lower(shape, key).compile()
        _SOLVE[cfg] = (init, epoch, ev, time.perf_counter() - t0)
    init, epoch, ev, compile_s = _SOLVE[cfg]
    st = dict(ts=None, steps=0)
    eval_key = jax.random.fold_in(key, 1)

    def run():
        t0 = time.perf_counter()
        if st["ts"] is None:
            st["ts"] = jax.block_until_ready(init(key, hp))
            st["steps"] = WARMUP
            return dict(run_s=time.perf_counter() - t0, env_steps=st["steps"], eval_return=None)
        st["ts"] = jax.block_until_ready(epoch(st["ts"], hp)[0])
        run_s = time.perf_counter() - t0
        st["steps"] += interval
        ret = float(ev(st["ts"], jax.random.fold_in(eval_key, st["steps"])))
        return dict(run_s=run_s, env_steps=st["steps"], eval_return=ret)

    return run, dict(compile_s=compile_s, jax=jax.__version__)


def solve_rejax(hidden: int, interval: int, seed: int, episodes: int):
    """rejax on gymnax's Pendulum-v1, the same protocol as :func:`solve_ours`."""
    import time

    import jax

    key = jax.random.PRNGKey(seed)
    cfg = ("rejax", hidden, interval, episodes)
    if cfg not in _SOLVE:
        warm, seg = rejax_td3("pendulum", hidden, WARMUP), rejax_td3("pendulum", hidden, interval)
        env, params = seg.env, seg.env_params

        def evaluate(ts, k):
            policy = seg.make_act(ts)

            def episode(k):
                k_reset, k_steps = jax.random.split(k)
                obs, s = env.reset(k_reset, params)

                def body(carry, k):
                    obs, s = carry
                    obs, s, r, _, _ = env.step(k, s, policy(obs, None), params)
                    return (obs, s), r.squeeze()

                return jax.lax.scan(body, (obs, s), jax.random.split(k_steps, PENDULUM_STEPS))[1].sum()

            return jax.vmap(episode)(jax.random.split(k, episodes)).mean()

        t0 = time.perf_counter()
        init = jax.jit(warm.init_state).lower(key).compile()
        shape = init(key)  # (each trace of init_state makes its own state class: lower on this one's)
        warm_up = jax.jit(lambda ts: warm.train(train_state=ts)[0]).lower(shape).compile()
        train = jax.jit(lambda ts: seg.train(train_state=ts)[0]).lower(shape).compile()
        ev = jax.jit(evaluate).lower(shape, key).compile()
        _SOLVE[cfg] = (init, warm_up, train, ev, time.perf_counter() - t0)
    init, warm_up, train, ev, compile_s = _SOLVE[cfg]
    st = dict(ts=None, steps=0)
    eval_key = jax.random.fold_in(key, 1)

    def run():
        t0 = time.perf_counter()
        if st["ts"] is None:  # rejax's warm-up: fill_buffer steps of uniform actions
            st["ts"] = jax.block_until_ready(warm_up(init(key)))
            st["steps"] = int(st["ts"].global_step)
            return dict(run_s=time.perf_counter() - t0, env_steps=st["steps"], eval_return=None)
        st["ts"] = jax.block_until_ready(train(st["ts"]))
        run_s = time.perf_counter() - t0
        st["steps"] = int(st["ts"].global_step)
        ret = float(ev(st["ts"], jax.random.fold_in(eval_key, st["steps"])))
        return dict(run_s=run_s, env_steps=st["steps"], eval_return=ret)

    return run, dict(compile_s=compile_s, jax=jax.__version__)


def solve_rltools(hidden: int, interval: int, seed: int, episodes: int, cpp: bool = False):
    """RLtools, the same protocol; it evaluates through ``State.action`` on Gymnasium's
    Pendulum-v1 (a Python loop, not timed)."""
    import time

    state, compile_s, extra = rltools_state(hidden, cpp, seed)
    eval_env = gym_pendulum(10_000 + seed)
    st = dict(steps=0)  # env steps so far (0: the warm-up comes next)

    def evaluate():
        total = 0.0
        for _ in range(episodes):
            obs, _ = eval_env.reset()
            for _ in range(PENDULUM_STEPS):
                obs, r, term, trunc, _ = eval_env.step(state.action(obs))
                total += float(r)
                if term or trunc:
                    break
        return total / episodes

    def run():
        warm_up = st["steps"] == 0
        n = WARMUP if warm_up else interval
        t0 = time.perf_counter()
        for _ in range(n):
            state.step()
        run_s = time.perf_counter() - t0
        st["steps"] += n
        return dict(run_s=run_s, env_steps=st["steps"], eval_return=None if warm_up else evaluate())

    return run, dict(compile_s=compile_s, **extra)


def solve(framework: str, **kw):
    if framework == "ours":
        return solve_ours(**kw)
    if framework == "rejax":
        return solve_rejax(**kw)
    return solve_rltools(cpp=framework == "rltools-cpp", **kw)


def build(framework: str, **kw):
    if framework == "ours":
        return build_ours(**kw)
    if framework == "rejax":
        return build_rejax(**kw)
    if framework in ("rltools", "rltools-cpp"):
        return build_rltools(cpp=framework == "rltools-cpp", **kw)
    return build_sb(framework, **kw)


BUILDERS = {"td3": build, "solve": solve}
MODULES = {"rejax": "rejax", "sbx": "sbx", "sb3": "stable_baselines3", "rltools": "rltools"}
MODULES["rltools-cpp"] = "rltools"
LABEL = {"ours": "ours", "rejax": "rejax", "sbx": "sbx", "sb3": "SB3", "rltools": "RLtools"}
LABEL["rltools-cpp"] = "RLtools-C++"
PEERS = ("rejax", "sbx", "sb3", "rltools", "rltools-cpp")
SOLVERS = ("ours", "rejax", "rltools")  # the frameworks of the time-to-solved study


def plan(quick: bool, steps: int | None):
    """Groups of cases: (group, case name, framework, builder kwargs)."""
    if quick:
        n = steps or 2_000
        return [
            ("pendulum h32", fw, dict(env="pendulum", hidden=32, steps=n))
            for fw in ("ours", "rejax", "sbx", "sb3", "rltools")
        ] + [
            (
                "design pendulum",
                "ours",
                dict(env="pendulum", hidden=32, steps=max(1, n // 64), num_envs=64, utd=16),
            )
        ]
    n256, n64 = steps or 2_000, steps or 4_000
    out = []
    for fw in ("ours", *PEERS):
        out.append(("pendulum h256", fw, dict(env="pendulum", hidden=256, steps=n256)))
    for fw in ("ours", "rejax", "sbx", "sb3"):
        out.append(("quadrotor h256", fw, dict(env="quadrotor", hidden=256, steps=n256)))
    for fw in ("ours", *PEERS):
        out.append(("pendulum h64", fw, dict(env="pendulum", hidden=64, steps=n64)))
    out += [
        ("design pendulum", "ours", dict(env="pendulum", hidden=256, steps=100, num_envs=64, utd=16)),
        ("design quadrotor", "ours", dict(env="quadrotor", hidden=256, steps=100, num_envs=64, utd=16)),
        ("design fast_dpg", "ours", dict(env="quadrotor", hidden=64, steps=300, preset="fast_dpg")),
        ("design fast", "ours", dict(env="quadrotor", hidden=64, steps=20, preset="fast")),
    ]
    return out


def plan_solve(quick: bool, seeds: int, hidden: int, max_steps: int):
    """The time-to-solved cases: (framework, seed, builder kwargs), and the env-step budget."""
    if quick:  # keeps the path alive; nothing is solved in 1000 steps
        return [(fw, 0, dict(hidden=32, interval=500, seed=0, episodes=2)) for fw in SOLVERS], WARMUP + 1_000
    kw = dict(hidden=hidden, interval=EVAL_EVERY, episodes=EVAL_EPISODES)
    return [(fw, s, dict(kw, seed=s)) for s in range(seeds) for fw in SOLVERS], WARMUP + max_steps


def start_workers(fws, no_peer: bool):
    """A worker per peer framework found; returns (workers, versions, {framework: why not})."""
    workers, peer_versions, absent = {}, {}, {}
    for fw in sorted(fws):
        if no_peer:
            absent[fw] = "skipped (--no-peer)"
            continue
        py = _peers.find_python(MODULES[fw])
        if py is None:
            print(_peers.missing(MODULES[fw]))
            absent[fw] = "not installed"
            continue
        workers[fw] = _peers.Worker(py, os.path.abspath(__file__), fw)
        mods = (
            ["jax", MODULES[fw]]
            + (["gymnax"] if fw == "rejax" else [])
            + (["torch"] if fw == "sb3" else [])
            + (["mkl"] if fw.startswith("rltools") else [])
        )
        peer_versions[fw] = {"python": py, **workers[fw].versions(mods + ["gymnasium"])}
        print(f"{fw} worker: {peer_versions[fw]}")
    return workers, peer_versions, absent


def throughput(cases, local, workers, repeats: int):
    """Build every case, time them interleaved (best of ``repeats``); returns (rows, failures)."""
    built, failed = {}, {}
    for i, (group, fw, kw) in enumerate(cases):
        backend = local if fw == "ours" else workers.get(fw)
        if backend is None:
            continue
        cid = f"{i}:{group}:{fw}"
        try:
            built[cid] = (group, fw, kw, backend, backend.build(cid, "td3", framework=fw, **kw))
        except RuntimeError as e:
            failed[group, fw] = f"build failed: {str(e).splitlines()[0]}"
            print(f"[{group} {fw}] {failed[group, fw]}", file=sys.stderr)
    best = {cid: float("inf") for cid in built}
    for _ in range(repeats):
        for cid, (*_, backend, _) in built.items():
            best[cid] = min(best[cid], backend.time(cid))
    for cid, (*_, backend, _) in built.items():
        backend.forget(cid)

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
    return rows, failed


def print_throughput(rows, cases, failed, absent):
    print(
        f"{'group':<15} {'framework':<11} {'envs':>4} {'UTD':>3} {'hidden':>7} {'setup s':>7} "
        f"{'compile s':>9} {'run s':>6} {'env-steps/s':>11} {'updates/s':>9} {'ours/this':>9}"
    )
    by_case = {(r["group"], r["framework"]): r for r in rows}
    for group, fw, _ in cases:
        r = by_case.get((group, fw))
        if r is None:
            why = failed.get((group, fw)) or absent.get(fw)
            if why:
                print(f"{group:<15} {LABEL[fw]:<11} {why}")
            continue
        ratio = f"{r['ours_vs_this']:.2f}" if r["ours_vs_this"] else "-"
        print(
            f"{r['group']:<15} {LABEL[r['framework']]:<11} {r['num_envs']:>4} {r['utd']:>3} "
            f"{'-'.join(map(str, r['hidden'])):>7} {r['setup_s']:>7.1f} {r['compile_s']:>9.1f} "
            f"{r['run_s']:>6.2f} {r['env_steps_per_s']:>11.3g} {r['updates_per_s']:>9.3g} {ratio:>9}"
        )
    print("ours/this: our updates/s over this framework's, same group (same env, nets, batch, UTD)")


def time_to_solved(cases, budget: int, local, workers):
    """Build every case, then run them round-robin, one segment (and its evaluation) each, until
    each is solved or has spent ``budget`` env steps.  Returns (runs, failures)."""
    runs, failed = {}, {}
    for fw, seed, kw in cases:
        backend = local if fw == "ours" else workers.get(fw)
        if backend is None:
            continue
        cid = f"solve:{fw}:{seed}"
        try:
            info = backend.build(cid, "solve", framework=fw, **kw)
        except RuntimeError as e:
            failed[fw] = f"build failed: {str(e).splitlines()[0]}"
            print(f"[solve {fw} seed {seed}] {failed[fw]}", file=sys.stderr)
            continue
        runs[cid] = dict(framework=fw, seed=seed, hidden=kw["hidden"], backend=backend, info=info,
                         train_s=0.0, env_steps=0, solved=False, curve=[])  # fmt: skip
    active = list(runs)
    while active:
        for cid in list(active):
            r = runs[cid]
            out = r["backend"].run(cid)
            r["train_s"] += out["run_s"]
            r["env_steps"] = out["env_steps"]
            if out["eval_return"] is not None:
                r["curve"].append((out["env_steps"], out["eval_return"], r["train_s"]))
                r["solved"] = out["eval_return"] >= SOLVED
            if r["solved"] or r["env_steps"] >= budget:
                r["backend"].forget(cid)
                active.remove(cid)
                verdict = "solved" if r["solved"] else "not solved"
                print(f"[solve] {r['framework']} seed {r['seed']}: {verdict} at {r['env_steps']} env steps, "
                      f"{r['train_s']:.1f} s", file=sys.stderr, flush=True)  # fmt: skip
    return runs, failed


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def print_solved(runs, failed, absent, budget: int, interval: int, episodes: int):
    """Per run and per framework (median over seeds) time and env steps to solved; returns the
    per-framework summary."""
    print(
        f"\ntime to solved, Pendulum-v1: mean return of {episodes} evaluation episodes >= {SOLVED:g}, "
        f"evaluated every {interval} env steps after a {WARMUP}-step warm-up (budget {budget} env steps)"
    )
    print(f"{'framework':<11} {'seed':>4} {'hidden':>7} {'compile s':>9} {'env steps':>9} {'train s':>8} "
          f"{'steps/s':>8} {'return':>8}")  # fmt: skip
    for r in runs.values():
        last = r["curve"][-1][1] if r["curve"] else float("nan")
        steps = f"{r['env_steps']}" if r["solved"] else f">{r['env_steps']}"
        print(
            f"{LABEL[r['framework']]:<11} {r['seed']:>4} {r['hidden']:>7} {r['info']['compile_s']:>9.1f} "
            f"{steps:>9} {r['train_s']:>8.1f} {r['env_steps'] / r['train_s']:>8.3g} {last:>8.1f}"
        )
    summary = {}
    for fw in SOLVERS:
        rs = [r for r in runs.values() if r["framework"] == fw]
        if not rs:
            why = failed.get(fw) or absent.get(fw)
            if why:
                print(f"{LABEL[fw]:<11} {why}")
            continue
        inf = float("inf")
        summary[fw] = dict(
            seeds=len(rs),
            solved=sum(r["solved"] for r in rs),
            median_train_s=_median([r["train_s"] if r["solved"] else inf for r in rs]),
            median_env_steps=_median([r["env_steps"] if r["solved"] else inf for r in rs]),
            compile_s=max(r["info"]["compile_s"] for r in rs),
        )
    o = summary.get("ours")
    for fw, m in summary.items():
        m["ours_over_this_s"] = o["median_train_s"] / m["median_train_s"] if o and fw != "ours" else None
    print(f"{'median':<11} {'solved':>6} {'env steps':>9} {'train s':>8} {'ours/this s':>11}")
    for fw, m in summary.items():
        ratio = m["ours_over_this_s"]
        ratio = "-" if ratio is None or ratio != ratio else f"{ratio:.2f}"
        print(
            f"{LABEL[fw]:<11} {m['solved']:>3}/{m['seeds']:<2} {m['median_env_steps']:>9.0f} "
            f"{m['median_train_s']:>8.1f} {ratio:>11}"
        )
    print("ours/this s: our median time to solved over this framework's (< 1: ours solves sooner)")
    return summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--study", choices=("all", "throughput", "solve"), default="all")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--steps", type=int, default=None, help="timed env steps per call (default 2000 / 4000)")
    ap.add_argument("--seeds", type=int, default=3, help="time to solved: seeds per framework")
    ap.add_argument("--solve-hidden", type=int, default=256, help="time to solved: hidden widths")
    ap.add_argument("--solve-max", type=int, default=30_000, help="time to solved: env steps after warm-up")
    ap.add_argument("--quick", action="store_true", help="32-32 nets, Pendulum only, ~2k steps (CI)")
    ap.add_argument("--no-peer", action="store_true", help="our cases only")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default="benchmarks/results/peer_trainer_throughput.jsonl")
    args = ap.parse_args(argv)
    if args.worker:
        return _peers.serve(BUILDERS)
    if min(args.repeats, args.seeds, args.solve_hidden, args.solve_max) < 1 or (
        args.steps is not None and args.steps < 1
    ):
        ap.error("--repeats, --steps, --seeds, --solve-hidden and --solve-max must be >= 1")
    if args.quick:
        args.repeats = 1

    record = _peers.machine_record(argv)
    record["loadavg_start"] = os.getloadavg()  # the machine is shared: how busy it was
    local = _peers.Local(BUILDERS)
    cases = plan(args.quick, args.steps) if args.study in ("all", "throughput") else []
    solve_cases, budget = (
        plan_solve(args.quick, args.seeds, args.solve_hidden, args.solve_max)
        if args.study in ("all", "solve")
        else ([], 0)
    )
    fws = {fw for _, fw, _ in cases} | {fw for fw, _, _ in solve_cases}
    workers, peer_versions, absent = start_workers(fws - {"ours"}, args.no_peer)
    rows, failed, runs, solve_failed = [], {}, {}, {}
    try:
        if cases:
            rows, failed = throughput(cases, local, workers, args.repeats)
        if solve_cases:
            runs, solve_failed = time_to_solved(solve_cases, budget, local, workers)
    finally:
        for w in workers.values():
            w.close()

    record["loadavg_end"] = os.getloadavg()
    _peers.print_machine(record)
    print(f"load average (1 / 5 / 15 min) at start {record['loadavg_start']}, at end {record['loadavg_end']}")
    goals, summary = {}, {}
    if cases:
        print_throughput(rows, cases, failed, absent)
        for r in rows:
            if r["group"] == "pendulum h256" and r["framework"] in ("rejax", "sb3"):
                target = 3 if r["framework"] == "rejax" else 20
                goals[f"vs_{r['framework']}_ge_{target}x"] = dict(
                    value=r["ours_vs_this"], met=r["ours_vs_this"] >= target
                )
        _peers.print_goals(goals, "{:.2f}", " (pendulum, 256-256)")
    if solve_cases:
        kw = solve_cases[0][2]
        summary = print_solved(runs, solve_failed, absent, budget, kw["interval"], kw["episodes"])
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
    if solve_cases:
        record["solve"] = dict(
            solved_at=SOLVED,
            eval_episodes=solve_cases[0][2]["episodes"],
            eval_every=solve_cases[0][2]["interval"],
            budget_env_steps=budget,
            runs=[{k: v for k, v in r.items() if k != "backend"} for r in runs.values()],
            summary=summary,
        )
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
