"""One policy, several vehicles (issue 37, item 5): the vehicles between two named ones, in
units every one of them shares.

With ``EnvConfig.randomization.vehicles = (a, b)`` (names of :data:`~ttd3_jax.sim.vehicles.VEHICLE_NAMES`)
each training episode draws s ~ U[0, 1] and flies the vehicle :func:`interpolate` gives: every
numeric field of :class:`~ttd3_jax.sim.dynamics.QuadParams` geometric (log-linear) between the two,
``a`` at s = 0 and ``b`` at s = 1 exactly; a signed field (``rate_min``) is the negative of its
magnitude's interpolation.  The config's vehicle gives the rest: the rate model, gravity and
thrust units (:func:`flown_as`).  That drawn vehicle is the episode's *nominal* vehicle, known to
the controller: the action map is its own (hover-centred thrust: a0 = 0 is its hover; rates as
fractions of its limits; ``sim.env``), and the actor observes its :func:`descriptor`.  The
randomisation's factors (mass, thrust gain, ...) then apply on top of it, unknown, as they do
around the config's vehicle.  ``(a, a)`` is vehicle ``a`` alone in the same units: what
evaluation flies (:func:`pin_vehicle`).

Layer ``sim``: imports the dynamics and the vehicle presets, no config (the config imports it:
the functions that take an ``EnvConfig`` read it without naming its type).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax import checks
from ttd3_jax.sim.dynamics import QuadParams
from ttd3_jax.sim.vehicles import VEHICLES

VEHICLE_TAG = 0x7E41  # folded into a reset's key to draw s, so that no other draw changes
RATE_REF, TAU_REF = 6.0, 0.03  # rad/s, s: the paper vehicle's rate limit and rate time constant
# the observation's "vehicle" part (sim.observation): the nominal vehicle's entries, each 0 for the paper's
# rate limit and time constant; thrust-to-weight 1.36 (paper) to 1.97 (crazyflie)
DESCRIPTOR = ("thrust_max / hover_thrust - 1", "ln(rate_max / 6 rad/s)", "ln(tau_rate / 0.03 s)")
DESCRIPTOR_MEANING = (
    "the episode's nominal vehicle (known, not its unknown errors): thrust-to-weight - 1 (thrust_max over "
    "mass x gravity), ln of its body-rate limit over 6 rad/s, ln of its rate time constant over 0.03 s"
)


def flown_as(name: str, like: QuadParams) -> QuadParams:
    """Preset ``name`` with ``like``'s rate model, thrust units and gravity (the config's)."""
    return VEHICLES[name].replace(
        gravity=like.gravity, rate_model=like.rate_model, thrust_units=like.thrust_units
    )


def pin_vehicle(cfg, name: str | None = None):
    """The ``EnvConfig`` ``cfg`` flying ``name`` (None: the first) of its ``randomization.vehicles``
    every episode: vehicles (name, name), quad that vehicle (:func:`flown_as`); the observation's
    layout and the shared action map stay.  ``cfg`` as it is without ``vehicles``."""
    v = cfg.randomization.vehicles
    if v and name is not None and name not in v:
        checks.fail("vehicle", f"one of EnvConfig.randomization.vehicles {v}", name)
    name = name or (v[0] if v else None)
    return cfg.replace(vehicles=(name, name), quad=flown_as(name, cfg.vehicle.quad)) if v else cfg


def check_units(cfg) -> None:
    """``randomization.vehicles`` of the ``EnvConfig`` ``cfg`` needs the units the vehicles share:
    hover-centred thrust, each vehicle's own hover (no ``thrust_map_mass``), newtons."""
    v = cfg.vehicle
    need = [n for ok, n in ((v.hover_centered_thrust, "vehicle.hover_centered_thrust true"),
                            (v.thrust_map_mass is None, "vehicle.thrust_map_mass None"),
                            (v.quad.thrust_units == "newton", "vehicle.quad.thrust_units 'newton'"),
                            (v.quad.rate_model != "firmware", "vehicle.quad.rate_model not 'firmware'"))
            if not ok]  # fmt: skip
    if need:
        raise ValueError(f"EnvConfig.randomization.vehicles {cfg.randomization.vehicles} needs {need[0]} "
                         "(the units they share: a0 = 0 is each vehicle's own hover thrust)")  # fmt: skip


def _between(x: float, y: float, s: jax.Array) -> jax.Array:
    """``x`` (s = 0) to ``y`` (s = 1) geometrically; exact at both ends and where ``x == y``."""
    if x == y:
        return jnp.full_like(s, x)
    if x < 0 and y < 0:
        return -_between(-x, -y, s)
    if not (x > 0 and y > 0):
        raise ValueError(
            f"vehicle_mix: cannot interpolate {x} and {y} geometrically (signs differ or one is 0)"
        )
    return jnp.where(s <= 0.5, x * (y / x) ** s, y * (x / y) ** (1.0 - s))


def interpolate(a: QuadParams, b: QuadParams, s: jax.Array) -> QuadParams:
    """The vehicle a fraction ``s`` (an array; any shape) of the way from ``a`` to ``b`` in every
    numeric field, geometric (:func:`_between`), as arrays of ``s``'s dtype; ``a`` and ``b`` must
    share the rate model and thrust units (:func:`flown_as`)."""
    s = jnp.asarray(s)
    return jax.tree.map(lambda x, y: _between(float(x), float(y), s), a, b)


def draw_vehicle(names: tuple[str, str], like: QuadParams, key: jax.Array, dtype) -> QuadParams:
    """An episode's nominal vehicle: s ~ U[0, 1) from ``key`` (folded with :data:`VEHICLE_TAG`),
    between ``names`` flown as ``like`` (:func:`flown_as`)."""
    s = jax.random.uniform(jax.random.fold_in(key, VEHICLE_TAG), (), dtype)
    return interpolate(flown_as(names[0], like), flown_as(names[1], like), s)


def descriptor(q: QuadParams) -> jax.Array:
    """(3,) the observed :data:`DESCRIPTOR` of vehicle ``q`` (its fields arrays of one float type,
    ``sim.randomization.vehicle_arrays``; newton thrust units)."""
    tw = q.thrust_max / (q.gravity * q.mass) - 1.0
    return jnp.stack([tw, jnp.log(q.rate_max / RATE_REF), jnp.log(q.tau_rate / TAU_REF)])
