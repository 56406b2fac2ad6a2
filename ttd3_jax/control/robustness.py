"""Robustness suite: the evaluation repeated under a fixed, unknown mismatch (spec O3, issue 37).

Each condition (``ROBUSTNESS_DESCRIPTIONS``) is the evaluation config of the nominal config
the controller was built for, with one perturbation of the flown plant, its actuation or
its observation fixed on top (``EnvConfig.randomization`` with ``lo == hi``, the
disturbances' wind and noise).  The controller (a policy, or a classical controller built
for the nominal config) does not know it: the action map stays the nominal vehicle's.
:func:`evaluate_robustness` reports, per condition, Σ‖e‖ (m) and energy Σ‖a‖ over
Spiral-RT and the LOS-RT test instances (mean ± std over seeds) and the crash count
(``python -m ttd3_jax.evaluate [RUN_DIR] --robustness`` prints it).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ttd3_jax.control.evaluator import Build, Evaluator, los_statistics
from ttd3_jax.sim.config import EnvConfig
from ttd3_jax.sim.env import TrackingEnv

ROBUSTNESS_WINDS = (0.5, 1.0)  # m/s^2, OU stationary std (spec O3), τ = 0.5 s
ROBUSTNESS_MASS = 0.3  # ± fraction of the mass
ROBUSTNESS_THRUST_GAIN = 0.8  # thrust produced / thrust commanded (20 % less thrust)
ROBUSTNESS_TAU_RATE = 0.05  # s, the flown body-rate time constant
ROBUSTNESS_LATENCIES = (0.01, 0.02)  # s of actuation latency (1 and 2 steps of a 100 Hz policy)
# observation noise std: position m, velocity m/s, each quaternion component (then renormalised)
ROBUSTNESS_OBS_NOISE = {"obs_noise_pos": 0.01, "obs_noise_vel": 0.05, "obs_noise_quat": 0.005}
ROBUSTNESS_POS_BIAS = 0.02  # m, length of the constant bias of the observed position
# its fixed direction: the diagonal (1, 1, 1)/√3, so every axis is off by 2/√3 ≈ 1.15 cm
POS_BIAS_VECTOR = tuple(ROBUSTNESS_POS_BIAS / math.sqrt(3) for _ in range(3))

_UNKNOWN = "unknown to the controller (the action map and the controller keep the nominal vehicle)"
ROBUSTNESS_DESCRIPTIONS = {
    "nominal": "nominal evaluation (spec §2.5)",
    **{f"wind{w:.1f}": f"OU acceleration disturbance, σ = {w:g} m/s², τ = 0.5 s" for w in ROBUSTNESS_WINDS},
    "mass+30": f"vehicle mass +{ROBUSTNESS_MASS:.0%}, {_UNKNOWN}",
    "mass-30": f"vehicle mass -{ROBUSTNESS_MASS:.0%}, {_UNKNOWN}",
    "thrust-20": f"every thrust command produces {1 - ROBUSTNESS_THRUST_GAIN:.0%} less thrust (thrust gain "
    f"{ROBUSTNESS_THRUST_GAIN:g}), {_UNKNOWN}",
    "rate_tau0.05": f"the body rates follow the command with a first-order time constant of "
    f"{ROBUSTNESS_TAU_RATE:g} s, {_UNKNOWN}",
    **{
        f"latency{1e3 * s:g}ms": f"actuation latency {1e3 * s:g} ms (whole physics steps, the same for every "
        f"control rate), {_UNKNOWN}"
        for s in ROBUSTNESS_LATENCIES
    },  # fmt: skip
    "obs_noise": "observation noise (std): position 0.01 m, velocity 0.05 m/s, quaternion 0.005",
    "pos_bias2cm": f"constant bias of the observed position, {100 * ROBUSTNESS_POS_BIAS:g} cm along "
    "(1, 1, 1)/√3, unknown to the controller",
}
ROBUSTNESS_CONDITIONS = tuple(ROBUSTNESS_DESCRIPTIONS)


def fixed(value: float) -> tuple[float, float]:
    """A randomisation range that always draws ``value``."""
    return (float(value), float(value))


def mass_error(nominal: EnvConfig, fraction: float) -> EnvConfig:
    """``nominal`` flying a vehicle ``1 + fraction`` times as heavy, unknown to the controller."""
    return nominal.replace(mass=fixed(1.0 + fraction))


def latency(nominal: EnvConfig, seconds: float) -> EnvConfig:
    """``nominal`` with ``seconds`` of actuation latency."""
    return nominal.replace(latency=fixed(seconds))


def obs_noise(nominal: EnvConfig, scale: float = 1.0) -> EnvConfig:
    """``nominal`` with ``scale`` times the robustness row's observation-noise stds."""
    return nominal.replace(**{k: scale * v for k, v in ROBUSTNESS_OBS_NOISE.items()})


def pos_bias(nominal: EnvConfig, bias=POS_BIAS_VECTOR) -> EnvConfig:
    """``nominal`` with a constant bias ``bias`` (3,) m of the observed position."""
    return nominal.replace(pos_bias=tuple(float(b) for b in bias))


def robustness_conditions(cfg: EnvConfig) -> dict[str, EnvConfig]:
    """Evaluation configs (``cfg.for_eval("los_rt")``) of each robustness condition: one
    fixed perturbation each (``randomization`` ranges with ``lo == hi``), so every track of
    a condition flies the same plant.  Latency is in seconds, the same for a 100 Hz policy
    and a 1 kHz NMPC."""
    nominal = cfg.for_eval("los_rt")
    tau = ROBUSTNESS_TAU_RATE / cfg.vehicle.quad.tau_rate
    return {
        "nominal": nominal,
        **{f"wind{w:.1f}": cfg.for_eval("los_rt", wind_sigma=w) for w in ROBUSTNESS_WINDS},
        "mass+30": mass_error(nominal, ROBUSTNESS_MASS),
        "mass-30": mass_error(nominal, -ROBUSTNESS_MASS),
        "thrust-20": nominal.replace(thrust_gain=fixed(ROBUSTNESS_THRUST_GAIN)),
        "rate_tau0.05": nominal.replace(tau_rate=fixed(tau)),
        **{f"latency{1e3 * s:g}ms": latency(nominal, s) for s in ROBUSTNESS_LATENCIES},
        "obs_noise": obs_noise(nominal),
        "pos_bias2cm": pos_bias(nominal),
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
    return evaluate_configs(build, theta, {c: all_conditions[c] for c in conditions}, los_seeds,
                            sequential=sequential, seed=seed)  # fmt: skip


def evaluate_configs(build: Build, theta, configs: dict[str, EnvConfig], los_seeds=range(1, 21), *,
                     sequential: bool = False, seed: int = 0, progress=None) -> dict:  # fmt: skip
    """:func:`~ttd3_jax.control.evaluator.los_statistics` of ``build(theta)`` on each
    evaluation config of ``configs`` (``{name: summary}``), one compiled batch each, with the
    keys of :func:`evaluate_robustness`; ``progress(name, summary)`` is called after each."""
    los_seeds = tuple(los_seeds)
    keys = condition_keys(len(los_seeds), seed)
    out = {}
    for name, c in configs.items():
        ev = Evaluator(TrackingEnv(c), build, sequential=sequential)
        out[name] = los_statistics(ev, theta, los_seeds, keys)
        if progress is not None:
            progress(name, out[name])
    return out


def condition_keys(num_los_seeds: int, seed: int = 0) -> jax.Array:
    """The wind and noise keys of one condition's batch (Spiral-RT, then ``num_los_seeds``
    LOS-RT tracks): ``fold_in(PRNGKey(seed), i)``, as :func:`evaluate_configs` uses them."""
    base = jax.random.PRNGKey(seed)
    return jnp.stack([jax.random.fold_in(base, i) for i in range(num_los_seeds + 1)])
