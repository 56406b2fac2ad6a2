"""Domain randomisation: what an episode draws about the plant it flies.

A :class:`Plant` is the vehicle flown and the errors around it that the controller does not
see: the thrust-map error, the actuation latency, the observation's noise level and position
bias, and a constant wind.  :func:`draw` draws one per episode from the ranges of
:class:`~ttd3_jax.sim.config.RandomizationConfig` (the env's reset does it).  The action map
always stays that of the config's (nominal) vehicle, so that a mass or thrust error is not
compensated by the map.  With ``randomization.vehicles`` the nominal vehicle is drawn too
(``sim.vehicle_mix``), known: a :class:`VehiclePlant` carries it, for the action map and the
observation's descriptor.

Units: masses, inertias, thrust and rate limits as factors on the given vehicle; latency in
physics steps of ``dt`` (drawn from seconds, so a 10 ms-control policy and a 1 ms NMPC get the
same delay); position bias in m; wind in m/s².
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct

from ttd3_jax.sim import inner_loop as il
from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import EnvConfig, plant_is_nominal
from ttd3_jax.sim.dynamics import QuadParams

PLANT_TAG = 0x0D12  # folded into a reset's key, so that drawing the plant changes no other draw
FIRMWARE_TAG = 0x0F1E  # folded into it for the firmware model's draws (the other draws keep their keys)


@struct.dataclass
class Plant:
    """One episode's plant (a pytree of arrays; vmap it over envs)."""

    quad: QuadParams  # the vehicle flown (leaves: arrays of the state's float type)
    thrust_gain: jax.Array  # thrust produced / thrust commanded by the (nominal) action map
    latency: jax.Array  # int32, physics steps between a command and its application
    noise_scale: jax.Array  # factor on the disturbances' obs_noise_* stds
    pos_bias: jax.Array  # (3,) m, added to the observed position
    wind_mean: jax.Array  # (3,) m/s², added to the OU wind acceleration


@struct.dataclass
class VehiclePlant(Plant):
    """The plant of a config with ``randomization.vehicles`` (a subclass, so that the others keep
    their layout): also the episode's nominal vehicle, known to the controller."""

    nominal: QuadParams  # the drawn vehicle before the unknown errors (arrays, as ``quad``)


def active(cfg: EnvConfig) -> bool:
    """Static: whether any plant range of ``cfg`` differs from its neutral value, or the
    nominal vehicle is drawn (``vehicles``)."""
    return not plant_is_nominal(cfg.randomization) or bool(cfg.randomization.vehicles)


def nominal_vehicle(plant: Plant) -> QuadParams | None:
    """The episode's known vehicle when it is drawn (:class:`VehiclePlant`), else ``None`` (the
    config's: ``sim.env``'s default)."""
    return plant.nominal if isinstance(plant, VehiclePlant) else None


def fixed_pos_bias(cfg: EnvConfig) -> bool:
    """Static: whether ``randomization.pos_bias`` is a fixed (x, y, z) bias, not a ± range."""
    return isinstance(cfg.randomization.pos_bias, tuple)


def has_pos_bias(cfg: EnvConfig) -> bool:
    """Static: whether the observed position carries a bias."""
    b = cfg.randomization.pos_bias
    return any(x != 0 for x in b) if fixed_pos_bias(cfg) else b > 0


def delay_steps(cfg: EnvConfig) -> int:
    """``action_delay`` in physics steps (the randomised env counts it as latency)."""
    return cfg.disturbances.action_delay * cfg.action_repeat


def latency_steps(cfg: EnvConfig) -> tuple[int, int]:
    """The latency range in physics steps: round(seconds / dt), plus ``action_delay`` control
    steps (which the randomised env counts as latency)."""
    extra = delay_steps(cfg)
    lo, hi = cfg.randomization.latency
    return round(lo / cfg.dt) + extra, round(hi / cfg.dt) + extra


def max_latency_steps(cfg: EnvConfig) -> int:
    """The largest latency an episode of ``cfg`` may draw, in physics steps."""
    return latency_steps(cfg)[1]


def pending_size(cfg: EnvConfig) -> int:
    """Past control steps' actions the randomised env keeps: ceil(max latency / action_repeat)."""
    return math.ceil(max_latency_steps(cfg) / cfg.action_repeat)


def flown_rate_model(cfg: EnvConfig) -> str:
    """The flown vehicle's rate model: the config's, except that an ``instant`` vehicle flies
    ``first_order`` when ``tau_rate`` is randomised (the observation keeps its layout)."""
    q = cfg.vehicle.quad
    if q.rate_model == "instant" and tuple(cfg.randomization.tau_rate) != (1.0, 1.0):
        return "first_order"
    return q.rate_model


def vehicle_arrays(quad: QuadParams, dtype=None) -> QuadParams:
    """``quad`` with every numeric field a JAX scalar of ``dtype`` (the state's float type):
    what an env state carries as its vehicle.  Stack several (``jax.tree.map(jnp.stack)``)
    and vmap ``reset_with_track`` over them to fly a different vehicle in each env."""
    dtype = dtype or jnp.zeros(()).dtype
    return jax.tree.map(lambda x: jnp.asarray(x, dtype), quad)


def _as_arrays(quad: QuadParams, rate_model: str, dtype) -> QuadParams:
    return vehicle_arrays(quad, dtype).replace(rate_model=rate_model)


def draw(cfg: EnvConfig, key: jax.Array, quad: QuadParams | None = None, dtype=None) -> Plant:
    """A plant drawn from ``cfg.randomization``'s ranges around ``quad`` (None: the config's
    vehicle), each uniform; ``key`` is folded with :data:`PLANT_TAG` first."""
    r = cfg.randomization
    dtype = dtype or jnp.zeros(()).dtype
    if r.vehicles:  # the nominal vehicle, drawn; the errors below apply around it
        if quad is not None:
            raise ValueError(
                "randomization.draw: a config with randomization.vehicles draws its vehicle; quad None"
            )
        known = vm.draw_vehicle(r.vehicles, cfg.vehicle.quad, key, dtype)
        quad = known.replace(rate_model=flown_rate_model(cfg))
    else:
        quad = _as_arrays(cfg.vehicle.quad if quad is None else quad, flown_rate_model(cfg), dtype)
    k = jax.random.split(jax.random.fold_in(key, PLANT_TAG), 10)

    def uni(i, rng, shape=(), neutral=1.0):
        lo, hi = rng
        return lo + (hi - lo) * jax.random.uniform(k[i], shape, dtype)

    rate = uni(4, r.rate_limit)
    inertia = uni(1, r.inertia, (3,))
    thrust_max, tau = uni(2, r.thrust_max), uni(3, r.tau_rate)
    if quad.rate_model == "firmware":
        quad = quad.replace(
            loop=_draw_loop(quad.loop, jax.random.fold_in(key, FIRMWARE_TAG), r, thrust_max, tau)
        )
    quad = quad.replace(
        mass=quad.mass * uni(0, r.mass),
        inertia=tuple(i * inertia[j] for j, i in enumerate(quad.inertia)),
        thrust_max=quad.thrust_max * thrust_max,
        tau_rate=quad.tau_rate * tau,
        rate_min=quad.rate_min * rate,
        rate_max=quad.rate_max * rate,
    )
    lo, hi = latency_steps(cfg)
    latency = jax.random.randint(k[5], (), lo, hi + 1, jnp.int32)
    if fixed_pos_bias(cfg):
        bias = jnp.asarray(r.pos_bias, dtype)
    else:
        bias = uni(8, (-r.pos_bias, r.pos_bias), (3,), 0.0)
    kind, known_part = (VehiclePlant, dict(nominal=known)) if r.vehicles else (Plant, {})
    return kind(
        **known_part,
        quad=quad,
        thrust_gain=uni(6, r.thrust_gain),
        latency=latency,
        noise_scale=uni(7, r.obs_noise, neutral=0.0),
        pos_bias=bias,
        wind_mean=uni(9, (-r.wind_mean, r.wind_mean), (3,), 0.0),
    )


def _draw_loop(loop: il.InnerLoop, key: jax.Array, r, thrust_max: jax.Array, tau: jax.Array) -> il.InnerLoop:
    """The firmware model's inner loop of one episode: the rotors' limits scaled with
    ``thrust_max``, their time constants with ``tau`` (the ``tau_rate`` draw), and the rate
    gains and drag drawn from ``rate_gains`` and ``drag`` (a key of their own)."""
    k_gain, k_drag = jax.random.split(key)
    gain = r.rate_gains[0] + (r.rate_gains[1] - r.rate_gains[0]) * jax.random.uniform(
        k_gain, (), thrust_max.dtype
    )
    drag = r.drag[0] + (r.drag[1] - r.drag[0]) * jax.random.uniform(k_drag, (), thrust_max.dtype)
    scale = lambda v, f: tuple(x * f for x in v)  # noqa: E731
    return loop.replace(kp=scale(loop.kp, gain), ki=scale(loop.ki, gain), kd=scale(loop.kd, gain),
                        motor_min=loop.motor_min * thrust_max, motor_max=loop.motor_max * thrust_max,
                        tau_up=loop.tau_up * tau, tau_down=loop.tau_down * tau,
                        drag=loop.drag * drag)  # fmt: skip


def commanded_lags(cfg: EnvConfig, latency: jax.Array) -> jax.Array:
    """(action_repeat,) int: for each physics substep j of a control step, how many control
    steps ago the command it applies was given, ceil((latency − j) / action_repeat) >= 0."""
    r = cfg.action_repeat
    j = jnp.arange(r, dtype=jnp.int32)
    return jnp.clip((latency - j + r - 1) // r, 0, pending_size(cfg))
