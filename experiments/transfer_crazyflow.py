"""Fly an exported policy in crazyflow's Crazyflie model, through a firmware-structured rate loop.

The plant is crazyflow's ``first_principles`` dynamics of drone ``cf2x_L250`` (crazyflow 0.4.0,
in its own venv: ``pip install -e '.[transfer]'``; it excludes jax 0.10.2): rigid body, drag,
propeller gyroscopic torque, and the motor speed as a state with crazyflow's identified spin-up
and spin-down dynamics, integrated with RK4 at 1 ms.  Every 1 ms step:

1. every ``action_repeat`` steps the policy (``policy.onnx``) reads an observation built in NumPy
   from ``policy.json`` alone (``experiments/fly_exported.py``: every part, memory, preview and
   reference integral included) and outputs a ∈ [-1, 1]^4, which ``action_map`` turns into
   collective thrust and body-rate setpoints (rad/s).  The policy's vehicle is not a Crazyflie
   (the ``paper`` one weighs 1.5 kg), so its thrust is passed on as a collective acceleration:
   T_cf = T · m_cf / m_policy (``thrust_scale`` in the JSON; T itself under ``thrust_units``
   acceleration);
2. a rate PID per body axis with the Crazyflie firmware's structure (``pid.c``): e = setpoint −
   gyro; P; I on the error's integral clamped to ±i_limit before use; D on the measurement
   (−Δgyro/dt, unfiltered); the output, a torque (N·m), clamped where the firmware's int16
   saturates.  Gains in SI from docs/crazyflie-parameters.md (sections 1 and 3), run at 1 kHz
   on the true body rates (the firmware: 500 Hz, on an 80 Hz low-passed gyro).  The firmware
   routes the yaw-rate setpoint through a yaw *angle* loop; this harness, like ttd3_jax's
   simulator, gives the yaw rate to a yaw-rate PID directly.  Frames are FLU throughout, so the
   firmware's legacy pitch sign flips (gyro and setpoint) cancel out;
3. a mixer from (collective thrust, torque) to per-rotor thrust with crazyflow's own cf2x_L250
   geometry (arm L, mixing matrix, yaw torque per newton from its rpm2torque / rpm2thrust at
   hover), each rotor clipped to [thrust_min, thrust_max], then crazyflow's rpm2thrust curve
   inverted to an RPM command, sent with ``Control.rotor_vel``.

``--ideal-rates`` bypasses 2 and 3 and the motors: each step crazyflow's body rates are set
to the command and the four rotors spin at the speed of the commanded thrust (not clipped),
the interface check: an ``instant``-rate policy should fly as in its own simulator.

The protocol is ``policy.json``'s: 3000 physics steps of 1 ms from rest, level, on the
track's first point (the rotors at hover speed: crazyflow's 0 RPM would drop the vehicle while
they spin up); Σ‖e‖ over k = 1 … 3000; crashed once ‖e‖ > 1 m.  A crashed flight **stops
there** and its remaining steps count at the crash distance (Σ‖e‖ then is the error flown plus
that distance for every step left); ``crash_time_s`` is the crash step's time; RMSE is over
the control steps (the protocol's).  crazyflow's floor clip is removed (the tracks start at
z = 0 and ttd3_jax has no ground plane).

Baselines per track: ``own_sim_tracking_error``, the same ONNX policy in ttd3_jax's own
``TrackingEnv`` on the same track (its ``env_config`` from policy.json, evaluation protocol,
whatever rate model it names; never stopped at a crash), and ``mellinger_tracking_error``,
crazyflow's own Mellinger state controller (``Control.state``: 100 Hz position, 500 Hz
attitude), fed p_d and its velocity and acceleration by central differences (±10 ms) of the
1 ms track, by the same protocol.

Tracks: Spiral-RT and LOS-RT seeds 0-4 (``experiments/tracks/protocol``), the generalisation
suite's (``ttd3_jax.control.generalization``, built in-process at 1 ms) and ``circle_r0.5``, a
horizontal circle of radius 0.5 m at 1 m/s from its first point.

    python experiments/transfer_crazyflow.py POLICY_DIR                        # every track
    python experiments/transfer_crazyflow.py POLICY_DIR --tracks spiral_rt --json out.json
    python experiments/transfer_crazyflow.py POLICY_DIR --ideal-rates          # interface check
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import sys
import time

try:  # before anything imports scipy (ttd3_jax's env does): crazyflow sets SCIPY_ARRAY_API for it
    import crazyflow
except ImportError:
    crazyflow = None
import jax
import jax.numpy as jnp
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
if HERE not in sys.path:  # (loaded from a file by the tests)
    sys.path.insert(0, HERE)
import fly_exported as fx  # noqa: E402

PROTOCOL_TRACKS = os.path.join(HERE, "tracks", "protocol")
CSV_TRACKS = ("spiral_rt",) + tuple(f"los_rt_seed{s:02d}" for s in range(5))
CIRCLE = "circle_r0.5"
CIRCLE_RADIUS_M, CIRCLE_SPEED = 0.5, 1.0  # m, m/s
TRACK_S = 5.1  # s of reference built for the in-process tracks (3 s flown, look-ahead and preview)
DRONE = "cf2x_L250"
PHYSICS_HZ = 1000
CRASH_M = 1.0
MELLINGER_HZ = (100, 500, 500)  # state, attitude, force-torque controller rates (the firmware's)
DIFF_STEPS = 10  # ±steps of the central differences that give the Mellinger p_d's v and a

# -- the firmware's rate PID in SI (docs/crazyflie-parameters.md, sections 1 and 3) ----------
_N_PER_UNIT = 0.12 / 65535  # N per rotor per PWM unit: THRUST_MAX / 65535, battery compensation on
_LEVER = 0.046 * math.sqrt(0.5)  # m: the x-mixer's per-axis lever arm, 0.707 ARM_LENGTH
_THRUST2TORQUE = 0.0069929  # m: yaw torque per newton of the 2.1+ props (the yaw gains' own)
_INT16 = 32767  # the PID output's saturation (saturateSignedInt16)
ROLL_NM_PER_UNIT = 4 * _N_PER_UNIT * 0.5 * _LEVER  # the legacy mixer halves roll and pitch
YAW_NM_PER_UNIT = 4 * _N_PER_UNIT * _THRUST2TORQUE


@dataclasses.dataclass(frozen=True)
class RateGains:
    """Rate PID gains per body axis (roll, pitch, yaw): ``kp`` N·m/(rad/s), ``ki`` N·m/rad,
    ``kd`` N·m/(rad/s²), ``i_limit`` rad (the clamp on ∫e dt), ``out_limit`` N·m."""

    kp: tuple[float, float, float]
    ki: tuple[float, float, float]
    kd: tuple[float, float, float]
    i_limit: tuple[float, float, float]
    out_limit: tuple[float, float, float]


FIRMWARE_GAINS = RateGains(
    kp=(1.706e-3, 1.706e-3, 3.522e-4),
    ki=(3.413e-3, 3.413e-3, 4.901e-5),
    kd=(1.706e-5, 1.706e-5, 0.0),
    i_limit=(0.5812, 0.5812, 2.909),
    out_limit=(_INT16 * ROLL_NM_PER_UNIT,) * 2 + (_INT16 * YAW_NM_PER_UNIT,),  # 3.90e-3, 1.68e-3
)


@dataclasses.dataclass(frozen=True)
class Geometry:
    """crazyflow's vehicle as the mixer sees it: ``mass`` kg, ``L`` m (per-axis lever arm),
    ``kappa`` m (yaw torque per newton of rotor thrust), ``mixing`` (3, 4) rows roll, pitch, yaw
    of each rotor's sign, rotor thrust limits (N), ``rpm2thrust`` [c0, c1, c2] (N, F = Σ c_i rpm^i)."""

    mass: float
    gravity: float
    L: float
    kappa: float
    mixing: tuple
    thrust_min: float
    thrust_max: float
    rpm2thrust: tuple


def rotor_rpm(rpm2thrust, force, xp=np):
    """RPM of rotors giving ``force`` (N each): crazyflow's rpm2thrust curve inverted (its upper
    root); ``xp`` the array module (jax.numpy inside the jitted step)."""
    c, b, a = rpm2thrust
    return (-b + xp.sqrt(b * b - 4 * a * (c - force))) / (2 * a)


def geometry(params: dict) -> Geometry:
    """The mixer's :class:`Geometry` from crazyflow's first_principles parameters of a drone;
    ``kappa`` is rpm2torque / rpm2thrust at the hover speed."""
    mass, g = float(params["mass"]), -float(np.asarray(params["gravity_vec"])[2])
    rpm = float(rotor_rpm(params["rpm2thrust"], mass * g / 4))
    poly = lambda c: float(c[0] + c[1] * rpm + c[2] * rpm * rpm)  # noqa: E731
    return Geometry(mass=mass, gravity=g, L=float(params["L"]),
                    kappa=poly(params["rpm2torque"]) / poly(params["rpm2thrust"]),
                    mixing=tuple(map(tuple, np.asarray(params["mixing_matrix"], float).tolist())),
                    thrust_min=float(params["thrust_min"]), thrust_max=float(params["thrust_max"]),
                    rpm2thrust=tuple(float(c) for c in params["rpm2thrust"]))  # fmt: skip


def rate_pid(gains: RateGains, state, setpoint, measured, dt: float):
    """One firmware PID step per axis: ``state`` = (∫e dt (3,) rad, previous gyro (3,) rad/s),
    ``setpoint`` and ``measured`` body rates (3,) rad/s, ``dt`` s.  Returns the torque (3,) N·m
    and the new state.  (jax.numpy: it runs inside the jitted step.)"""
    integ, prev = state
    f = measured.dtype
    err = setpoint - measured
    lim = jnp.asarray(gains.i_limit, f)
    integ = jnp.clip(integ + err * dt, -lim, lim)  # clamped before use
    deriv = -(measured - prev) / dt  # on the measurement, unfiltered
    out = jnp.asarray(gains.kp, f) * err + jnp.asarray(gains.ki, f) * integ + jnp.asarray(gains.kd, f) * deriv
    olim = jnp.asarray(gains.out_limit, f)
    return jnp.clip(out, -olim, olim), (integ, measured)


def mix(geo: Geometry, thrust, torque):
    """Per-rotor thrust (4,) N of collective ``thrust`` (N) and body ``torque`` (3,) N·m, each
    rotor clipped to [thrust_min, thrust_max] (crazyflow's force_torque2rotor_vel mixer)."""
    f = torque.dtype
    per = (thrust + (torque / jnp.asarray([geo.L, geo.L, geo.kappa], f)) @ jnp.asarray(geo.mixing, f)) / 4
    return jnp.clip(per, geo.thrust_min, geo.thrust_max)


# -- crazyflow ------------------------------------------------------------------------------


class Crazyflow:
    """One cf2x_L250 in crazyflow's ``first_principles`` dynamics at 1 kHz, RK4, rotor dynamics
    on, controlled by ``control`` (``"rotor_vel"`` or ``"state"``), without its floor clip.
    The jitted ``*_period`` functions run ``n`` physics steps and return (data, carry, positions
    (n, 3), the end state (13,) as ttd3_jax orders it: p, v, q (qw, qx, qy, qz), ω body)."""

    def __init__(self, control: str):
        from crazyflow.control import Control
        from crazyflow.drones import Drone
        from crazyflow.dynamics import Dynamics, load_params
        from crazyflow.sim import Sim
        from crazyflow.sim.integration import Integrator

        state_hz, att_hz, ft_hz = MELLINGER_HZ
        self.sim = Sim(drone=Drone(DRONE), dynamics=Dynamics.first_principles, control=Control(control),
                       integrator=Integrator.rk4, freq=PHYSICS_HZ, state_freq=state_hz, attitude_freq=att_hz,
                       force_torque_freq=ft_hz)  # fmt: skip
        self.params = load_params(Dynamics.first_principles, Drone(DRONE))
        self.geo = geometry(self.params)
        self.stages = {k: fn for k, fn in self.sim.step_pipeline.items() if k != "clip_floor_pos"}

    def start(self, p0: np.ndarray):
        """Sim data at rest, level, on ``p0`` (m), the rotors (state and command) at hover speed."""
        self.sim.reset()
        d = self.sim.data
        hover = jnp.full((1, 1, 4), rotor_rpm(self.geo.rpm2thrust, self.geo.mass * self.geo.gravity / 4),
                         d.states.rotor_vel.dtype)  # fmt: skip
        states = d.states.replace(pos=jnp.asarray(p0, d.states.pos.dtype).reshape(1, 1, 3), rotor_vel=hover)
        return d.replace(states=states, controls=d.controls.replace(rotor_vel=hover))

    @staticmethod
    def measured(data):
        """The state (13,) in ttd3_jax's order: p, v, q (qw, qx, qy, qz), ω (body, FLU)."""
        s = data.states
        q = s.quat[0, 0]
        return jnp.concatenate([s.pos[0, 0], s.vel[0, 0], q[3:], q[:3], s.ang_vel[0, 0]])

    def _run(self, body, n: int):
        def period(data, carry, u):
            (data, carry), pos = jax.lax.scan(lambda c, _: body(c, u), (data, carry), None, length=n)
            return data, carry, pos, self.measured(data)

        return jax.jit(period)

    def rate_loop_period(self, n: int, gains: RateGains = FIRMWARE_GAINS):
        """``(data, pid state, u) -> ...``: u = (thrust N, body-rate setpoints (3,) rad/s) held
        for n steps through :func:`rate_pid`, :func:`mix` and the RPM command."""
        geo, stages, dt = self.geo, tuple(self.stages.values()), 1.0 / PHYSICS_HZ

        def body(carry, u):
            data, pid = carry
            torque, pid = rate_pid(gains, pid, u[1:], data.states.ang_vel[0, 0], dt)
            rpm = rotor_rpm(geo.rpm2thrust, mix(geo, u[0], torque), jnp)
            data = data.replace(controls=data.controls.replace(rotor_vel=rpm.reshape(1, 1, 4)))
            for fn in stages:
                data = fn(data)
            return (data, pid), data.states.pos[0, 0]

        return self._run(body, n)

    def ideal_period(self, n: int):
        """``(data, (), u) -> ...``: each step the body rates set to u[1:] and the four rotors
        (state and command) at the speed of thrust u[0] / 4, no PID, mixer clip or motor lag."""
        geo, stages = self.geo, (self.stages["integration"], self.stages["increment_steps"])

        def body(carry, u):
            data, none = carry
            rpm = jnp.broadcast_to(rotor_rpm(geo.rpm2thrust, u[0] / 4, jnp), (1, 1, 4)).astype(
                data.states.rotor_vel.dtype
            )
            states = data.states.replace(ang_vel=u[1:].reshape(1, 1, 3), rotor_vel=rpm)
            data = data.replace(states=states, controls=data.controls.replace(rotor_vel=rpm))
            for fn in stages:
                data = fn(data)
            return (data, none), data.states.pos[0, 0]

        return self._run(body, n)

    def state_period(self, n: int):
        """``(data, (), cmd) -> ...``: crazyflow's Mellinger state controller given ``cmd`` (16,)
        = [p, v, a, q (xyzw), ω] for n steps (its own controller rates)."""
        import crazyflow.sim.functional as F

        stages = tuple(self.stages.values())

        def body(carry, cmd):
            data, none = carry
            for fn in stages:
                data = fn(data)
            return (data, none), data.states.pos[0, 0]

        run = self._run(body, n)
        return lambda data, carry, cmd: run(F.state_control(data, cmd.reshape(1, 1, 16)), carry, cmd)


# -- the tracks -----------------------------------------------------------------------------


def track_names() -> tuple[str, ...]:
    """Every track this harness flies, in table order."""
    from ttd3_jax.control import generalization as gen

    return (*CSV_TRACKS, *gen.DESCRIPTIONS, CIRCLE)


def circle(t: np.ndarray) -> np.ndarray:
    """The horizontal circle (m) at times ``t`` (s): radius 0.5 m, 1 m/s, from the origin along +x."""
    w = CIRCLE_SPEED / CIRCLE_RADIUS_M
    return np.stack([CIRCLE_RADIUS_M * np.sin(w * t), CIRCLE_RADIUS_M * (1 - np.cos(w * t)), 0 * t], -1)


def reference(name: str, dt: float = 1.0 / PHYSICS_HZ) -> np.ndarray:
    """p_d (rows, 3) m of track ``name`` at every physics step, float32 (as the env reads it)."""
    if name in CSV_TRACKS:
        return np.loadtxt(os.path.join(PROTOCOL_TRACKS, f"{name}.csv"), delimiter=",", skiprows=1,
                          dtype=np.float64)[:, 1:4].astype(np.float32)  # fmt: skip
    from ttd3_jax.sim import custom_tracks as ct
    from ttd3_jax.sim import trajectories as tr

    if name == CIRCLE:
        track = ct.from_function(circle, TRACK_S, dt=dt, name=CIRCLE).track()
    else:
        track = _suite(dt)[name]
    k = jnp.arange(round(TRACK_S / dt) + 1)
    return np.asarray(jax.vmap(lambda i: tr.position(track, i, dt))(k), np.float32)


@functools.cache
def _suite(dt: float) -> dict:
    from ttd3_jax.control import generalization as gen

    return gen.suite_tracks("generalization", dt)


def derivatives(ref: np.ndarray, k: int, h: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """v (m/s), a (m/s²) of the reference at step k by central differences over ±h steps, on
    samples 1 … end (sample 0 is the start point: LOS-RT's lies off its first leg)."""
    c = min(max(k, 1 + h), len(ref) - 1 - h)
    lo, mid, hi = (ref[i].astype(np.float64) for i in (c - h, c, c + h))
    return (hi - lo) / (2 * h * dt), (hi - 2 * mid + lo) / (h * dt) ** 2


# -- flights --------------------------------------------------------------------------------


def figures(errors: np.ndarray, crash: int | None, rep: int, dt: float) -> dict:
    """The protocol's figures of ‖e‖ at steps 1 … N (``errors[j]``: step j + 1), a crash at
    ``errors[crash]`` counting that distance for every step after it."""
    e = errors.astype(np.float64)
    if crash is not None:
        e[crash + 1 :] = e[crash]
    sampled = e[rep - 1 :: rep]  # the control steps
    return {"tracking_error": float(np.sum(e)), "crashed": crash is not None,
            "crash_time_s": None if crash is None else round((crash + 1) * dt, 9),
            "rmse": float(np.sqrt(np.mean(sampled**2))), "max_error": float(np.max(e))}  # fmt: skip


def fly(period, start, ref: np.ndarray, act, n: int, rep: int, dt: float, carry=()) -> dict:
    """One flight of ``n`` physics steps on ``ref``: every ``rep`` steps ``act(x, k)`` (x the
    measured state (13,), k the step) gives the input ``period`` holds for ``rep`` steps;
    stops at the first step with ‖e‖ > 1 m (or a non-finite state)."""
    data, errors, crash = start, np.zeros(n), None
    x = np.asarray(Crazyflow.measured(start), np.float32)
    for k in range(0, n, rep):
        u = act(x, k)
        data, carry, pos, x = period(data, carry, u)
        x = np.asarray(x, np.float32)
        e = np.linalg.norm(np.asarray(pos, np.float64) - ref[k + 1 : k + rep + 1], axis=-1)
        errors[k : k + rep] = e
        bad = np.flatnonzero(~(e <= CRASH_M))  # (NaN: crashed)
        if bad.size:
            crash = k + int(bad[0])
            if not np.isfinite(errors[crash]):
                errors[crash:] = np.inf
            break
    return figures(errors, crash, rep, dt)


def policy_actor(meta: dict, session, ref: np.ndarray, thrust_scale: float):
    """``act(x, k)`` of the ONNX policy: the observation (fly_exported's), the action, the
    action map, the thrust scaled onto crazyflow's vehicle; keeps the observation's memory.
    ``act.last["a"]``: the action it chose last."""
    memory, last = fx.Memory(meta), {}

    def act(x, k):
        if k > 0:  # the control step that ended at k
            memory.update(last["a"], x[0:3], ref[k])
        obs = fx.observe(meta, x, ref, k, memory)[None].astype(np.float32)
        a = np.clip(session.run(["action"], {"obs": obs})[0][0], -1.0, 1.0)
        last["a"] = a
        thrust, w = fx.action_to_control(meta, a)
        return np.asarray([thrust * thrust_scale, *w], np.float32)

    act.last = last
    return act


def mellinger_actor(ref: np.ndarray, dt: float):
    """``act(x, k)`` of the Mellinger baseline: the state command [p_d, v_d, a_d, q (0, 0, 0, 1), 0]."""

    def act(x, k):
        v, a = derivatives(ref, k, DIFF_STEPS, dt)
        return np.concatenate([ref[k], v, a, [0, 0, 0, 1], [0, 0, 0]]).astype(np.float32)

    return act


def thrust_scale(meta: dict, geo: Geometry) -> float:
    """Crazyflow thrust per unit of the policy's thrust: m_cf / m_policy (N per N), or m_cf
    when the policy's thrust is an acceleration (``thrust_units``)."""
    veh = meta["vehicle"]
    newton = veh.get("thrust_units", "newton") == "newton"
    return geo.mass / veh["mass"] if newton else geo.mass


def own_sim(meta: dict, session, refs: dict[str, np.ndarray]) -> dict[str, dict] | str:
    """The policy in ttd3_jax's ``TrackingEnv`` (policy.json's ``env_config``, the evaluation
    protocol, its own rate model) on each reference, through a ``pure_callback`` to the ONNX
    model: ``{name: {tracking_error, crashed, crash_time_s, rmse}}``, or why not (a string)."""
    from ttd3_jax.control import closed_loop as cl
    from ttd3_jax.interop import policy as pe
    from ttd3_jax.sim import custom_tracks as ct
    from ttd3_jax.sim.env import TrackingEnv

    try:
        cfg = pe.env_config(meta)
    except ValueError as e:
        return str(e)
    env = TrackingEnv(cfg.for_eval("los_rt"))
    size = meta["obs_size"]

    def host(o):
        return session.run(["action"], {"obs": np.asarray(o, np.float32)[None, :size]})[0][0]

    policy = lambda obs: jax.pure_callback(host, jax.ShapeDtypeStruct((4,), jnp.float32), obs)  # noqa: E731
    controller = cl.policy_controller(policy)

    @jax.jit
    def episode(track):
        r = cl.closed_loop(env, controller, env.reset_with_track(jax.random.PRNGKey(0), track))
        return cl.metrics(env, r), r.crashed

    rows = max(len(r) for r in refs.values()) + 1  # one table size: one compiled episode
    out = {}
    for name, ref in refs.items():
        t = np.arange(len(ref)) * cfg.dt
        track = ct.from_samples(t, ref.astype(np.float64), dt=cfg.dt, name=name).track(rows)
        m, crashed = jax.device_get(episode(track))
        first = np.flatnonzero(crashed > 0)
        out[name] = {"tracking_error": float(m["tracking_error"]), "crashed": bool(m["crashed"] > 0),
                     "crash_time_s": round(float((first[0] + 1) * cfg.control_dt), 9) if first.size else None,
                     "rmse": float(m["rmse"])}  # fmt: skip
    return out


# -- the command line ------------------------------------------------------------------------


def settings(cf: Crazyflow, meta: dict, ideal: bool) -> dict:
    """The harness settings the JSON records beside the figures."""
    from importlib import metadata

    g = cf.geo
    pid = dict(
        **dataclasses.asdict(FIRMWARE_GAINS),
        rate_hz=PHYSICS_HZ,
        axes="roll, pitch, yaw (FLU)",
        d_term="on the measurement, unfiltered",
        gyro="crazyflow's body rates, unfiltered",
        yaw="rate PID on the yaw-rate setpoint (the firmware: through a yaw angle loop)",
        source="docs/crazyflie-parameters.md",
    )
    mixer = dict(
        L_m=g.L,
        yaw_torque_per_newton_m=g.kappa,
        mixing_matrix=[list(r) for r in g.mixing],
        rotor_thrust_min_N=g.thrust_min,
        rotor_thrust_max_N=g.thrust_max,
        rpm2thrust=list(g.rpm2thrust),
        command="crazyflow Control.rotor_vel (RPM)",
    )
    mellinger = dict(
        control="crazyflow Control.state",
        rates_hz=dict(zip(("state", "attitude", "force_torque"), MELLINGER_HZ, strict=True)),
        reference=f"p_d, and v, a by central differences over ±{DIFF_STEPS} ms of the 1 ms track",
    )
    return dict(
        crazyflow_version=metadata.version("crazyflow"),
        drone=DRONE,
        dynamics="first_principles",
        integrator="rk4",
        physics_dt_s=1.0 / PHYSICS_HZ,
        rotor_dynamics="on (crazyflow's rotor_dyn_coef)",
        interface="ideal_rates" if ideal else "rate_loop",
        rate_pid=pid,
        mixer=mixer,
        vehicle_mass_kg=g.mass,
        thrust_scale=thrust_scale(meta, g),
        thrust_map="T_cf = thrust_scale x the policy's thrust (its collective acceleration x m_cf)",
        start="at rest on p_d(0), level, rotors at hover speed",
        floor="crazyflow's floor clip removed",
        crash=f"||e|| > {CRASH_M} m: the flight stops, the remaining steps count at the crash distance",
        rmse="over the control steps k = action_repeat, 2 action_repeat, ..., 3000",
        own_sim="ttd3_jax TrackingEnv, policy.json's env_config under the evaluation protocol, not stopped "
        "at a crash (crash_time_s at control-step resolution)",
        mellinger=mellinger,
        policy=dict(
            source=meta.get("source"), control_hz=meta["control_hz"], rate_model=meta["rate_model"]["name"]
        ),
    )


def check_input(policy_dir: str, tracks: list[str], allowed: tuple[str, ...]) -> str | None:
    """One line naming what is wrong with the command's input (None: nothing)."""
    for name in ("policy.json", "policy.onnx"):
        if not os.path.isfile(os.path.join(policy_dir, name)):
            return (
                f"{policy_dir}: no {name} (a policy directory holds policy.json and policy.onnx, written "
                "by python -m ttd3_jax.export RUN --out DIR)"
            )
    unknown = [t for t in tracks if t not in allowed]
    if unknown:
        return f"unknown track {unknown[0]!r}; allowed: {', '.join(allowed)}"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/transfer_crazyflow.py",
                                 description=__doc__.split("\n\n")[0])  # fmt: skip
    ap.add_argument("policy_dir", help="a directory written by python -m ttd3_jax.export")
    ap.add_argument("--tracks", nargs="+", default=None, help="track names (default: every track)")
    ap.add_argument("--json", default=None, help="write the figures and the harness settings here")
    ap.add_argument(
        "--ideal-rates",
        action="store_true",
        help="body rates set to the command each step, thrust as commanded (no PID, mixer, motors)",
    )
    a = ap.parse_args(argv)
    if crazyflow is None:
        print("error: crazyflow is not installed: pip install -e '.[transfer]' in a venv of its own "
              "(crazyflow 0.4.0 excludes jax 0.10.2)", file=sys.stderr)  # fmt: skip
        return 2
    allowed = track_names()
    tracks = a.tracks or list(allowed)
    why = check_input(a.policy_dir, tracks, allowed)
    if why is None:
        meta = json.load(open(os.path.join(a.policy_dir, "policy.json")))
        why = fx.check_observation(meta)
        why = why and f"{a.policy_dir}: {why}"
    if why:
        print(f"error: {why}", file=sys.stderr)
        return 2
    import onnxruntime as ort

    session = ort.InferenceSession(
        os.path.join(a.policy_dir, "policy.onnx"), providers=["CPUExecutionProvider"]
    )
    proto = meta["evaluation_protocol"]
    n, rep, dt = proto["physics_steps"], meta["action_repeat"], proto["physics_dt_s"]
    if abs(dt - 1.0 / PHYSICS_HZ) > 1e-12:
        why = f"policy.json's physics_dt_s is {dt}; allowed: {1.0 / PHYSICS_HZ} (this harness's 1 kHz)"
        print(f"error: {why}", file=sys.stderr)
        return 2
    refs = {name: reference(name, dt) for name in tracks}
    cf, mel = Crazyflow("rotor_vel"), Crazyflow("state")
    period = cf.ideal_period(rep) if a.ideal_rates else cf.rate_loop_period(rep)
    carry = () if a.ideal_rates else tuple(np.zeros(3, np.float32) for _ in range(2))
    mel_rep = PHYSICS_HZ // MELLINGER_HZ[0]
    mel_period = mel.state_period(mel_rep)
    scale = thrust_scale(meta, cf.geo)
    print(f"crazyflow {DRONE}, {'ideal rates' if a.ideal_rates else 'firmware rate PID + mixer + motors'}; "
          f"own simulator: ttd3_jax ({meta['rate_model']['name']} rates)", flush=True)  # fmt: skip
    t0 = time.perf_counter()
    own = own_sim(meta, session, refs)
    if isinstance(own, str):
        print(f"own-sim baseline skipped: {own}", flush=True)
    else:
        print(f"own-sim baseline: {len(own)} tracks in {time.perf_counter() - t0:.1f} s", flush=True)
    results = {}
    for name, ref in refs.items():
        t0 = time.perf_counter()
        r = fly(period, cf.start(ref[0]), ref, policy_actor(meta, session, ref, scale), n, rep, dt, carry)
        m = fly(mel_period, mel.start(ref[0]), ref, mellinger_actor(ref, dt), n, mel_rep, dt)
        o = own.get(name, {}) if isinstance(own, dict) else {}
        results[name] = {
            **r,
            "own_sim_tracking_error": o.get("tracking_error"),
            "own_sim_crashed": o.get("crashed"),
            "own_sim_crash_time_s": o.get("crash_time_s"),
            "mellinger_tracking_error": m["tracking_error"],
            "mellinger_crashed": m["crashed"],
            "mellinger_crash_time_s": m["crash_time_s"],
            "mellinger_rmse": m["rmse"],
        }
        print(f"  {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    print(table(results))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"settings": settings(cf, meta, a.ideal_rates), "tracks": results}, fh, indent=2)
        print(f"wrote {a.json}")
    return 0


def table(results: dict) -> str:
    """The per-track table: Σ‖e‖ on crazyflow, crash (time), own-sim Σ‖e‖, Mellinger Σ‖e‖, ratio."""
    cells = (("track", 14), ("Σ‖e‖ cf (m)", 12), ("crashed", 9), ("RMSE (m)", 9), ("own-sim", 10),
             ("Mellinger", 10), ("ratio", 7))  # fmt: skip
    head = " ".join(f"{name:>{width}}" for name, width in cells)
    lines = [head]
    for name, r in results.items():
        crash = f"{r['crash_time_s']:.3f} s" if r["crashed"] else "no"
        own = r["own_sim_tracking_error"]
        mel_s = f"{r['mellinger_tracking_error']:.2f}" + ("*" if r["mellinger_crashed"] else "")
        ratio = f"{r['tracking_error'] / own:7.2f}" if own else f"{'-':>7}"
        lines.append(f"{name:>14} {r['tracking_error']:12.3f} {crash:>9} {r['rmse']:9.4f} "
                     f"{f'{own:10.3f}' if own is not None else '-':>10} {mel_s:>10} {ratio}")  # fmt: skip
    lines.append(
        "ratio: Σ‖e‖ on crazyflow / own-sim; a crashed flight counts its crash distance for every step left; "
        "* Mellinger crashed"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
