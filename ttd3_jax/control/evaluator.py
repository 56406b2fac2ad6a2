"""Compiled evaluation of a controller family: batched metrics, traces and run times.  The
family's parameters (a policy's weights, or ``None``) are an argument of every program, so
the seeds of a run share one compilation.  :func:`make_controller` builds classical ones.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.control.closed_loop import (
    Controller,
    Rollout,
    closed_loop,
    hover_controller,
    metrics,
    sensed_controller,
    test_tracks,
)
from ttd3_jax.control.generalization import precision
from ttd3_jax.control.geometric import geometric_controller
from ttd3_jax.control.nmpc import NMPCConfig, nmpc_controller
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.env import TrackingEnv

CONTROLLERS = ("geometric", "hover", "nmpc")
Build = Callable[[Any], Controller]  # parameters theta (a pytree, or None) -> Controller


def make_controller(name: str, cfg: EnvConfig, **options) -> Controller:
    """Classical controller ``name`` for env config ``cfg``; ``options`` go to the
    controller's config (``nmpc``: fields of :class:`~ttd3_jax.control.nmpc.NMPCConfig`)."""
    if name == "nmpc":
        return nmpc_controller(cfg, NMPCConfig(**options))
    if options:
        raise ValueError(f"controller {name!r} takes no options, got {sorted(options)}")
    if name == "geometric":
        return geometric_controller(cfg)
    if name == "hover":
        return hover_controller(cfg)
    raise ValueError(f"unknown controller {name!r}; allowed: {CONTROLLERS}")


def fixed(controller: Controller) -> Build:
    """A :data:`Build` for a controller without parameters (use ``theta=None``)."""
    return lambda theta: controller


def controller_build(name: str, cfg: EnvConfig, sensed: bool = True, **options) -> Build:
    """:func:`make_controller` for ``cfg`` as a :data:`Build`; ``sensed`` (default) feeds it
    the observed state (:func:`~ttd3_jax.control.closed_loop.sensed_controller`)."""
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


def index(tree, i):
    """Entry ``i`` of every leaf's leading axis."""
    return jax.tree.map(lambda x: x[i], tree)


def _signature(name, args):
    leaves, treedef = jax.tree.flatten(args)
    return name, treedef, tuple((jnp.shape(x), str(jnp.result_type(x))) for x in leaves)


class Evaluator:
    """Compiled programs that evaluate one controller family (``build(theta)``) on one env;
    ``compile_s`` holds each program's first compile time.  ``sequential=True`` runs a batch
    of tracks one after the other (``lax.map``), for controllers whose ``lax.cond`` must stay
    a branch (NMPC with ``solve_every > 1``: under ``vmap`` both sides run every step)."""

    def __init__(self, env: TrackingEnv, build: Build, sequential: bool = False):
        self.env, self.build, self.sequential = env, build, sequential
        self.compile_s: dict[str, float] = {}
        self._programs: dict = {}

    def program(self, name: str, fn: Callable, *args):
        """``jit(fn)`` compiled for ``args`` (once per name and argument shapes)."""
        key = _signature(name, args)
        if key not in self._programs:
            t0 = time.perf_counter()
            self._programs[key] = jax.jit(fn).lower(*args).compile()
            self.compile_s.setdefault(name, time.perf_counter() - t0)
        return self._programs[key]

    def episode(self, theta, track, key):
        """``(Rollout, metrics)`` of one episode on ``track`` from the evaluation start."""
        env = self.env
        r = closed_loop(env, self.build(theta), env.reset_with_track(key, track))
        return r, metrics(env, r)

    def rollouts(self, theta, tracks: tr.Track, keys: jax.Array | None = None):
        """``(Rollout, metrics)`` on the host, one episode per track (leading axis).  ``keys``
        (one per track) seed wind and observation noise; default ``PRNGKey(0)`` for all."""
        n = tracks.kind.shape[0]
        if keys is None:
            keys = jnp.stack([jax.random.PRNGKey(0)] * n)

        def batch(theta, tracks, keys):
            if self.sequential:
                return jax.lax.map(lambda tk: self.episode(theta, *tk), (tracks, keys))
            return jax.vmap(self.episode, in_axes=(None, 0, 0))(theta, tracks, keys)

        out = self.program("rollouts", batch, theta, tracks, keys)(theta, tracks, keys)
        return jax.device_get(out)

    def timing(self, theta, track: tr.Track, repeats: int = 3, warmup_steps: int = 10) -> dict:
        """Run time of one episode on ``track`` (spec §2.5) after compilation: ``loop_s``
        drives it from Python, one jitted (controller + env step) call per control step,
        waiting for each action, as the paper timed it; ``scan_s`` is one compiled
        ``lax.scan``; ``act_ms`` the jitted ``act`` alone per call (means of ``repeats``
        runs); ``compile_*_s`` those programs' compile times."""
        env, build, key = self.env, self.build, jax.random.PRNGKey(0)

        def start(theta, track):
            s = env.reset_with_track(key, track)
            return s, build(theta).init(s)

        def step(theta, s, c):
            a, c = build(theta).act(c, s)
            return env.step(s, a), c, a

        s0, c0 = self.program("start", start, theta, track)(theta, track)
        step_c = self.program("loop_step", step, theta, s0, c0)
        scan_c = self.program(
            "scan", lambda th, t: self.episode(th, t, key)[1]["tracking_error"], theta, track
        )
        act_c = self.program("act", lambda th, c, s: build(th).act(c, s), theta, c0, s0)
        env_c = self.program("env_step", env.step, s0, jnp.zeros(4, s0.obs.dtype))

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
        loop_runs = [timed(lambda: loop(env.episode_length)) for _ in range(repeats)]
        scan_runs = [timed(lambda: scan_c(theta, track)) for _ in range(repeats)]
        s, c, lat = s0, c0, []
        for _ in range(env.episode_length):
            t0 = time.perf_counter()
            a, c = act_c(theta, c, s)
            a.block_until_ready()
            lat.append(time.perf_counter() - t0)
            s = env_c(s, a)
        cs = self.compile_s
        return dict(control_steps=env.episode_length, loop_s=float(np.mean(loop_runs)), loop_runs_s=loop_runs,
                    scan_s=float(np.mean(scan_runs)), scan_runs_s=scan_runs, act_ms=1e3 * float(np.mean(lat)),
                    act_max_ms=1e3 * float(np.max(lat)), compile_scan_s=cs["scan"],
                    compile_loop_step_s=cs["loop_step"], compile_act_s=cs["act"])  # fmt: skip


def evaluate_controller(ev: Evaluator, theta=None, *, los_seed: int = 0, tracks=tr.TEST_TRACKS,
                        timing: bool = True, repeats: int = 3) -> tuple[dict, dict]:  # fmt: skip
    """Metrics (spec §2.5), optional run times and traces on Spiral-RT and LOS-RT
    ``los_seed``: ``({track: {metric: float}}, {track: Trace})``."""
    batch = test_tracks(ev.env, (los_seed,))  # spiral_rt, los_rt
    r, m = ev.rollouts(theta, batch)
    results, traces = {}, {}
    for i, name in enumerate(tr.TEST_TRACKS):
        if name not in tracks:
            continue
        res = {k: float(v[i]) for k, v in m.items()} | {"control_hz": 1.0 / ev.env.config.control_dt}
        if timing:
            res.update(ev.timing(theta, index(batch, i), repeats))
        results[name] = res
        traces[name] = Trace.from_rollout(index(r, i), ev.env.config.control_dt)
    return results, traces


def evaluate_tracks(ev: Evaluator, theta, tracks: dict[str, tr.Track], timing: bool = True,
                    repeats: int = 3) -> tuple[dict, dict]:  # fmt: skip
    """Like :func:`evaluate_controller` on any named tracks (one compiled batch), with the
    precision figures of :func:`~ttd3_jax.control.generalization.precision`."""
    names, cdt = list(tracks), ev.env.config.control_dt
    batch = ct.stack([tracks[n] for n in names], ev.env.config.dt)
    r, m = ev.rollouts(theta, batch)
    results, traces = {}, {}
    for i, name in enumerate(names):
        ri = index(r, i)
        results[name] = (
            {k: float(v[i]) for k, v in m.items()} | precision(ri, cdt, name) | {"control_hz": 1 / cdt}
        )
        if timing:
            results[name].update(ev.timing(theta, index(batch, i), repeats))
        traces[name] = Trace.from_rollout(ri, cdt)
    return results, traces


SUMMARY_METRICS = ("tracking_error", "rmse", "max_error", "energy", "energy_sq")


def summarize(m: dict, los_seeds) -> dict:
    """Metrics of a :func:`~ttd3_jax.control.closed_loop.test_tracks` batch (Spiral-RT first,
    then the LOS seeds) as ``{"spiral_rt": {metric: value}, "los_rt": {metric: {"mean",
    "std"}, "crashed": count, "seeds": [...]}}``.  A non-finite Σ‖e‖ makes mean and std inf."""
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
