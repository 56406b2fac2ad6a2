"""A trained policy out of JAX: an ONNX model, a dependency-free C header and a JSON sidecar.

All three compute the deterministic actor on the raw observation exactly as
:class:`~ttd3_jax.sim.env.TrackingEnv` emits it, the run's observation normalisation
included: ``a = tanh(W_L relu(... relu(W_1 clip((obs - mean) / std, ±10) + b_1) ...) + b_L)``,
an action in [-1, 1]^4 that ``policy.json``'s ``action_map`` turns into thrust and body rates.
The ONNX model needs the ``onnx`` package (``pip install -e ".[export]"``); the C header needs
nothing.  The header also builds that observation on a vehicle: ``ttd3_step`` (:func:`c_state`)
takes the measured state and the reference points of a control step, updates what the policy
keeps between steps as the env does (``policy.json``'s ``c_api``, :func:`c_api`), and returns
the action.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from importlib import metadata
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ttd3_jax.interop.c_header import C_PARTS, c_header
from ttd3_jax.run import rundir
from ttd3_jax.run import spec as sp
from ttd3_jax.sim import observation
from ttd3_jax.sim import randomization as rz
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import EnvConfig, TracksConfig
from ttd3_jax.sim.env import thrust_range
from ttd3_jax.sim.track_families import FAMILIES
from ttd3_jax.sim.vehicles import vehicle_of
from ttd3_jax.td3 import networks

ONNX_OPSET = 17
FILES = ("policy.onnx", "policy.h", "policy.json")


class Policy(NamedTuple):
    """The actor as plain float32 arrays: ``layers`` [(W (n_in, n_out), b (n_out,))], the
    last one tanh-squashed, the others ReLU; ``mean`` / ``std`` (n_obs,) normalise the input
    (identity when the run does not normalise)."""

    layers: list
    mean: np.ndarray
    std: np.ndarray


def from_params(actor, stats: networks.ObsStats | None, obs_size: int) -> Policy:
    """A :class:`Policy` from flax actor params and the run's observation statistics."""
    dense = actor["params"]
    names = sorted(dense, key=lambda n: int(n.rsplit("_", 1)[1]))  # Dense_0, Dense_1, ...
    layers = [(np.asarray(dense[n]["kernel"], np.float32), np.asarray(dense[n]["bias"], np.float32))
              for n in names]  # fmt: skip
    if stats is None:
        mean, std = np.zeros(obs_size, np.float32), np.ones(obs_size, np.float32)
    else:
        mean, std = np.asarray(stats.mean, np.float32), np.asarray(networks.obs_std(stats), np.float32)
    return Policy(layers, mean, std)


def forward(p: Policy, obs: np.ndarray) -> np.ndarray:
    """The policy in numpy float32: obs (..., n_obs) -> action (..., n_act)."""
    x = np.clip((np.asarray(obs, np.float32) - p.mean) / p.std, -networks.CLIP, networks.CLIP)
    for i, (w, b) in enumerate(p.layers):
        x = x @ w + b
        x = np.tanh(x) if i == len(p.layers) - 1 else np.maximum(x, 0)
    return x


def onnx_model(p: Policy, name: str = "ttd3_policy"):
    """The policy as an ``onnx.ModelProto``: input ``obs`` [batch, n_obs] float32, output
    ``action`` [batch, n_act] float32."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        raise ImportError('writing policy.onnx needs the onnx package: pip install -e ".[export]"') from None
    n_obs, n_act = p.layers[0][0].shape[0], p.layers[-1][0].shape[1]
    init = [numpy_helper.from_array(p.mean, "obs_mean"), numpy_helper.from_array(p.std, "obs_std"),
            numpy_helper.from_array(np.float32(-networks.CLIP), "clip_lo"),
            numpy_helper.from_array(np.float32(networks.CLIP), "clip_hi")]  # fmt: skip
    nodes = [helper.make_node("Sub", ["obs", "obs_mean"], ["centred"]),
             helper.make_node("Div", ["centred", "obs_std"], ["scaled"]),
             helper.make_node("Clip", ["scaled", "clip_lo", "clip_hi"], ["h0"])]  # fmt: skip
    for i, (w, b) in enumerate(p.layers):
        init += [numpy_helper.from_array(w, f"W{i}"), numpy_helper.from_array(b, f"b{i}")]
        last = i == len(p.layers) - 1
        nodes += [helper.make_node("MatMul", [f"h{i}", f"W{i}"], [f"m{i}"]),
                  helper.make_node("Add", [f"m{i}", f"b{i}"], [f"z{i}"]),
                  helper.make_node("Tanh" if last else "Relu", [f"z{i}"],
                                   ["action" if last else f"h{i + 1}"])]  # fmt: skip
    graph = helper.make_graph(
        nodes, name, [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", n_obs])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", n_act])], init,
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", ONNX_OPSET)],
                              producer_name="ttd3_jax")  # fmt: skip
    model.ir_version = min(model.ir_version, 8)  # readable by onnxruntime releases since 1.11
    onnx.checker.check_model(model)
    return model


def c_api(cfg: EnvConfig) -> dict:
    """``policy.json``'s ``c_api``: how firmware flies ``policy.h`` (``call_order``, one call per
    control step) and what the header's ``ttd3_observe`` builds from what (:func:`c_state` writes
    it in C): the state kept, the reference points p_d(k + n) read, the parts in order, the
    frame, the error's reference point, qw >= 0, the memory's and the reference integral's
    constants. ``ValueError`` names an observation part the header cannot build."""
    o, parts = cfg.observation, observation.layout(cfg).parts
    previews = [observation.preview_name(t) for t in o.preview_s]
    for part in parts:
        if part.critic_only or part.name not in (*C_PARTS, *previews):
            why = "only the critics see it" if part.critic_only else f"it builds {[*C_PARTS, *previews]}"
            raise ValueError(f"policy.h cannot build the observation part {part.name!r}: {why}")
    # the reference points read, in physics steps after the control step's k (p_d,k+1 is p_ahead at L = 1)
    refs = dict(now=0) if o.obs_frame == "track" or o.obs_memory or o.err_ref == "current" else {}
    refs.update(dict(next=1) if o.err_ref == "next" and o.lookahead_k != 1 else {}, ahead=o.lookahead_k)
    refs.update(
        {name: o.lookahead_k + round(t / cfg.dt) for name, t in zip(previews, o.preview_s, strict=True)}
    )
    kept = (("last_action", o.obs_memory), ("error_integral", o.obs_memory),
            ("ref_int", o.ref_integral_gain > 0), ("action_history", bool(o.action_history_s)))  # fmt: skip
    state = [n for n, on in kept if on]
    m, ri = memory_spec(cfg), reference_integral_spec(cfg)
    return dict(
        call_order=c_call_order(cfg, state, any(part.name == "omega" for part in parts)),
        state=state,
        reference_points=refs,
        reference_points_meaning="ref[3 i + j] (policy.h's ref): axis j of p_d (m, world frame) at "
        "physics step k + the i-th value, k the control step's physics step (ttd3_ref_steps)",
        parts={part.name: part.size for part in parts},
        frame=o.obs_frame,
        error_reference="now" if o.err_ref == "current" else ("next" if "next" in refs else "ahead"),
        canonical_q=o.canonical_q_obs,
        memory={k: m[k] for k in ("leak", "dt_s", "action_history_keep") if k in m} if o.obs_memory else None,
        reference_integral={k: ri[k] for k in ("gain_per_s", "band_m", "limit_m")}
        if o.ref_integral_gain > 0
        else None,
    )


def c_call_order(cfg: EnvConfig, state: list[str], omega: bool) -> list[str]:
    """How firmware calls policy.h (its opening comment, ``c_api``'s ``call_order``)."""
    kept = f"keeps {', '.join(state)} between control steps" if state else "keeps nothing between steps"
    r, dt = cfg.action_repeat, cfg.dt
    vehicle = ["  s.vehicle = TTD3_VEHICLE_<NAME>;  the vehicle flown (ttd3_reset: the first one's)"]
    return [
        f"Flying it: one call per control step, every {r} physics steps of {dt:g} s ({r * dt * 1e3:g} ms).",
        f"This policy {kept} (ttd3_state).",
        "",
        "  ttd3_state s;",
        "  ttd3_reset(&s);                   at the start of a flight",
        *(vehicle if cfg.randomization.vehicles else []),
        f"  at each control step, physics step k = 0, {r}, {2 * r}, ... since the start:",
        "    float ref[3 * TTD3_REF_COUNT], action[TTD3_ACTION_SIZE];",
        f"    ref[3 * i + j] = axis j of p_d (m, world frame) at time (k + ttd3_ref_steps[i]) * {dt:g} s,",
        "                     for each reference point i < TTD3_REF_COUNT (TTD3_REF_AHEAD, ...)",
        "    ttd3_step(&s, p, v, q, omega, ref, action);",
        "    apply action (in [-1, 1]^4; policy.json: action_map) until the next control step",
        "",
        "p (m), v (m/s): measured, world frame; q = (qw, qx, qy, qz): measured, body to world, either sign;",
        "omega (rad/s): body rates, body frame" + ("." if omega else " (unread by this policy: NULL)."),
        "ttd3_step makes these three calls; make them instead to apply an action other than the policy's:",
        "  ttd3_observe(&s, p, v, q, omega, ref, obs);  updates the state with the measured p (not in the",
        "                                               first call after ttd3_reset), then fills obs",
        "  ttd3_policy_forward(obs, action);",
        "  ttd3_remember(&s, applied);  the action applied until the next step (clipped to [-1, 1])",
    ]  # fmt: skip


def observation_layout(cfg: EnvConfig, obs_size: int) -> list[str]:
    """Names of the observation's entries in order (:func:`ttd3_jax.sim.observation.layout`)."""
    names = observation.layout(cfg).names
    if len(names) != obs_size:
        raise ValueError(f"the observation layout has {len(names)} entries, the policy reads {obs_size}")
    return names


def action_map(cfg: EnvConfig) -> dict:
    """How the action in [-1, 1]^4 becomes thrust (N) and body-rate commands (rad/s)."""
    lo, hi, hover = (float(x) for x in thrust_range(cfg))
    rule = ("a0 >= 0: hover + a0 (max - hover); a0 < 0: hover + a0 (hover - min)"
            if cfg.vehicle.hover_centered_thrust else "min + (a0 + 1) / 2 (max - min)")  # fmt: skip
    return dict(thrust_N=dict(min=lo, max=hi, hover=hover, rule=rule),
                body_rates_rad_s=dict(min=list(map(float, np.broadcast_to(cfg.vehicle.quad.rate_min, 3))),
                                      max=list(map(float, np.broadcast_to(cfg.vehicle.quad.rate_max, 3))),
                                      rule="a1..a3 -> min + (a + 1) / 2 (max - min)"))  # fmt: skip


RATE_MODEL_MEANING = {
    "instant": "the commanded body rates are the vehicle's body rates at once (no rate dynamics); "
    "the vehicle's tau_rate, inertia, k_rate and torque_max are not used",
    "first_order": "body rates follow the command as a first-order lag with time constant tau_rate; "
    "inertia, k_rate and torque_max are not used",
    "torque": "a rate loop, torque = J k_rate (w_cmd - w) + w x Jw clipped to torque_max, drives "
    "the body rates through the diagonal inertia J; tau_rate is not used",
    "firmware": "the vehicle's flight firmware tracks the commands (vehicle.loop, ttd3_jax.sim.inner_loop): "
    "every physics step a rate PID per body axis (e = w_cmd - w; I = clip(I + e dt, +-i_limit); "
    "tau = clip(kp e + ki I - kd (w - w_prev) / dt, +-torque_limit)), a mixer of (thrust, tau) into four "
    "rotor thrusts (x configuration, arm, yaw_coeff; an excess over motor_max taken off all four, each "
    "clipped to [motor_min, motor_max]), rotor speeds s (1 = full thrust) lagging their commands with "
    "tau_up / tau_down, rotor thrust motor_max (curve s^2 + (1 - curve) s), and air drag -drag v; "
    "the body rates follow from the torques through the diagonal inertia. On a vehicle, its own "
    "firmware does this: send it the thrust and body-rate commands",
}
CONVENTIONS = dict(
    world_frame="right-handed, z up; gravity along -z",
    position="p (m), world frame",
    velocity="v (m/s), world frame",
    attitude="unit quaternion q = (qw, qx, qy, qz), scalar first, Hamilton convention, rotating "
    "body-frame vectors into the world frame",
    body_rates="omega (rad/s), body frame; thrust along the body z axis",
)
DYNAMICS = dict(
    position="dp/dt = v",
    velocity="dv/dt = c R(q) (0, 0, 1) - (0, 0, vehicle.gravity): c = thrust / vehicle.mass when "
    "vehicle.thrust_units is 'newton', c = thrust otherwise; no drag, no ground plane, no other force",
    attitude="dq/dt = 1/2 q (x) (0, omega_att), Hamilton product: omega_att = the commanded rates "
    "under rate_model 'instant', the body rates omega otherwise",
    body_rates="see rate_model.meaning",
    source="docs/paper-notes.md section 1 (D1-D7) in the ttd3_jax repository; ttd3_jax.sim.dynamics",
)
PROTOCOL = dict(
    start="at rest (v = 0, omega = 0) on the track's first point p_d(0), level (q = (1, 0, 0, 0))",
    timing="the first observation is made and the first action chosen at k = 0, before the first "
    "physics step; the next at k = action_repeat, and so on",
    physics_steps=3000,
    physics_dt_s=1e-3,
    integrator="RK4 at the physics step; q renormalised after each step",
    action_hold="each action is held for action_repeat physics steps (the control period)",
    tracking_error="sum over physics steps k = 1 ... 3000 of ||p(k) - p_d(k)|| (m), never terminated early",
    rmse_and_max_error="of ||p(k) - p_d(k)|| at the control steps k = action_repeat, 2 action_repeat, "
    "..., 3000 only",
    crash="||p(k) - p_d(k)|| > 1 m at any physics step",
    disturbances="none: no wind, no observation noise",
)
TEST_TRACKS = ("experiments/tracks/protocol/ in the ttd3_jax repository: spiral_rt.csv, los_rt_seed00.csv "
               "(the paper's LOS-RT) ... los_rt_seed20.csv, validation_00.csv ... validation_09.csv "
               "(the fast preset's validation tracks; python experiments/protocol_tracks.py "
               "--validation-preset P writes preset P's); t,x,y,z at every physics step. LOS-RT and the "
               "validation tracks are drawn with JAX's Threefry PRNG: outside JAX only these files "
               "rebuild them")  # fmt: skip


def observation_spec(cfg: EnvConfig, obs_size: int) -> dict:
    """What each observation entry means: frame, look-ahead, error reference, quaternion sign."""
    track, look = cfg.observation.obs_frame == "track", cfg.observation.lookahead_k
    return dict(
        names=observation_layout(cfg, obs_size),
        parts=observation.layout(cfg).describe(),
        frame=(
            "track: positions relative to p_d,k, the reference at the current physics step k (a shift "
            "of origin only; the axes are the world's); velocity stays world-frame"
        )
        if track
        else "world: positions in world coordinates",  # fmt: skip
        p_d_k="the reference position at physics step k (time k * physics_dt_s since the start)",
        lookahead_physics_steps=cfg.observation.lookahead_k,
        p_ahead=f"p_d,k+{look}: the reference {look * cfg.dt * 1e3:g} ms ahead",
        error_reference=("p_err = p_d,k" if cfg.observation.err_ref == "current" else "p_err = p_d,k+1"),
        quaternion_sign="q observed with qw >= 0 (q and -q are one attitude)"
        if cfg.observation.canonical_q_obs
        else "q as integrated (either sign)",  # fmt: skip
        noise="none in the evaluation protocol",
        memory=memory_spec(cfg) if cfg.observation.obs_memory else None,
        preview=(
            f"for each t in preview_s (s): p_d at physics step k + {look} + round(t / physics_dt_s) "
            f"minus p_d,k+{look} (m), the reference t s after p_ahead relative to it"
        )
        if cfg.observation.preview_s
        else None,  # fmt: skip
        preview_s=list(cfg.observation.preview_s),
    )


def memory_spec(cfg: EnvConfig) -> dict:
    """How a deployment keeps the observation's memory parts (``obs_memory``) from step to step."""
    leak = math.exp(-cfg.control_dt / cfg.observation.memory_tau)
    out = dict(
        reset="last_action = 0 (4), error_integral = 0 (3) at the start of a flight",
        last_action="after each control step: the action the policy output (clipped to [-1, 1])",
        error_integral=(
            "after each control step, with p the measured position and p_d the reference at that "
            f"time: error_integral = leak * error_integral + dt * (p_d - p), leak = exp(-dt / tau) = "
            f"{leak!r}, dt = {cfg.control_dt!r} s, tau = {cfg.observation.memory_tau!r} s"
        ),
        leak=leak,
        dt_s=cfg.control_dt,
        reference_integral=reference_integral_spec(cfg) if cfg.observation.ref_integral_gain > 0 else None,
    )
    if cfg.observation.action_history_s:
        keep = list(cfg.action_history_keep)
        out.update(
            action_history=(
                "after each control step, for each time constant tau_j (s) of "
                f"{list(cfg.observation.action_history_s)}: action_history[j] = keep_j * action_history[j] "
                "+ (1 - keep_j) * a (4 each, a the applied action clipped to [-1, 1], after last_action), "
                f"keep_j = exp(-dt / tau_j) = {keep}; zeros at the start of a flight"
            ),
            action_history_keep=keep,
        )
    return out


def reference_integral_spec(cfg: EnvConfig) -> dict:
    """How a deployment keeps the integral that shifts the observed reference
    (``observation.ref_integral_gain``) and applies it."""
    o = cfg.observation
    return dict(
        reset="ref_int = 0 (3) at the start of a flight",
        update=(
            "after each control step, before the observation is built (the same p and p_d as "
            f"error_integral), per axis: e = p_d - p; ref_int = ref_int + dt * e if |e| < "
            f"{o.ref_integral_band!r} m, else unchanged; dt = {cfg.control_dt!r} s"
        ),
        shift=(
            f"s = clip({o.ref_integral_gain!r} * ref_int, -{o.ref_integral_limit!r}, "
            f"{o.ref_integral_limit!r}) "
            "per axis (m); every position part is built with p - s in place of the measured p "
            "(p, p_ahead_error, error), so the policy tracks p_d + s"
        ),
        gain_per_s=o.ref_integral_gain,
        band_m=o.ref_integral_band,
        limit_m=o.ref_integral_limit,
    )


def expected_errors(run_dir: str, seed: int, epoch: int) -> dict:
    """The Σ‖e‖ this policy reached in its run's evaluation (metrics.csv), for a deployment to
    check itself against; empty when that epoch was not evaluated (the warm-up)."""
    rows = [r for r in rundir.read_metrics(run_dir) if int(r["epoch"]) == epoch and int(r["seed"]) == seed]
    if not rows:
        return {}
    names = dict(spiral_rt="spiral_tracking_error", los_rt_seed00="los_tracking_error",
                 validation_mean="val_tracking_error")  # fmt: skip
    return {k: rows[-1][v] for k, v in names.items() if v in rows[-1]}


def trained_under(cfg: EnvConfig) -> dict:
    """What the training episodes drew and flew in, beyond the nominal vehicle: the domain
    randomisation (ranges, each drawn per episode; factors on the vehicle above, latency in s,
    bias ± m per axis or a fixed vector, wind mean ± m/s² per axis), the disturbances, and the
    track mixture (``wide_mix``: weights of the families, empty: the paper's mixture)."""
    r = dataclasses.asdict(cfg.randomization)
    known = (
        "each drawn vehicle's own (vehicles below)"
        if cfg.randomization.vehicles
        else "the nominal vehicle above"
    )
    return dict(randomization=r, randomized=rz.active(cfg),
                disturbances=dataclasses.asdict(cfg.disturbances),
                wide_mix=dict(zip(FAMILIES, cfg.tracks.wide_mix, strict=True)) if cfg.tracks.wide_mix else {},
                action_map=f"of {known}: thrust and rate errors are not in it")  # fmt: skip


def vehicles_spec(cfg: EnvConfig) -> dict | None:
    """``policy.json``'s ``vehicles`` of a policy trained with ``randomization.vehicles`` (else
    None): where the observation holds the flown vehicle's descriptor, and each vehicle's
    descriptor values (float32, as the env computes them), action map and parameters."""
    mix = cfg.randomization.vehicles
    if not mix:
        return None
    per = {}
    for name in dict.fromkeys(mix):
        c = vm.pin_vehicle(cfg, name)
        d = vm.descriptor(rz.vehicle_arrays(c.vehicle.quad, jnp.float32))
        per[name] = dict(descriptor=[float(x) for x in np.asarray(d)], action_map=action_map(c),
                         vehicle=dataclasses.asdict(c.vehicle.quad))  # fmt: skip
    return dict(descriptor_start=observation.layout(cfg).slice("vehicle").start,
                descriptor_entries=list(vm.DESCRIPTOR), meaning=vm.DESCRIPTOR_MEANING,
                trained_on=f"each episode drew s ~ U[0, 1] and flew the vehicle between {mix[0]} (s = 0) and "
                f"{mix[1]} (s = 1), every parameter geometric between theirs; the randomisation's factors "
                "(trained_under) around it, unknown",
                use="fill obs[descriptor_start:descriptor_start + 3] with the flown vehicle's descriptor and "
                "map the action with its action_map (policy.h: ttd3_set_vehicle, ttd3_action_to_control); "
                "the top-level vehicle and action_map are the first vehicle's, and so are the Spiral-RT and "
                "LOS-RT figures of expected_tracking_error (its validation_mean: the mean over the vehicles)",
                per_vehicle=per)  # fmt: skip


def sidecar(run_dir: str, run: rundir.LoadedRun, seed: int, best: bool, obs_size: int) -> dict:
    """``policy.json``: what the policy reads and writes, at what rate, for which vehicle, and
    every fact a re-implementation needs to fly it and reproduce its tracking error."""
    cfg = vm.pin_vehicle(run.env_config)  # with vehicles: the first (each one's: vehicles_spec)
    quad, mix = cfg.vehicle.quad, run.env_config.randomization.vehicles
    epoch = run.epoch[seed] if isinstance(run.epoch, dict) else run.epoch
    return dict(observation=observation_layout(cfg, obs_size), obs_size=obs_size,
                observation_spec=observation_spec(cfg, obs_size), conventions=CONVENTIONS, dynamics=DYNAMICS,
                action_size=4, action_map=action_map(cfg), control_hz=1 / cfg.control_dt,
                action_repeat=cfg.action_repeat, physics_dt_s=cfg.dt, vehicle=dataclasses.asdict(quad),
                rate_model=dict(name=quad.rate_model, meaning=RATE_MODEL_MEANING[quad.rate_model]),
                evaluation_protocol=PROTOCOL, test_tracks=TEST_TRACKS,
                trained_under=trained_under(run.env_config), vehicles=vehicles_spec(run.env_config),
                env_config=dataclasses.asdict(run.env_config),
                evaluated_on=list(dict.fromkeys(mix)) or [vehicle_of(quad) or "custom"],
                expected_tracking_error=dict(sum_norm_e_m=expected_errors(run_dir, seed, epoch),
                                             protocol="evaluation_protocol above, float32"),
                source=dict(run=os.path.basename(os.path.normpath(run_dir)), seed=seed, epoch=epoch,
                            selected_on_validation=best, algo=run.spec.algo),
                ttd3_jax_version=metadata.version("ttd3_jax"),
                c_api=c_api(cfg),
                files=dict(onnx="input obs [batch, n_obs] float32 -> output action [batch, 4]",
                           c="ttd3_step(&state, p, v, q, omega, ref, action) once per control step after "
                             "ttd3_reset(&state) (c_api); ttd3_policy_forward(const float *obs, "
                             "float *action) alone: the action of an observation (also policy_forward unless "
                             "TTD3_NO_SHORT_NAMES is defined)"))  # fmt: skip


def env_config(meta: dict) -> EnvConfig:
    """The run's (training) :class:`EnvConfig` that ``policy.json`` stores as ``env_config``, for
    flying the policy in ``TrackingEnv`` (``cfg.for_eval(...)``: the protocol's nominal plant).
    Users' training tracks are dropped (files of the training machine; no evaluation reads
    them).  ``ValueError`` for a policy.json without one (exported by an older ttd3_jax)."""
    d = meta.get("env_config")
    if d is None:
        raise ValueError(
            "policy.json has no env_config (exported by an older ttd3_jax): export the run again"
        )
    tracks = {
        **d.get("tracks", {}),
        "train_tracks": [],
        "train_tracks_weight": TracksConfig.train_tracks_weight,
    }
    return sp.task_from_dict({**d, "tracks": tracks})


def write(out: str, p: Policy, meta: dict, onnx: bool = True) -> list[str]:
    """Write ``policy.onnx`` (if ``onnx``), ``policy.h`` and ``policy.json`` into ``out``; all
    are built before any is written, so a policy that cannot be exported (non-finite weights:
    ``ValueError``) leaves ``out`` as it was."""
    src = meta["source"]
    note = f"run {src['run']}, seed {src['seed']}, epoch {src['epoch']}"
    files = {"policy.h": c_header(p, note, meta.get("vehicles"), meta.get("c_api")).encode(),
             "policy.json": json.dumps(meta, indent=2).encode()}  # fmt: skip
    if onnx:
        files = {"policy.onnx": onnx_model(p).SerializeToString(), **files}
    os.makedirs(out, exist_ok=True)
    for name, data in files.items():
        with open(os.path.join(out, name), "wb") as fh:
            fh.write(data)
    return list(files)
