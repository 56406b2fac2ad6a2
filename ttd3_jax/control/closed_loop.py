"""The controller protocol, the closed loop and its metrics (spec §2.5).  A
:class:`Controller` is ``init(env_state) -> carry`` and ``act(carry, env_state) -> (action
(4,), carry)``; :func:`closed_loop` runs one for an episode as one ``lax.scan``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttd3_jax.sim import observation
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.dynamics import QuadState
from ttd3_jax.sim.env import (
    TrackingEnv,
    action_to_control,
    control_to_action,
    hover_action,
    validation_tracks,
)
from ttd3_jax.sim.env_state import last_applied_action, reference_shift
from ttd3_jax.sim.vehicle_mix import pin_vehicle


class Controller(NamedTuple):
    init: Callable  # env State -> carry
    act: Callable  # (carry, env State) -> (action (4,), carry)


def policy_controller(policy: Callable[[jax.Array], jax.Array]) -> Controller:
    """A memoryless controller from ``policy(obs) -> action``: obs as the env emits it
    (``TrackingEnv.observation_size``,), action (4,) in [-1, 1]."""
    return Controller(init=lambda s: (), act=lambda carry, s: (policy(s.obs), carry))


def hover_controller(cfg: EnvConfig) -> Controller:
    """Constant hover thrust and zero rates: the do-nothing baseline."""
    a = hover_action(cfg)
    return Controller(init=lambda s: (), act=lambda c, s: (a.astype(s.obs.dtype), c))


def sensed_controller(controller: Controller, cfg: EnvConfig) -> Controller:
    """``controller`` fed with the vehicle state as the env observes it (p, v, q, and ω when
    observed, read from ``obs``) instead of the true state, so that observation noise
    reaches classical controllers as it reaches a policy.  Without noise the two agree
    (q and −q are the same attitude; track-frame positions are shifted back)."""

    lay = observation.layout(cfg)

    def sensed(s):
        ps, o = s.pipeline_state, s.obs
        p = o[lay.slice("p")] + reference_shift(cfg, ps)  # (the observed p, without the policy's shift)
        if cfg.observation.obs_frame == "track":
            p = p + tr.position(ps.track, ps.k, cfg.dt).astype(p.dtype)
        w = o[lay.slice("omega")] if lay.has("omega") else ps.quad.w
        quad = QuadState(p=p, v=o[lay.slice("v")], q=o[lay.slice("q")], w=w)
        return s.replace(pipeline_state=ps.replace(quad=quad))

    return Controller(
        init=lambda s: controller.init(sensed(s)), act=lambda c, s: controller.act(c, sensed(s))
    )


@struct.dataclass
class Rollout:
    """One episode, per control step i = 0 … T-1 (T = episode_length)."""

    pos: jax.Array  # (T, 3) m, position after step i
    ref: jax.Array  # (T, 3) m, reference at the same time
    action: jax.Array  # (T, 4) applied normalised action (of the step's last physics step)
    error_sum: jax.Array  # (T,) m, Σ ||e|| over the physics steps of control step i
    crashed: jax.Array  # (T,) 1.0 once the tracking error exceeded e_max or went non-finite
    vel: jax.Array  # (T, 3) m/s, velocity after step i (world frame)
    quat: jax.Array  # (T, 4) attitude after step i, scalar-first unit quaternion (body to world)


def closed_loop(env: TrackingEnv, controller: Controller, state) -> Rollout:
    """Run ``env.episode_length`` control steps from ``state`` (pure; jit/vmap it)."""
    c = env.config

    def body(carry, _):
        s, ctrl = carry
        a, ctrl = controller.act(ctrl, s)
        # the action the env's last physics step of this control step applies: the previous one
        # under ``action_delay = 1``, the one the latency picks under domain randomisation
        applied = last_applied_action(c, s.pipeline_state, a)
        s = env.step(s, a)
        ps, m = s.pipeline_state, s.metrics
        ref = tr.position(ps.track, ps.k, c.dt)
        return (s, ctrl), Rollout(
            ps.quad.p, ref, applied, m["tracking_error"], m["crashed"], ps.quad.v, ps.quad.q
        )

    init = (state, controller.init(state))
    r = jax.lax.scan(body, init, None, length=env.episode_length)[1]
    return r.replace(crashed=jnp.maximum.accumulate(r.crashed))


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


def to_paper_map(actions, cfg: EnvConfig) -> np.ndarray:
    """Normalised actions (..., 4) of an env with config ``cfg`` in the paper's action map
    (O2: thrust f_min + (a0+1)/2·(f_max − f_min), no hover centring): the same physical
    commands, so controllers trained or built with different maps become comparable."""
    paper = cfg.replace(hover_centered_thrust=False, thrust_map_mass=None, vehicles=())  # quad: a pinned one
    return np.asarray(control_to_action(paper, action_to_control(cfg, jnp.asarray(actions))))


def energy_paper_map(actions, cfg: EnvConfig) -> np.ndarray:
    """Σ‖a‖ over the physics steps (spec §2.5) of applied actions ``actions`` (..., T, 4),
    in the paper's action map (:func:`to_paper_map`; under ``hover_centered_thrust`` hover
    is a0 = 0, in the paper's map a0 = 0.4715)."""
    a = to_paper_map(actions, cfg)
    return cfg.action_repeat * np.sum(np.linalg.norm(a, axis=-1), axis=-1)


def test_tracks(env: TrackingEnv, los_seeds=(0,)) -> tr.Track:
    """Spiral-RT followed by the LOS-RT test instances ``los_seeds``, stacked on a leading
    axis with the table size of ``env`` (so one ``vmap`` evaluates them all)."""
    c = env.config
    n = env.num_segments
    tracks = [tr.spiral_rt(c.tracks.generator, n)] + [
        tr.los_test_track(s, c.tracks.generator, num_segments=n, dt=c.dt, horizon_steps=c.horizon_steps)
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


def test_and_validation_metrics(cfg: EnvConfig, controller: Controller) -> dict:
    """What a training run reports each epoch (pure; jit it): the test metrics on Spiral-RT
    and LOS-RT seed 0 (``spiral_*``, ``los_*``), in one vmapped closed loop, and
    ``val_tracking_error``, the mean Σ‖e‖ over the validation tracks (spec T8; the wide
    mixture's with ``tracks.wide_mix`` set: ``sim.env.validation_tracks``), the only figure
    used to select a policy.  ``controller`` is built for the env of ``cfg``.  With
    ``randomization.vehicles``: the test metrics of the first vehicle, and the validation mean
    averaged over each vehicle's (one policy is selected for all of them)."""
    env = TrackingEnv(cfg.for_eval("los_rt"))
    m = evaluate_on_tracks(env, controller, test_tracks(env))
    out = {}
    for i, name in enumerate(("spiral", "los")):
        out.update({f"{name}_{k}": v[i] for k, v in m.items()})
    vals = []
    for vehicle in dict.fromkeys(cfg.randomization.vehicles) or (None,):
        venv = TrackingEnv(pin_vehicle(cfg, vehicle).for_eval("validation"))
        val = validation_tracks(cfg, venv.num_segments)
        vals.append(jnp.mean(evaluate_on_tracks(venv, controller, val)["tracking_error"]))
    out["val_tracking_error"] = vals[0] if len(vals) == 1 else jnp.mean(jnp.stack(vals))
    return out
