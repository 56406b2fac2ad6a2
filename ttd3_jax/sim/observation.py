"""The named observation layout: one table of the parts the env's observation is built from.

:func:`layout` gives, for an env configuration, the ordered :class:`Part` s of the observation
(name, entry names, meaning, and whether only the critics see it).  ``TrackingEnv.observe``
builds the observation from it (:meth:`ObsLayout.build`), the closed loop reads the vehicle
state back through :meth:`ObsLayout.slice`, and the export writes it into ``policy.json``.
The critics-only parts come last, so that the actor reads the leading
:attr:`ObsLayout.actor_size` entries.
"""

from __future__ import annotations

import dataclasses

from ttd3_jax.sim import vehicle_mix as vm
from ttd3_jax.sim.config import PRIVILEGED_AHEAD_S, EnvConfig

XYZ = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class Part:
    """One named slice of the observation."""

    name: str  # the key ``observe`` fills and ``slice`` reads
    entries: tuple[str, ...]  # the name of each entry, in order (policy.json)
    meaning: str  # what it is, with its unit
    critic_only: bool = False  # True: the critics see it, the actor does not

    @property
    def size(self) -> int:
        return len(self.entries)


@dataclasses.dataclass(frozen=True)
class ObsLayout:
    """The observation's parts in order; the critics-only ones after all the others."""

    parts: tuple[Part, ...]

    def __post_init__(self):
        names = [p.name for p in self.parts]
        if len(set(names)) != len(names):
            raise ValueError(f"ObsLayout: part names must be unique, got {names}")
        flags = [p.critic_only for p in self.parts]
        if flags != sorted(flags):
            raise ValueError(f"ObsLayout: the critics-only parts must come last, got {names}")

    @property
    def size(self) -> int:
        """Entries of the whole observation (what the critics read)."""
        return sum(p.size for p in self.parts)

    @property
    def actor_size(self) -> int:
        """Entries the actor reads: the leading ones, up to the first critics-only part."""
        return sum(p.size for p in self.parts if not p.critic_only)

    @property
    def names(self) -> list[str]:
        """Every entry's name, in order."""
        return [e for p in self.parts for e in p.entries]

    @property
    def critic_only(self) -> tuple[str, ...]:
        """The names of the parts only the critics see."""
        return tuple(p.name for p in self.parts if p.critic_only)

    def has(self, name: str) -> bool:
        return any(p.name == name for p in self.parts)

    def slice(self, name: str) -> slice:
        """Where part ``name`` sits in the observation (``KeyError`` when it is not there)."""
        start = 0
        for p in self.parts:
            if p.name == name:
                return slice(start, start + p.size)
            start += p.size
        raise KeyError(f"observation part {name!r} not in {[p.name for p in self.parts]}")

    def build(self, values: dict, concatenate):
        """``concatenate`` of ``values[name]`` in layout order; ``values`` must hold exactly the
        layout's parts (a static check: the layout and the code that fills it agree)."""
        want = [p.name for p in self.parts]
        if set(values) != set(want):
            raise ValueError(f"observation parts {sorted(values)} do not match the layout {want}")
        return concatenate([values[name] for name in want])

    def describe(self) -> list[dict]:
        """The parts as ``policy.json`` records them: name, start, size, meaning, critics only."""
        return [dict(name=p.name, start=self.slice(p.name).start, size=p.size, meaning=p.meaning,
                     critic_only=p.critic_only) for p in self.parts]  # fmt: skip


def preview_name(t: float) -> str:
    """The part of the actor's preview point ``t`` s after p_d,k+L (``observation.preview_s``)."""
    return f"preview_{t:g}s"


def _vec(prefix: str) -> tuple[str, ...]:
    return tuple(f"{prefix}.{a}" for a in XYZ)


def layout(cfg: EnvConfig) -> ObsLayout:
    """The observation of an env with configuration ``cfg`` (O1, then this project's parts)."""
    rel = cfg.observation.obs_frame == "track"  # positions relative to p_d,k
    where = " relative to p_d,k" if rel else ", world frame"
    # with ref_integral_gain, p is p - s throughout (memory_spec in policy_export says how)
    shifted = "; p - s, s the reference integral's shift" if cfg.observation.ref_integral_gain > 0 else ""
    parts = [
        Part("p", _vec("p - p_d" if rel else "p"), f"position (m){where}{shifted}"),
        Part("v", _vec("v"), "velocity (m/s), world frame"),
        Part("q", tuple(f"q.{a}" for a in "wxyz"), "attitude, unit quaternion body to world, scalar first"),
        Part(
            "p_ahead",
            _vec("p_ahead - p_d" if rel else "p_ahead"),
            f"reference p_d,k+L (m), L = lookahead_k physics steps{where}",
        ),  # fmt: skip
        Part("p_ahead_error", _vec("p_ahead - p"), "p_d,k+L - p (m)"),
        Part("error", ("|p_err - p|",), "||p_err - p|| (m), p_err = p_d,k or p_d,k+1 (err_ref)"),
    ]
    if cfg.vehicle.quad.rate_model != "instant":
        parts.append(Part("omega", _vec("omega"), "body rates (rad/s), body frame"))
    if cfg.observation.obs_memory:
        parts.append(Part("last_action", tuple(f"last_action.{i}" for i in range(4)),
                          "the action the last step applied (zeros at reset)"))  # fmt: skip
        parts.append(Part("error_integral", _vec("error_integral"),
                          "leaky integral of p_d - p (m s), leak time constant memory_tau"))  # fmt: skip
    if cfg.observation.action_history_s:
        times = cfg.observation.action_history_s
        names = tuple(f"action_history_{t:g}s.{i}" for t in times for i in range(4))
        meaning = "leaky averages of the applied action, 4 per time constant action_history_s"
        parts.append(Part("action_history", names, meaning))
    if cfg.randomization.vehicles:  # the known vehicle of one policy for several (sim.vehicle_mix)
        parts.append(Part("vehicle", tuple(f"vehicle.{e}" for e in vm.DESCRIPTOR), vm.DESCRIPTOR_MEANING))
    for t in cfg.observation.preview_s:
        meaning = f"the reference {t:g} s after p_d,k+L, relative to it (m)"
        parts.append(Part(preview_name(t), _vec(f"p_d(+{t:g} s) - p_ahead"), meaning))
    if cfg.observation.obs_privileged:
        parts.append(Part("wind", _vec("wind"), "the wind acceleration (m/s^2)", critic_only=True))
        for t in PRIVILEGED_AHEAD_S:
            meaning = f"the reference {t:g} s after p_d,k+L, relative to it (m)"
            parts.append(Part(f"p_ahead_{t:g}s", _vec(f"p_d(+{t:g} s) - p_ahead"), meaning, critic_only=True))
    return ObsLayout(tuple(parts))
