"""Robustness suite: the evaluation repeated under disturbances (spec O3).

Each condition (``ROBUSTNESS_DESCRIPTIONS``) is an evaluation config of the nominal config
the controller was built for.  :func:`evaluate_robustness` reports, per condition, Σ‖e‖ (m)
and energy Σ‖a‖ over Spiral-RT and the LOS-RT test instances (mean ± std over seeds) and
the crash count (``python -m ttd3_jax.evaluate [RUN_DIR] --robustness`` prints it).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttd3_jax.control.evaluator import Build, Evaluator, los_statistics
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.env import TrackingEnv

ROBUSTNESS_WIND = 0.5  # m/s^2, OU stationary std (spec O3)
ROBUSTNESS_MASS = 0.2  # ± fraction of the mass, unknown to the controller
# observation noise std: position m, velocity m/s, each quaternion component (then renormalised)
ROBUSTNESS_OBS_NOISE = {"obs_noise_pos": 0.01, "obs_noise_vel": 0.05, "obs_noise_quat": 0.005}
ROBUSTNESS_DESCRIPTIONS = {
    "nominal": "nominal evaluation (spec §2.5)",
    "wind": f"OU acceleration disturbance, σ = {ROBUSTNESS_WIND} m/s², τ = 0.5 s",
    "mass+20": f"vehicle mass +{ROBUSTNESS_MASS:.0%}, unknown to the controller and the action map",
    "mass-20": f"vehicle mass -{ROBUSTNESS_MASS:.0%}, unknown to the controller and the action map",
    "obs_noise": "observation noise (std): position 0.01 m, velocity 0.05 m/s, quaternion 0.005",
    "delay": "one control step of actuation delay (the env applies the previous action)",
}
ROBUSTNESS_CONDITIONS = tuple(ROBUSTNESS_DESCRIPTIONS)


def robustness_conditions(cfg: EnvConfig) -> dict[str, EnvConfig]:
    """Evaluation configs (``cfg.for_eval("los_rt")``) of each robustness condition.  The mass
    conditions pin ``thrust_map_mass`` to the nominal mass, so that a hover-centred action map
    does not learn of the change either.  A step of delay is one control step (1 or 10 ms)."""
    nominal = cfg.for_eval("los_rt")
    m0 = cfg.vehicle.quad.mass if cfg.vehicle.thrust_map_mass is None else cfg.vehicle.thrust_map_mass

    def mass(factor):
        quad = nominal.vehicle.quad.replace(mass=cfg.vehicle.quad.mass * factor)
        return nominal.replace(quad=quad, thrust_map_mass=m0)

    return {
        "nominal": nominal,
        "wind": cfg.for_eval("los_rt", wind_sigma=ROBUSTNESS_WIND),
        "mass+20": mass(1.0 + ROBUSTNESS_MASS),
        "mass-20": mass(1.0 - ROBUSTNESS_MASS),
        "obs_noise": nominal.replace(**ROBUSTNESS_OBS_NOISE),
        "delay": nominal.replace(action_delay=1),
    }


def evaluate_robustness(build: Build, theta, cfg: EnvConfig, los_seeds=range(1, 21), *,
                        conditions=ROBUSTNESS_CONDITIONS, sequential: bool = False,
                        seed: int = 0) -> dict:  # fmt: skip
    """The controller ``build(theta)`` (built by the caller for the *nominal* ``cfg``) under
    each robustness condition: ``{condition: summarize(...)}`` over Spiral-RT and the LOS-RT
    test instances ``los_seeds`` (mean ± std of Σ‖e‖, energy, crash count).  Each track of a
    condition runs in one compiled batch; wind and noise keys differ per track (fold_in of
    ``seed``)."""
    all_conditions = robustness_conditions(cfg)
    unknown = [c for c in conditions if c not in all_conditions]
    if unknown:
        raise ValueError(f"unknown robustness condition(s) {unknown}; allowed: {ROBUSTNESS_CONDITIONS}")
    los_seeds = tuple(los_seeds)
    base = jax.random.PRNGKey(seed)
    keys = jnp.stack([jax.random.fold_in(base, i) for i in range(len(los_seeds) + 1)])
    out = {}
    for name in conditions:
        ev = Evaluator(TrackingEnv(all_conditions[name]), build, sequential=sequential)
        out[name] = los_statistics(ev, theta, los_seeds, keys)
    return out
