"""Closed-loop evaluation of a controller on the test tracks (spec §2.5).

A controller is a pair of pure functions ``init(env_state) -> carry`` and
``act(carry, env_state) -> (action, carry)`` returning a normalised action (4,).
:func:`closed_loop` runs it for a whole episode as one ``lax.scan``.

:class:`Evaluator` compiles the evaluation programs of a controller family once
(parameters such as a policy's weights are arguments, so the seeds of a run share
them): batched metrics over many tracks, and the run-time figures (Python loop over a
jitted step as the paper timed it, one compiled scan, per-call latency).
The robustness suite (:func:`ttd3_jax.robustness.evaluate_robustness`: the evaluation
repeated under wind, an unknown mass error, observation noise and one step of actuation
delay) lives in :mod:`ttd3_jax.robustness`, the trace plots (:func:`ttd3_jax.plots.plot_traces`)
in :mod:`ttd3_jax.plots`; the CLI below uses both.

CLI::

    python -m ttd3_jax.evaluate --controller geometric        # Spiral-RT and LOS-RT seed 0
    python -m ttd3_jax.evaluate --controller nmpc --nmpc-solve-every 10
    python -m ttd3_jax.evaluate RUN_DIR [--epoch E | --best] [--seed-index I] [--robustness]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttd3_jax import trajectories as tr
from ttd3_jax.dynamics import QuadState
from ttd3_jax.env import (
    EVAL_PROTOCOL_FIELDS,
    PRESETS,
    EnvConfig,
    TrackingEnv,
    action_to_control,
    control_to_action,
    hover_action,
    make_config,
    parse_overrides,
    yaw_of,
)
from ttd3_jax.geometric import GeometricGains, geometric_control

CONTROLLERS = ("geometric", "hover", "nmpc")
# set by the evaluation protocol (EnvConfig.for_eval), so not by --env-overrides
_PROTOCOL_REASON = "set by the evaluation protocol (--track, --los-seed; --robustness for wind and noise)"


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
    vel: jax.Array  # (T, 3) m/s, velocity after step i (world frame)
    quat: jax.Array  # (T, 4) attitude after step i, scalar-first unit quaternion (body to world)


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
        # the action the env applies now: the previous one under ``action_delay = 1``
        applied = s.pipeline_state.prev_action if c.action_delay else jnp.clip(a, -1.0, 1.0)
        s = env.step(s, a)
        ps = s.pipeline_state
        out = (
            ps.quad.p,
            tr.position(ps.track, ps.k, c.dt),
            applied,
            s.metrics["tracking_error"],
            s.metrics["crashed"],
            ps.quad.v,
            ps.quad.q,
        )
        return (s, ctrl), out

    _, (pos, ref, act, err, crash, vel, quat) = jax.lax.scan(
        body, (state, controller.init(state)), None, length=env.episode_length
    )
    crashed = jnp.maximum.accumulate(crash)
    return Rollout(pos=pos, ref=ref, action=act, error_sum=err, crashed=crashed, vel=vel, quat=quat)


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


def energy_paper_map(actions, cfg: EnvConfig) -> np.ndarray:
    """Σ‖a‖ over the physics steps (spec §2.5) of applied actions ``actions`` (..., T, 4)
    of an env with config ``cfg``, re-expressed in the paper's action map (O2: thrust
    f_min + (a0+1)/2·(f_max − f_min), no hover centring).  The physical commands are the
    same, so controllers trained or built with different maps become comparable (under
    ``hover_centered_thrust`` hover is a0 = 0, in the paper's map a0 = 0.4715)."""
    a = to_paper_map(actions, cfg)
    return cfg.action_repeat * np.sum(np.linalg.norm(a, axis=-1), axis=-1)


def to_paper_map(actions, cfg: EnvConfig) -> np.ndarray:
    """Normalised actions (..., 4) of an env with config ``cfg`` in the paper's action map
    (the same physical commands; see :func:`energy_paper_map`)."""
    paper = dataclasses.replace(cfg, hover_centered_thrust=False, thrust_map_mass=None)
    return np.asarray(control_to_action(paper, action_to_control(cfg, jnp.asarray(actions))))


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


# --------------------------------------------------------------------------- paper values

# The paper's Tables 3-5 (quadrotor; "MPC" is the paper's own, unspecified MPC).  Σ‖e‖ in m,
# energy Σ√(uᵀu) (spec M2: the LOS values exceed the bound of 2 per step), run time in s
# (Python loop of 3000 controller outputs, mean of 3 runs, hardware not stated).
PAPER = {
    "T-TD3": {
        "spiral_rt": {"tracking_error": 25.99, "energy": 2759.582772, "run_s": 4.879404},
        "los_rt": {"tracking_error": 398.74, "energy": 7156.452883, "run_s": 4.754059},
    },
    "MPC": {
        "spiral_rt": {"tracking_error": 78.47, "energy": 2762.378835, "run_s": 19.360494},
        "los_rt": {"tracking_error": 542.92, "energy": 7467.541158, "run_s": 16.305317},
    },
}

TRACK_TITLES = {"spiral_rt": "Spiral-RT", "los_rt": "LOS-RT"}


def device_description() -> str:
    """The default JAX device in words, e.g. ``"cpu (cpu), 1 core(s) usable"``."""
    dev = jax.devices()[0]
    text = f"{dev.platform} ({dev.device_kind})"
    if dev.platform == "cpu":
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count()
        model = ""
        with contextlib.suppress(OSError):
            with open("/proc/cpuinfo") as fh:
                model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
        text += f", {model + ', ' if model else ''}{cores} core(s) usable"
    return text


# --------------------------------------------------------------------------- compiled evaluation

Build = Callable[[Any], Controller]  # parameters theta (a pytree, or None) -> Controller


def fixed(controller: Controller) -> Build:
    """A :data:`Build` for a controller without parameters (use ``theta=None``)."""
    return lambda theta: controller


def sensed_controller(controller: Controller, cfg: EnvConfig) -> Controller:
    """``controller`` fed with the vehicle state as the env observes it (p, v, q, and ω when
    observed, read from ``obs``) instead of the true state, so that observation noise
    reaches classical controllers as it reaches a policy.  Without noise the two agree
    (q and −q are the same attitude; track-frame positions are shifted back)."""
    if cfg.obs_frame == "heading":
        raise ValueError(
            "obs_frame='heading' drops the yaw from the observation, so a classical controller "
            "cannot read its state from it; use obs_frame 'world' or 'track', or sensed=False"
        )

    def sensed(s):
        ps, o = s.pipeline_state, s.obs
        p = o[0:3]
        if cfg.obs_frame == "track":
            p = p + tr.position(ps.track, ps.k, cfg.dt).astype(p.dtype)
        w = o[17:20] if cfg.quad.rate_model != "instant" else ps.quad.w
        quad = QuadState(p=p, v=o[3:6], q=o[6:10], w=w)
        return s.replace(pipeline_state=ps.replace(quad=quad))

    return Controller(
        init=lambda s: controller.init(sensed(s)), act=lambda c, s: controller.act(c, sensed(s))
    )


def controller_build(name: str, cfg: EnvConfig, sensed: bool = True, **options) -> Build:
    """:func:`make_controller` for ``cfg`` as a :data:`Build`; ``sensed`` (default) feeds it
    the observed state (:func:`sensed_controller`)."""
    ctrl = make_controller(name, cfg, **options)
    return fixed(sensed_controller(ctrl, cfg) if sensed else ctrl)


@dataclasses.dataclass
class Trace:
    """One episode on the host, for plots: per control step i, at t = (i+1)·control_dt."""

    t: np.ndarray  # (T,) s
    pos: np.ndarray  # (T, 3) m
    ref: np.ndarray  # (T, 3) m
    action: np.ndarray  # (T, 4) applied normalised action
    error: np.ndarray  # (T,) m, ||p_d - p||
    vel: np.ndarray  # (T, 3) m/s
    quat: np.ndarray  # (T, 4) scalar-first unit quaternion, body to world

    @classmethod
    def from_rollout(cls, r: Rollout, control_dt: float) -> Trace:
        pos, ref = np.asarray(r.pos), np.asarray(r.ref)
        t = control_dt * np.arange(1, pos.shape[0] + 1)
        error = np.linalg.norm(pos - ref, axis=-1)
        vel, quat = np.asarray(r.vel), np.asarray(r.quat)
        return cls(t=t, pos=pos, ref=ref, action=np.asarray(r.action), error=error, vel=vel, quat=quat)


TRACE_COLUMNS = (
    "label,t_s,x_m,y_m,z_m,x_ref_m,y_ref_m,z_ref_m,error_m,a0_thrust,a1_wx,a2_wy,a3_wz,"
    "vx_mps,vy_mps,vz_mps,qw,qx,qy,qz,yaw_rad"
)


def write_traces(traces: dict[str, dict[str, Trace]], out_dir: str, prefix: str = "") -> list[str]:
    """Per track, ``{prefix}{track}_trace.csv``: one row per control step and label
    (controller or seed), with the time (s), the flown and reference positions (m), the
    error ‖p_d − p‖ (m), the applied normalised action, the velocity (m/s), the attitude
    quaternion and its yaw (rad, z-y-x) (columns ``TRACE_COLUMNS``).  The plots of
    :func:`ttd3_jax.plots.plot_traces` draw from the same data."""
    os.makedirs(out_dir, exist_ok=True)
    tracks = [t for t in tr.TEST_TRACKS if any(t in v for v in traces.values())]
    paths = []
    for track in tracks:
        path = os.path.join(out_dir, f"{prefix}{track}_trace.csv")
        with open(path, "w") as fh:
            fh.write(TRACE_COLUMNS + "\n")
            for label, v in traces.items():
                if track not in v:
                    continue
                x = v[track]
                yaw = np.asarray(yaw_of(x.quat.T))
                cols = np.column_stack([x.t, x.pos, x.ref, x.error, x.action, x.vel, x.quat, yaw])
                name = str(label).replace(",", ";")
                for row in cols:
                    fh.write(name + "," + ",".join(f"{c:.9g}" for c in row) + "\n")
        paths.append(path)
    return paths


def _index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _signature(name, args):
    leaves, treedef = jax.tree.flatten(args)
    return name, treedef, tuple((jnp.shape(x), str(jnp.result_type(x))) for x in leaves)


class Evaluator:
    """Compiled programs that evaluate one controller family on one env.

    ``build(theta)`` returns the controller for parameters ``theta`` (a policy's weights, or
    ``None`` for a fixed controller).  ``theta`` is an argument of every program, so the
    seeds of a training run share one compilation.  ``compile_s`` holds the compile time of
    each program (its first compilation).  ``sequential=True`` runs a batch of tracks one
    after the other (``lax.map``) instead of ``vmap``: use it for controllers whose
    ``lax.cond`` must stay a branch (NMPC with ``solve_every > 1``; under ``vmap`` both
    sides of a ``cond`` run at every step).
    """

    def __init__(self, env: TrackingEnv, build: Build, sequential: bool = False):
        self.env, self.build, self.sequential = env, build, sequential
        self.compile_s: dict[str, float] = {}
        self._programs: dict = {}

    def _program(self, name: str, fn: Callable, *args):
        key = _signature(name, args)
        if key not in self._programs:
            t0 = time.perf_counter()
            self._programs[key] = jax.jit(fn).lower(*args).compile()
            self.compile_s.setdefault(name, time.perf_counter() - t0)
        return self._programs[key]

    def _episode(self, theta, track, key):
        env = self.env
        r = closed_loop(env, self.build(theta), env.reset_with_track(key, track))
        return r, metrics(env, r)

    def rollouts(self, theta, tracks: tr.Track, keys: jax.Array | None = None):
        """``(Rollout, metrics)`` on the host, one episode per track (leading axis).  ``keys``
        (one per track) seed wind and observation noise; default ``PRNGKey(0)`` for all,
        as :func:`evaluate_on_tracks`."""
        n = tracks.kind.shape[0]
        if keys is None:
            keys = jnp.stack([jax.random.PRNGKey(0)] * n)

        def batch(theta, tracks, keys):
            if self.sequential:
                return jax.lax.map(lambda tk: self._episode(theta, *tk), (tracks, keys))
            return jax.vmap(self._episode, in_axes=(None, 0, 0))(theta, tracks, keys)

        out = self._program("rollouts", batch, theta, tracks, keys)(theta, tracks, keys)
        return jax.device_get(out)

    def timing(self, theta, track: tr.Track, repeats: int = 3, warmup_steps: int = 10) -> dict:
        """Run time of one episode on ``track`` (spec §2.5), measured after compilation:

        * ``loop_s``: the episode driven step by step from Python, one call of a jitted
          (controller + env step) function per control step, waiting for each action
          (as the paper timed its controllers), mean of ``repeats`` runs;
        * ``scan_s``: the same episode as one compiled ``lax.scan``, mean of ``repeats``;
        * ``act_ms``: per-call latency of the jitted controller ``act`` alone, mean over
          the episode's control steps (the env is stepped by a separate program);
        * ``compile_*_s``: compile times of those programs (first compilation).
        """
        env, build = self.env, self.build
        key = jax.random.PRNGKey(0)
        n = env.episode_length

        def start(theta, track):
            s = env.reset_with_track(key, track)
            return s, build(theta).init(s)

        def step(theta, s, c):
            a, c = build(theta).act(c, s)
            return env.step(s, a), c, a

        def scan(theta, track):
            return self._episode(theta, track, key)[1]["tracking_error"]

        def act(theta, c, s):
            return build(theta).act(c, s)

        s0, c0 = self._program("start", start, theta, track)(theta, track)
        step_c = self._program("loop_step", step, theta, s0, c0)
        scan_c = self._program("scan", scan, theta, track)
        act_c = self._program("act", act, theta, c0, s0)
        env_c = self._program("env_step", env.step, s0, jnp.zeros(4, s0.obs.dtype))

        def loop(steps):
            s, c = s0, c0
            for _ in range(steps):
                s, c, a = step_c(theta, s, c)
                a.block_until_ready()
            return s

        def timed(fn):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            return time.perf_counter() - t0

        loop(warmup_steps)
        loop_runs = [timed(lambda: loop(n)) for _ in range(repeats)]
        scan_runs = [timed(lambda: scan_c(theta, track)) for _ in range(repeats)]
        s, c, lat = s0, c0, []
        for _ in range(n):
            t0 = time.perf_counter()
            a, c = act_c(theta, c, s)
            a.block_until_ready()
            lat.append(time.perf_counter() - t0)
            s = env_c(s, a)
        cs = self.compile_s
        return {
            "control_steps": n,
            "loop_s": float(np.mean(loop_runs)),
            "loop_runs_s": loop_runs,
            "scan_s": float(np.mean(scan_runs)),
            "scan_runs_s": scan_runs,
            "act_ms": 1e3 * float(np.mean(lat)),
            "act_max_ms": 1e3 * float(np.max(lat)),
            "compile_scan_s": cs["scan"],
            "compile_loop_step_s": cs["loop_step"],
            "compile_act_s": cs["act"],
        }


def evaluate_controller(
    ev: Evaluator,
    theta=None,
    los_seed: int = 0,
    tracks=tr.TEST_TRACKS,
    timing: bool = True,
    repeats: int = 3,
) -> tuple[dict, dict]:
    """Metrics (spec §2.5), optional run times and traces on Spiral-RT and LOS-RT
    ``los_seed``: ``({track: {metric: float}}, {track: Trace})``."""
    batch = test_tracks(ev.env, (los_seed,))  # spiral_rt, los_rt
    r, m = ev.rollouts(theta, batch)
    results, traces = {}, {}
    for i, name in enumerate(tr.TEST_TRACKS):
        if name not in tracks:
            continue
        res = {k: float(v[i]) for k, v in m.items()}
        if timing:
            res.update(ev.timing(theta, _index(batch, i), repeats))
        results[name] = res
        traces[name] = Trace.from_rollout(_index(r, i), ev.env.config.control_dt)
    return results, traces


SUMMARY_METRICS = ("tracking_error", "rmse", "max_error", "energy", "energy_sq")


def summarize(m: dict, los_seeds) -> dict:
    """Metrics of a :func:`test_tracks` batch (Spiral-RT first, then the LOS seeds) as
    ``{"spiral_rt": {metric: value}, "los_rt": {metric: {"mean", "std"}, "crashed": count,
    "seeds": [...]}}``.  A non-finite Σ‖e‖ (a state that blew up) makes mean and std inf."""
    m = {k: np.asarray(v) for k, v in m.items()}
    spiral = {k: float(v[0]) for k, v in m.items()}
    los = {k: {"mean": float(np.mean(m[k][1:])), "std": float(np.std(m[k][1:]))} for k in SUMMARY_METRICS}
    los["crashed"] = int(np.sum(m["crashed"][1:] > 0))
    los["seeds"] = [int(s) for s in los_seeds]
    return {"spiral_rt": spiral, "los_rt": los}


def los_statistics(ev: Evaluator, theta=None, los_seeds=range(1, 21), keys=None) -> dict:
    """:func:`summarize` of Spiral-RT and the LOS-RT test instances ``los_seeds`` (one
    compiled batch)."""
    los_seeds = tuple(los_seeds)
    _, m = ev.rollouts(theta, test_tracks(ev.env, los_seeds), keys)
    return summarize(m, los_seeds)


# --------------------------------------------------------------------------- trained policies


class LoadedRun(NamedTuple):
    config: Any  # TrainConfig
    env_config: EnvConfig  # the run's (training) env config
    epoch: int | dict  # the checkpoint's epoch, or {seed: epoch} of the selected policies
    build: Build  # theta = (actor params, obs stats or None) -> policy Controller
    thetas: list  # [(seed, theta)] for every seed of the run


def load_run(run_dir: str, epoch: int | None = None, best: bool = False) -> LoadedRun:
    """A quadrotor training run's checkpoint ``epoch`` (default: the latest) as policy
    controllers, one per seed, with the env config the run trained on (the policy must see
    the observation layout it was trained with).  ``best``: instead, each seed's policy
    selected on the validation tracks during training (``run_dir/best/``)."""
    from ttd3_jax import checkpoint as ckpt
    from ttd3_jax.runner import load_config, load_train_state
    from ttd3_jax.train import QUADROTOR, policy_controller, quad_env_config

    c = load_config(run_dir)
    if c.env != QUADROTOR:
        raise ValueError(f"{run_dir!r} is a {c.env!r} run; only quadrotor runs can be evaluated here")
    if best:
        return _load_selected(run_dir, c)
    if epoch is None:
        epoch = ckpt.latest_epoch(ckpt.manager(run_dir))
    c, trainer, state = load_train_state(run_dir, epoch)
    nets = trainer.nets

    def build(theta):
        actor, stats = theta
        return policy_controller(nets, actor, stats)

    thetas = [
        (c.seed + i, (_index(state.actor, i), _index(state.obs_stats, i) if c.normalize_obs else None))
        for i in range(c.num_seeds)
    ]
    return LoadedRun(c, quad_env_config(c), int(epoch), build, thetas)


def _load_selected(run_dir: str, c) -> LoadedRun:
    from ttd3_jax import checkpoint as ckpt
    from ttd3_jax import normalize as nrm
    from ttd3_jax.train import initial_actor, make_trainer, policy_controller, quad_env_config

    record = ckpt.best_record(run_dir)
    seeds = range(c.seed, c.seed + c.num_seeds)
    missing = [s for s in seeds if s not in record]
    if missing:
        raise FileNotFoundError(f"no selected policy for seed(s) {missing} in {run_dir!r} (best/best.json)")
    trainer = make_trainer(c)
    like = {
        "actor": initial_actor(trainer, jax.random.PRNGKey(0)),
        "obs_stats": nrm.init(trainer.spec.obs_size) if c.normalize_obs else None,
    }

    def build(theta):
        actor, stats = theta
        return policy_controller(trainer.nets, actor, stats)

    thetas = []
    for s in seeds:
        p = ckpt.load_policy(run_dir, s, like)
        thetas.append((s, (p["actor"], p["obs_stats"])))
    return LoadedRun(c, quad_env_config(c), {s: record[s]["epoch"] for s in seeds}, build, thetas)


# --------------------------------------------------------------------------- CLI helpers


def _json_safe(x):
    """JSON-ready copy: non-finite floats become None (strict JSON has no inf/nan)."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _fmt(x: float, spec: str) -> str:
    return format(x, spec) if math.isfinite(x) else "inf" if x > 0 else "nan"


def format_results(results: dict[str, dict[str, dict]], timing: bool) -> str:
    """The CLI's table: one row per (label, track)."""
    head = f"{'':<14} {'track':<10} {'Σ||e|| [m]':>11} {'RMSE [m]':>9} {'max [m]':>8} {'crash':>5} "
    head += f"{'Σ||a||':>8} {'Σaᵀa':>8}"
    if timing:
        head += f" {'steps':>5} {'compile s':>9} {'loop s':>7} {'scan s':>7} {'act ms':>7}"
    lines = [head]
    for label, per_track in results.items():
        for name, m in per_track.items():
            row = (
                f"{label:<14} {name:<10} {_fmt(m['tracking_error'], '11.2f')} {_fmt(m['rmse'], '9.4f')} "
                f"{_fmt(m['max_error'], '8.4f')} {int(m['crashed']):>5} {_fmt(m['energy'], '8.1f')} "
                f"{_fmt(m['energy_sq'], '8.1f')}"
            )
            if timing:
                row += (
                    f" {m['control_steps']:>5} {m['compile_scan_s']:>9.2f} {m['loop_s']:>7.3f} "
                    f"{m['scan_s']:>7.3f} {m['act_ms']:>7.3f}"
                )
            lines.append(row)
    return "\n".join(lines)


# --------------------------------------------------------------------------- CLI


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m ttd3_jax.evaluate",
        description=(
            "Evaluate a trained policy (RUN_DIR) or a classical controller (--controller) in closed loop "
            "on Spiral-RT and LOS-RT: tracking metrics, run times, optional robustness, JSON and plots."
        ),
    )
    ap.add_argument("run_dir", nargs="?", default=None, help="training run directory: evaluate its policy")
    ap.add_argument(
        "--controller", default=None, choices=CONTROLLERS, help="classical controller (default geometric)"
    )
    ap.add_argument("--epoch", type=int, default=None, help="checkpoint of RUN_DIR (default: the latest)")
    ap.add_argument(
        "--best", action="store_true", help="RUN_DIR's policies selected on the validation tracks (best/)"
    )
    ap.add_argument("--seed-index", type=int, default=None, help="only this seed of RUN_DIR (default: all)")
    ap.add_argument(
        "--preset", default=None, choices=PRESETS, help="env preset of --controller (default paper)"
    )
    ap.add_argument(
        "--env-overrides",
        nargs="+",
        default=None,
        metavar="NAME=VALUE",
        help="EnvConfig fields of --controller's env (and of its model) on top of --preset "
        "(values in JSON), e.g. "
        "action_repeat=5 'quad={\"mass\": 1.8}'; the evaluation protocol's fields are refused",
    )
    ap.add_argument("--track", default="all", choices=("all", *tr.TEST_TRACKS))
    ap.add_argument("--los-seed", type=int, default=0, help="LOS-RT test instance (0 = headline)")
    ap.add_argument("--json", default=None, help="write results here (default RUN_DIR/evaluation.json)")
    ap.add_argument(
        "--plots", default=None, help="write plots and trace CSVs here (default: the JSON file's directory)"
    )
    ap.add_argument(
        "--timing",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="measure run times: Python loop, scan, per-call latency (default on)",
    )
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per run-time figure (default 3)")
    ap.add_argument("--robustness", action="store_true", help="also evaluate under wind, mass, noise, delay")
    ap.add_argument("--robustness-seeds", type=int, default=20, help="LOS-RT seeds 1..N for --robustness")
    ap.add_argument("--nmpc-horizon", type=int, default=None, help="NMPC nodes N (nmpc only)")
    ap.add_argument(
        "--nmpc-solve-every", type=int, default=None, help="NMPC control steps between re-solves (nmpc only)"
    )
    ap.add_argument("--nmpc-weight-scale", type=float, default=None, help="NMPC state-weight scale")
    args = ap.parse_args(argv)
    if args.los_seed < 0:
        ap.error(f"--los-seed must be >= 0, got {args.los_seed}")
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.robustness_seeds < 1:
        ap.error(f"--robustness-seeds must be >= 1, got {args.robustness_seeds}")
    options = {
        name: value
        for name, value in (
            ("horizon", args.nmpc_horizon),
            ("solve_every", args.nmpc_solve_every),
            ("weight_scale", args.nmpc_weight_scale),
        )
        if value is not None
    }
    if args.run_dir is not None:
        for flag, value in (
            ("--controller", args.controller),
            ("--preset", args.preset),
            ("--env-overrides", args.env_overrides),
        ):
            if value is not None:
                ap.error(f"{flag} does not apply to RUN_DIR (the run's policy and env config are used)")
        if options:
            ap.error("--nmpc-* options need --controller nmpc")
    else:
        for flag, value in (("--epoch", args.epoch), ("--seed-index", args.seed_index)):
            if value is not None:
                ap.error(f"{flag} needs RUN_DIR")
        if args.best:
            ap.error("--best needs RUN_DIR")
        args.controller = args.controller or "geometric"
        args.preset = args.preset or "paper"
        try:
            env_overrides = parse_overrides(
                args.env_overrides or (), dict.fromkeys(EVAL_PROTOCOL_FIELDS, _PROTOCOL_REASON)
            )
            make_config(args.preset, **env_overrides)
        except (TypeError, ValueError) as e:
            ap.error(f"--env-overrides: {e}")
        if options and args.controller != "nmpc":
            ap.error("--nmpc-* options need --controller nmpc")
        if options:
            from ttd3_jax.nmpc import NMPCConfig

            try:
                NMPCConfig(**options)
            except ValueError as e:
                ap.error(str(e))

    device = device_description()
    header: dict = {"device": device, "los_seed": args.los_seed}
    if args.run_dir is not None:
        from ttd3_jax.runner import load_config

        try:
            num_seeds = load_config(args.run_dir).num_seeds
            if args.seed_index is not None and not 0 <= args.seed_index < num_seeds:
                raise ValueError(f"--seed-index must be in [0, {num_seeds - 1}], got {args.seed_index}")
            if args.best and args.epoch is not None:
                raise ValueError("--best and --epoch exclude each other")
            run = load_run(args.run_dir, args.epoch, best=args.best)
        except (FileNotFoundError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        thetas = run.thetas if args.seed_index is None else [run.thetas[args.seed_index]]
        cfg, build = run.env_config, run.build
        labels = {f"seed {s}": theta for s, theta in thetas}
        c = run.config
        header.update(run_dir=args.run_dir, epoch=run.epoch, algo=c.algo, env_preset=c.env_preset)
        which = f"selected on the validation tracks, epochs {run.epoch}" if args.best else ""
        which = which or f"epoch {run.epoch}"
        print(
            f"run {args.run_dir} {which} ({c.algo}, env preset {c.env_preset}, "
            f"hover_centered_thrust={c.hover_centered_thrust}) device={device}"
        )
        sequential = False
    else:
        cfg = make_config(args.preset, **env_overrides)
        build = controller_build(args.controller, cfg.for_eval("los_rt"), **options)
        labels = {args.controller: None}
        header.update(
            controller=args.controller, options=options, preset=args.preset, env_overrides=args.env_overrides
        )
        opts = "".join(f" {k}={v}" for k, v in options.items())
        env_o = f" env_overrides={' '.join(args.env_overrides)}" if args.env_overrides else ""
        print(f"controller={args.controller}{opts} preset={args.preset}{env_o} device={device}")
        sequential = args.controller == "nmpc" and options.get("solve_every", 1) > 1
    header["env_config"] = dataclasses.asdict(cfg)
    tracks = tr.TEST_TRACKS if args.track == "all" else (args.track,)
    ev = Evaluator(TrackingEnv(cfg.for_eval("los_rt", los_seed=args.los_seed)), build, sequential)
    results, traces = {}, {}
    for label, theta in labels.items():
        results[label], traces[label] = evaluate_controller(
            ev, theta, args.los_seed, tracks, args.timing, args.repeats
        )
    print(format_results(results, args.timing))
    p = PAPER
    print(
        "paper Σ||e|| / Σ√(uᵀu) / run s: T-TD3 Spiral-RT "
        f"{p['T-TD3']['spiral_rt']['tracking_error']} / {p['T-TD3']['spiral_rt']['energy']:.1f} / "
        f"{p['T-TD3']['spiral_rt']['run_s']:.2f}, LOS-RT {p['T-TD3']['los_rt']['tracking_error']} / "
        f"{p['T-TD3']['los_rt']['energy']:.1f} / {p['T-TD3']['los_rt']['run_s']:.2f}; MPC Spiral-RT "
        f"{p['MPC']['spiral_rt']['tracking_error']} / {p['MPC']['spiral_rt']['energy']:.1f} / "
        f"{p['MPC']['spiral_rt']['run_s']:.2f}, LOS-RT {p['MPC']['los_rt']['tracking_error']} / "
        f"{p['MPC']['los_rt']['energy']:.1f} / {p['MPC']['los_rt']['run_s']:.2f}"
    )
    if args.timing:
        print(
            "loop s: Python loop over a jitted controller+env step (mean of "
            f"{args.repeats}); scan s: one compiled scan; act ms: jitted act alone per call"
        )
    out: dict = dict(header, results=results, paper=PAPER)
    if args.robustness:
        from ttd3_jax.robustness import ROBUSTNESS_DESCRIPTIONS, evaluate_robustness, format_robustness

        seeds = range(1, args.robustness_seeds + 1)
        out["robustness"] = {}
        out["robustness_conditions"] = ROBUSTNESS_DESCRIPTIONS
        for label, theta in labels.items():
            rob = evaluate_robustness(build, theta, cfg, seeds, sequential=sequential)
            out["robustness"][label] = rob
            print(format_robustness(label, rob))
        for name, text in ROBUSTNESS_DESCRIPTIONS.items():
            print(f"  {name}: {text}")
    json_path = args.json
    if json_path is None and args.run_dir is not None:
        json_path = os.path.join(args.run_dir, "evaluation.json")
    if json_path:
        os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
        with open(json_path, "w") as fh:
            json.dump(_json_safe(out), fh, indent=2, default=str)
        print(f"wrote {json_path}")
    plots = args.plots or (os.path.dirname(os.path.abspath(json_path)) if json_path else None)
    if plots:
        from ttd3_jax.plots import plot_traces

        title = header.get("algo", args.controller)
        paths = plot_traces(traces, plots, title, args.los_seed)
        csvs = write_traces(traces, plots)
        names = ", ".join(os.path.basename(p) for p in csvs)
        print(f"wrote {len(paths)} plots and {len(csvs)} trace CSVs ({names}) to {plots}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
