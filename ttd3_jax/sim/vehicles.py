"""Named vehicles: :class:`~ttd3_jax.sim.dynamics.QuadParams` presets.

``paper``: the default ``QuadParams()`` (1.5 kg, 0-20 N, ±6 rad/s; the paper's vehicle as we
read it).  ``crazyflie``: a Crazyflie 2.x class vehicle (27 g) from public sources; every
number and where it comes from is in :data:`CRAZYFLIE_SOURCES` and docs/paper-notes.md.
Both keep the paper's ``instant`` rate model, so the env's observation, the presets and the
controllers apply unchanged; the torque-model fields are the vehicle's own, for
``--task.vehicle.quad.rate-model first_order|torque``.
"""

from __future__ import annotations

import math

from ttd3_jax.sim.dynamics import QuadParams

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

VEHICLES: dict[str, QuadParams] = {"paper": QuadParams.create(), "crazyflie": CRAZYFLIE}
VEHICLE_NAMES: tuple[str, ...] = tuple(VEHICLES)


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
