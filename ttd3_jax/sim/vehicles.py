"""Named vehicles: :class:`~ttd3_jax.sim.dynamics.QuadParams` presets.

``paper``: the default ``QuadParams()`` (1.5 kg, 0-20 N, ±6 rad/s; the paper's vehicle as we
read it).  ``crazyflie``: a Crazyflie 2.x class vehicle (27 g) from public sources; every
number and where it comes from is in :data:`CRAZYFLIE_SOURCES` and docs/paper-notes.md.
Both keep the paper's ``instant`` rate model, so the env's observation, the presets and the
controllers apply unchanged; the torque-model fields are the vehicle's own, for
``--task.vehicle.quad.rate-model first_order|torque``.  ``cf2``: a Crazyflie 2.x as crazyflow
identifies it (32.8 g, thrust-to-weight 1.49), flown through its firmware's rate PID, mixer and
motors (rate model ``firmware``, :mod:`ttd3_jax.sim.inner_loop`); sources in :data:`CF2_SOURCES`.
"""

from __future__ import annotations

import math

from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.sim.inner_loop import InnerLoop

_L2F = "rl-tools/rl-tools include/rl_tools/rl/environments/l2f/parameters/dynamics/crazyflie.h"
_L2F_COMMIT = "e8cad8334285ec0fd2e581aac59833771f02f6f9"
_CF_FW = "bitcraze/crazyflie-firmware src/modules/src/crtp_commander_generic.c"

_CF_MASS = 0.027  # kg, l2f "mass vehicle"
_CF_THRUST_CURVE = (0.0213, -0.0112, 0.1201)  # N per motor, f(u) = c0 + c1 u + c2 u^2, u in [0, 1]
_CF_MOTOR_MAX = sum(_CF_THRUST_CURVE)  # N per motor at full throttle (u = 1): 0.1302
_CF_ARM_XY = 0.028  # m, |x| = |y| of every rotor position
_CF_TORQUE_CONSTANT = 4.665e-3  # m, yaw torque per newton of rotor thrust
_CF_RATE_DEG = 720.0  # deg/s, firmware roll/pitch rate at full stick (yaw: 400)

CRAZYFLIE = QuadParams.create(
    mass=_CF_MASS,
    thrust_min=0.0,
    thrust_max=4 * _CF_MOTOR_MAX,  # 0.5208 N, thrust-to-weight 1.97
    rate_min=-math.radians(_CF_RATE_DEG),  # ±12.57 rad/s on every axis (one range in QuadParams)
    rate_max=math.radians(_CF_RATE_DEG),
    tau_rate=0.072,  # s, l2f "T, RPM time constant": the fastest a body rate can follow
    inertia=(1.029e-5, 1.105e-5, 2.005e-5),  # kg m^2, l2f "J" diagonal
    k_rate=QuadParams().k_rate,  # 1/s: no public value in these units; the paper vehicle's
    # roll/pitch: two rotors at full thrust on one side, 2 * 0.028 m * 0.1302 N; yaw: two
    # rotors of one spin direction at full thrust, 2 * 4.665e-3 m * 0.1302 N
    torque_max=(2 * _CF_ARM_XY * _CF_MOTOR_MAX,) * 2 + (2 * _CF_TORQUE_CONSTANT * _CF_MOTOR_MAX,),
)

# QuadParams field -> (value, where it comes from)
CRAZYFLIE_SOURCES: dict[str, tuple[object, str]] = {
    "mass": (CRAZYFLIE.mass, f"{_L2F} @ {_L2F_COMMIT[:8]}: mass vehicle 0.027 kg"),
    "thrust_max": (CRAZYFLIE.thrust_max, f"{_L2F}: 4 x thrust curve at u = 1, 0.0213 - 0.0112 + 0.1201 N"),
    "thrust_min": (0.0, "chosen: motors off (the curve's 0.0213 N at u = 0 is a fit intercept)"),
    "rate_min/rate_max": (CRAZYFLIE.rate_max, f"{_CF_FW}: s_CppmEmuRoll/PitchMaxRateDps = 720 deg/s"),
    "tau_rate": (CRAZYFLIE.tau_rate, f"{_L2F}: T, RPM time constant 0.072 s"),
    "inertia": (CRAZYFLIE.inertia, f"{_L2F}: J = diag(1.029e-5, 1.105e-5, 2.005e-5) kg m^2"),
    "torque_max": (CRAZYFLIE.torque_max, f"{_L2F}: rotor positions ±0.028 m, torque constant 4.665e-3 m"),
    "k_rate": (CRAZYFLIE.k_rate, "chosen: the paper vehicle's rate-loop gains (no public value)"),
}

_DM = (
    "utiasDSL/drone-models @ 77f04ab1 drone_models/data/params.toml [cf2x_L250] (crazyflow 0.4.0's cf2x_L250)"
)
_FW = "bitcraze/crazyflie-firmware @ 2a18fc29 src/platform/interface/platform_defaults_cf2.h"
_CF2_RATE = 2 * math.pi  # rad/s, the action map's body-rate range (chosen; the firmware allows 720 deg/s)

# A Crazyflie 2.x (legacy propellers) as crazyflow identifies it, flown through its firmware's
# rate PID, mixer and motors (rate model "firmware", sim.inner_loop; InnerLoop's defaults)
CF2 = QuadParams.create(
    mass=0.0328,
    thrust_min=0.0,
    thrust_max=4 * InnerLoop().motor_max,  # 0.48 N, thrust-to-weight 1.49
    rate_min=-_CF2_RATE,
    rate_max=_CF2_RATE,
    inertia=(16.8e-6, 16.8e-6, 29.8e-6),
    torque_max=InnerLoop().torque_limit,  # (the torque model's field; firmware: the PID's output bound)
    rate_model="firmware",
    loop=InnerLoop(),
)

CF2_SOURCES: dict[str, tuple[object, str]] = {
    "mass": (
        CF2.mass,
        f"{_DM} [first_principles]: mass = 0.0328 kg (crazyflow's plant; the firmware assumes 0.029)",
    ),
    "inertia": (CF2.inertia, f"{_DM}: J = diag(16.8e-6, 16.8e-6, 29.8e-6) kg m^2 (marked TODO upstream)"),
    "thrust_max": (CF2.thrust_max, f"{_FW}: THRUST_MAX 0.12 N per motor, x 4"),
    "rate_min/rate_max": (CF2.rate_max, "chosen: ±2π rad/s (the firmware's rate mode allows ±720 deg/s)"),
    "loop.kp/ki/kd/i_limit/torque_limit": (
        InnerLoop().kp,
        f"{_FW}: PID_ROLL/PITCH/YAW_RATE_KP/KI/KD/"
        "INTEGRATION_LIMIT, int16 output clamp; to SI: docs/crazyflie-parameters.md",
    ),
    "loop.arm": (InnerLoop().arm, f"{_DM}: L = 0.03253 m (firmware ARM_LENGTH 0.046 m x √½)"),
    "loop.yaw_coeff": (
        InnerLoop().yaw_coeff,
        f"{_FW}: THRUST2TORQUE 0.0073509 m (legacy props; DM thrust2torque)",
    ),
    "loop.motor_min/motor_max": (
        (InnerLoop().motor_min, InnerLoop().motor_max),
        f"{_FW}: THRUST_MIN, THRUST_MAX",
    ),
    "loop.curve": (
        InnerLoop().curve,
        f"{_DM}: rpm2thrust = [0, -5.382e-7, 2.458e-10] rescaled to F(1) = 0.12 N",
    ),
    "loop.tau_up/tau_down": (
        (InnerLoop().tau_up, InnerLoop().tau_down),
        f"{_DM}: rotor_dyn_coef = [7.3556, 0, 0, "
        "2.4444e-4]: 1/7.3556 s up; down 2.4444e-4 (cmd² − rpm²), linearised at hover",
    ),
    "loop.drag": (
        InnerLoop().drag,
        f"{_DM} [so_rpy_rotor_drag]: drag_matrix diag -0.01495 (x, y), -0.01390 (z) "
        "N/(m/s); the x, y value on every axis",
    ),
}

VEHICLES: dict[str, QuadParams] = {"paper": QuadParams.create(), "crazyflie": CRAZYFLIE, "cf2": CF2}
VEHICLE_NAMES: tuple[str, ...] = tuple(VEHICLES)
# the vehicles randomization.vehicles may blend: those without an inner loop (sim.vehicle_mix
# interpolates every parameter; a firmware loop has no counterpart to blend with)
MIXABLE_NAMES: tuple[str, ...] = tuple(n for n, q in VEHICLES.items() if q.rate_model != "firmware")


def vehicle(name: str) -> QuadParams:
    """The preset ``name`` (one of :data:`VEHICLE_NAMES`)."""
    if name not in VEHICLES:
        raise ValueError(f"unknown vehicle {name!r}; allowed: {VEHICLE_NAMES}")
    return VEHICLES[name]


def vehicle_of(quad: QuadParams) -> str | None:
    """The name of the preset equal to ``quad``, or ``None`` (a changed or custom vehicle)."""
    return next((name for name, q in VEHICLES.items() if q == quad), None)


def thrust_to_weight(quad: QuadParams) -> float:
    """Maximum collective thrust over the weight (dimensionless)."""
    return quad.thrust_max / quad.hover_thrust


def with_vehicle(cfg, name: str):
    """The ``EnvConfig`` ``cfg`` flying vehicle ``name`` (this module imports no config: the
    config imports it).  Refuses a ``cfg`` with ``thrust_map_mass`` set (a mass pinned for
    another vehicle's action map)."""
    quad = vehicle(name)
    if cfg.vehicle.thrust_map_mass is not None:
        raise ValueError(
            f"with_vehicle({name!r}): cfg.vehicle.thrust_map_mass={cfg.vehicle.thrust_map_mass} pins another "
            "vehicle's action map; allowed: thrust_map_mass None"
        )
    return cfg.replace(quad=quad)
