"""Your own reference tracks: samples on a time grid, a Python function of time, or a CSV
file with header ``t,x,y,z`` (seconds, metres) and optional ``vx,vy,vz`` (m/s) and
``ax,ay,az`` (m/s^2) columns.

A :class:`CustomTrack` holds the reference resampled on the physics grid (``dt``, 1 ms)
and becomes a table :class:`~ttd3_jax.sim.trajectories.Track` (one segment per physics
step), which the env, every controller and the NMPC's preview read like a built-in track.

* Times are shifted so that the first sample is t = 0; they must increase strictly.
* Velocity and acceleration not given are derived by second-order finite differences on
  the samples' own grid, then all three are interpolated linearly onto the physics grid.
* The episode lasts as long as the track.  After its last sample the reference **holds
  the last point** (v = a = 0): that is what the NMPC's 1 s preview and the policy's
  look-ahead see near the end, stated here rather than extrapolated silently.
* A step from hover: the vehicle starts at rest on p_d(0), so a track whose first sample
  is the hover point and whose later samples sit at the target, with v = a = 0 given
  (``vel`` / ``acc`` zeros, or ``vx..az`` columns of zeros), is a position step.
  :func:`step` builds one.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.sim import trajectories as tr

CSV_REQUIRED = ("t", "x", "y", "z")
CSV_OPTIONAL = (("vx", "vy", "vz"), ("ax", "ay", "az"))
MIN_SAMPLES = 3
MAX_RATE = 1e6  # bound on |velocity| (m/s) and |acceleration| (m/s^2), given or derived


@dataclasses.dataclass(frozen=True)
class CustomTrack:
    """A reference on the physics grid: ``pos``, ``vel``, ``acc`` each (n, 3) at t_k = k·dt,
    k = 0 … n−1 (m, m/s, m/s^2)."""

    name: str
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    dt: float = 1e-3

    @property
    def duration_s(self) -> float:
        return (self.pos.shape[0] - 1) * self.dt

    def episode_steps(self, action_repeat: int) -> int:
        """Physics steps an episode on this track lasts: the longest multiple of
        ``action_repeat`` that fits in the track."""
        return (self.pos.shape[0] - 1) // action_repeat * action_repeat

    def track(self, num_segments: int | None = None) -> tr.Track:
        """The table :class:`~ttd3_jax.sim.trajectories.Track`: the n samples, then rows that
        hold the last point, ``num_segments`` rows in all (default n + 1)."""
        n = self.pos.shape[0]
        rows = n + 1 if num_segments is None else num_segments
        if rows < n + 1:
            raise ValueError(f"num_segments={rows} is too small for track {self.name!r}; allowed: >= {n + 1}")
        hold = rows - n
        pos = np.concatenate([self.pos, np.repeat(self.pos[-1:], hold, 0)])
        zeros = np.zeros((hold, 3))
        return tr.table(pos, np.concatenate([self.vel, zeros]), np.concatenate([self.acc, zeros]))


def _array(name: str, x, shape_hint: str, bound: float = math.inf) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # derived differences of huge values
        ok = np.isfinite(a) & (np.abs(a) <= bound)
    if not np.all(ok):
        bad = tuple(int(i) for i in np.argwhere(~ok)[0])
        span = f" and within ±{bound:g}" if math.isfinite(bound) else ""
        raise ValueError(f"{name} must be finite{span}; entry {bad} is {a[bad]}")
    if a.ndim != len(shape_hint.split(",")):
        raise ValueError(f"{name} must have shape ({shape_hint}), got {a.shape}")
    return a


def from_samples(t, pos, vel=None, acc=None, *, dt: float = 1e-3, name: str = "custom") -> CustomTrack:
    """A track from reference samples: ``t`` (N,) s strictly increasing, ``pos`` (N, 3) m,
    optional ``vel`` (N, 3) m/s and ``acc`` (N, 3) m/s^2 (finite differences otherwise)."""
    t = _array("t", t, "N")
    if t.size < MIN_SAMPLES:
        raise ValueError(f"a track needs at least {MIN_SAMPLES} samples, got {t.size}")
    if not np.all(np.diff(t) > 0):
        i = int(np.argmax(~(np.diff(t) > 0)))
        raise ValueError(f"t must increase strictly; t[{i}] = {t[i]} is followed by t[{i + 1}] = {t[i + 1]}")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0 s, got {dt}")
    t = t - t[0]
    if t[-1] < 2 * dt:
        raise ValueError(f"the track lasts {t[-1]} s; it must last at least 2 physics steps ({2 * dt} s)")
    p = _array("pos [m]", pos, "N, 3", tr.MAX_COORD)
    if p.shape != (t.size, 3):
        raise ValueError(f"pos must have shape ({t.size}, 3) to match t, got {p.shape}")
    with np.errstate(over="ignore", invalid="ignore"):
        v = np.gradient(p, t, axis=0, edge_order=2) if vel is None else vel
        v = _array("vel [m/s]" + " (from pos)" * (vel is None), v, "N, 3", MAX_RATE)
        a = np.gradient(v, t, axis=0, edge_order=2) if acc is None else acc
        a = _array("acc [m/s^2]" + " (from vel)" * (acc is None), a, "N, 3", MAX_RATE)
    for label, x in (("vel", v), ("acc", a)):
        if x.shape != p.shape:
            raise ValueError(f"{label} must have shape {p.shape} like pos, got {x.shape}")
    grid = np.arange(int(math.floor(t[-1] / dt + 1e-9)) + 1) * dt
    on_grid = [np.stack([np.interp(grid, t, x[:, j]) for j in range(3)], -1) for x in (p, v, a)]
    return CustomTrack(name, *on_grid, dt=dt)


def from_function(f: Callable[[np.ndarray], np.ndarray], duration_s: float, *, dt: float = 1e-3,
                  name: str = "custom") -> CustomTrack:  # fmt: skip
    """A track from ``f(t) -> positions``: ``t`` (M,) s on the physics grid 0 … duration_s,
    positions (M, 3) m; velocity and acceleration by finite differences."""
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be a finite number > 0, got {duration_s}")
    t = np.arange(int(math.floor(duration_s / dt + 1e-9)) + 1) * dt
    return from_samples(t, f(t), dt=dt, name=name)


def from_csv(path: str, *, dt: float = 1e-3) -> CustomTrack:
    """A track from a CSV file (see the module docstring); errors name the file."""
    if os.path.exists(path) and not os.path.isfile(path):  # a FIFO or a device would block the read
        raise ValueError(f"cannot read track file {path!r}: not a regular file (a directory, FIFO or device)")
    try:  # utf-8-sig: a byte-order mark (as Excel writes) is not part of the first column's name
        with open(path, newline="", encoding="utf-8-sig") as fh:  # (line number, cells); blank, "#" skipped
            rows = [
                (n, r) for n, r in enumerate(csv.reader(fh), 1) if r and not r[0].lstrip().startswith("#")
            ]
    except OSError as e:
        raise ValueError(f"cannot read track file {path!r}: {e.strerror}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        bad = isinstance(e, UnicodeDecodeError)
        what = f"byte {e.object[e.start]:#04x} at offset {e.start}" if bad else e
        head = ",".join(CSV_REQUIRED)
        raise ValueError(f"{path} is not a CSV text file ({what}); expected a header {head}") from None
    if not rows:
        raise ValueError(f"{path}: empty file; expected a header {','.join(CSV_REQUIRED)}")
    head = [h.strip() for h in rows[0][1]]
    missing = [c for c in CSV_REQUIRED if c not in head]
    if missing:
        raise ValueError(f"{path}: header {head} lacks column(s) {missing}; required: {list(CSV_REQUIRED)}")
    allowed = set(CSV_REQUIRED).union(*CSV_OPTIONAL)
    unknown = [c for c in head if c not in allowed]
    if unknown:
        raise ValueError(f"{path}: unknown column(s) {unknown}; allowed: {sorted(allowed)}")
    values = []
    for n, r in rows[1:]:
        if len(r) != len(head):
            raise ValueError(f"{path}, line {n}: {len(r)} values for the {len(head)} columns {head}")
        try:
            values.append([float(x) for x in r])
        except ValueError as e:
            raise ValueError(f"{path}, line {n}: every value must be a number ({e})") from None
    data = np.array(values, dtype=np.float64).reshape(-1, len(head))
    lines = [n for n, _ in rows[1:]]
    bad = np.argwhere(~np.isfinite(data))
    if bad.size:
        ((i, j),) = bad[:1]
        raise ValueError(f"{path}, line {lines[i]}: {head[j]} = {data[i, j]}; every value must be finite")
    t = data[:, head.index("t")]
    if t.size > 1 and not np.all(np.diff(t) > 0):
        i = int(np.argmax(~(np.diff(t) > 0))) + 1
        raise ValueError(
            f"{path}, line {lines[i]}: t = {t[i]} s does not increase (previous row: {t[i - 1]} s)"
        )
    col = {h: data[:, i] for i, h in enumerate(head)}
    derived = []
    for names in CSV_OPTIONAL:
        present = [c in col for c in names]
        if any(present) and not all(present):
            raise ValueError(f"{path}: give all of {list(names)} or none")
        derived.append(np.stack([col[c] for c in names], -1) if all(present) else None)
    name = path.rsplit("/", 1)[-1].removesuffix(".csv")
    try:
        return from_samples(col["t"], np.stack([col[c] for c in "xyz"], -1), *derived, dt=dt, name=name)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def to_csv(track: CustomTrack, path: str) -> None:
    """Write ``track`` as a CSV file with every column (``from_csv`` reads it back)."""
    t = np.arange(track.pos.shape[0]) * track.dt
    cols = np.concatenate([t[:, None], track.pos, track.vel, track.acc], -1)
    header = ",".join((*CSV_REQUIRED, *CSV_OPTIONAL[0], *CSV_OPTIONAL[1]))
    np.savetxt(path, cols, delimiter=",", header=header, comments="", fmt="%.9g")


def step(target, duration_s: float = 3.0, *, dt: float = 1e-3, name: str = "step") -> CustomTrack:
    """A position step from hover at the origin to ``target`` (3,) m at t = dt, v = a = 0."""
    n = int(math.floor(duration_s / dt + 1e-9)) + 1
    pos = np.zeros((n, 3))
    pos[1:] = np.asarray(target, np.float64)
    return CustomTrack(name, pos, np.zeros((n, 3)), np.zeros((n, 3)), dt=dt)


def pad(t: tr.Track, num_segments: int, dt: float = 1e-3) -> tr.Track:
    """``t`` with its table grown to ``num_segments`` rows that continue the last segment's
    motion, so that its reference does not change (a spiral ignores its table)."""
    extra = num_segments - t.num_segments
    if extra < 0:
        raise ValueError(f"cannot shrink a track table of {t.num_segments} rows to {num_segments}")
    P, V, A = t.seg[-1, 0], t.seg[-1, 1], t.seg[-1, 2]
    tau = (jnp.arange(1, extra + 1) * t.seg_steps * dt)[:, None].astype(P.dtype)
    rows = jnp.stack([P + V * tau + 0.5 * A * tau * tau, V + A * tau, jnp.broadcast_to(A, (extra, 3))], 1)
    return t.replace(seg=jnp.concatenate([t.seg, rows]))


def stack(tracks: list[tr.Track], dt: float = 1e-3) -> tr.Track:
    """Tracks of any kinds and table sizes on one leading axis (tables :func:`pad`-ded to
    the largest)."""
    n = max(t.num_segments for t in tracks)
    return jax.tree.map(lambda *x: jnp.stack(x), *(pad(t, n, dt) for t in tracks))
