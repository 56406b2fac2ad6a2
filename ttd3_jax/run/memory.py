"""What a run will hold in memory, estimated from its spec before anything compiles or is
written: the replay buffers, the networks with their targets and Adam moments, the track
tables, the scanned updates' working set and the model-based rollout.  Each estimate
names the run-spec field that drives it, so a refusal can say what to lower.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import jax

from ttd3_jax.run import spec as sp
from ttd3_jax.sim.env import mixture_num_segments, num_validation_tracks
from ttd3_jax.td3.buffer import transition_bytes

FRACTION = 0.7  # of the free memory a run may plan to use
F32 = 4
NETWORK_COPIES = 4  # parameters, targets, Adam's two moments
TRACK_ROW_BYTES = 9 * F32  # one segment row: position, velocity, acceleration (3 each)
PER_UPDATE_BYTES = 3 * F32 + 2 * 4  # per scanned update: its 3 metrics and its PRNG key
ROLLOUT_STATE_BYTES = 64 * F32  # per env and rollout step kept for the model-based gradient


class Need(NamedTuple):
    what: str
    bytes: int
    field: str  # the run-spec field that drives it
    value: object  # that field's value


def available_memory_bytes() -> int | None:
    """Free memory of the default device (GPU) or of the host (CPU), if known."""
    dev = jax.devices()[0]
    if dev.platform != "cpu":
        stats = dev.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def mlp_params(sizes: list[int]) -> int:
    """Weights and biases of a dense network with layer widths ``sizes`` (input first)."""
    return sum(i * o + o for i, o in zip(sizes, sizes[1:], strict=False))


def network_bytes(spec: sp.RunSpec, obs_size: int, action_size: int) -> int:
    """Actor and twin critics with their targets and Adam moments, plus one minibatch's
    activations and gradients, for every seed."""
    c, hidden = spec.train, list(spec.train.hidden)
    params = mlp_params([obs_size, *hidden, action_size]) + 2 * mlp_params(
        [obs_size + action_size, *hidden, 1]
    )
    activations = 3 * 2 * c.batch_size * sum(hidden)  # actor and two critics, forward and backward
    return spec.num_seeds * F32 * (NETWORK_COPIES * params + 2 * params + activations)


def track_bytes(spec: sp.RunSpec, rows: int | None = None) -> int:
    """The track tables: one per training env, the users' training tracks, the validation and
    test tracks, each of ``rows`` rows (the env's ``num_segments``, which a long user track
    grows; None: the training mixture's)."""
    t = spec.task
    rows = mixture_num_segments(t) if rows is None else rows
    tracks = spec.train.num_envs + len(t.tracks.train_tracks) + num_validation_tracks(t) + 2
    return spec.num_seeds * tracks * rows * TRACK_ROW_BYTES


def _track_field(spec: sp.RunSpec, rows: int | None) -> tuple[str, object]:
    """The field that sets the track tables' size, and its value."""
    t = spec.task
    if t.tracks.train_tracks and rows is not None and rows > mixture_num_segments(t):
        return "task.tracks.train_tracks", " ".join(t.tracks.train_tracks)
    if t.observation.lookahead_k > t.episode_steps:
        return "task.observation.lookahead_k", t.observation.lookahead_k
    return "task.episode_steps", t.episode_steps


def needs(spec: sp.RunSpec, obs_size: int, action_size: int, track_rows: int | None = None) -> list[Need]:
    """Every large allocation of ``spec``'s run, with the field that drives it (``track_rows``:
    the env's track-table rows, see :func:`track_bytes`)."""
    c = spec.train
    out = [
        Need("the replay buffers", sp.buffer_bytes(spec, obs_size, action_size), "buffer_size",
             c.buffer_size),
        Need("the networks and optimiser state", network_bytes(spec, obs_size, action_size), "hidden",
             " ".join(map(str, c.hidden))),
        Need("the scanned updates' working set", spec.num_seeds * c.updates_per_step * PER_UPDATE_BYTES,
             "updates_per_step", c.updates_per_step),
    ]  # fmt: skip
    if spec.is_quadrotor:
        out.append(Need("the track tables", track_bytes(spec, track_rows), *_track_field(spec, track_rows)))
        rollout = (
            c.model_horizon * c.num_envs * (ROLLOUT_STATE_BYTES + transition_bytes(obs_size, action_size))
        )
        out.append(
            Need("the model-based rollout", spec.num_seeds * rollout, "model_horizon", c.model_horizon)
        )
    return out


def gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check(spec: sp.RunSpec, obs_size: int, action_size: int, free: int | None = None,
          track_rows: int | None = None) -> int:  # fmt: skip
    """Total bytes of :func:`needs`; refuses (``ValueError``, with the figure and the field
    that drives the largest part) a run that would take over ``FRACTION`` of free memory."""
    parts = needs(spec, obs_size, action_size, track_rows)
    total = sum(p.bytes for p in parts)
    free = available_memory_bytes() if free is None else free
    if free is not None and total > FRACTION * free:
        big = max(parts, key=lambda p: p.bytes)
        raise ValueError(
            f"the run needs about {gib(total)} of memory, {gib(big.bytes)} of it for {big.what} (--"
            f"{big.field.replace('_', '-')} {big.value}), but only {gib(free)} is free; lower {big.field}"
            f"{' or num_seeds' * (spec.num_seeds > 1)}"
        )
    return total
