"""What a run will hold in memory, estimated from its spec before anything compiles or is
written: the replay buffers, the networks with their targets and Adam moments, the track
tables, the training envs' step, the scanned updates' working set and the model-based
rollout.  Each estimate names the run-spec fields that drive it; a refusal blames the one a
user set largest against its usual size (``--num-seeds 20000``, not the rollout's horizon).

The per-env constants were measured with XLA:CPU's ``memory_analysis()`` of the compiled
epoch and init programs (``python benchmarks/memory_calibration.py``; the ``practical`` env,
10 RK4 steps per action, jax 0.10.2): the model-based rollout keeps about 3.7 KB per env and
rollout step for its gradient, and one vectorised env step with its resets about 12 KB per env.
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
ROLLOUT_STEP_BYTES = 4096  # per env and rollout step kept for the model-based gradient (3.7 KB measured)
ENV_STEP_BYTES = 12 * 1024  # per training env: one vectorised step with its resets (12.3 KB measured)
# per evaluation flight (one track of 3000 steps, its closed loop and its per-step trace): the
# peak RSS of `python -m ttd3_jax.evaluate --controller hover --robustness --robustness-seeds N`
# grew by 390 KB per LOS-RT seed from N = 20 to N = 1000 (653 MB to 1,036 MB)
FLIGHT_BYTES = 400_000
# the size of each field a user sets, as the presets use it: a refusal blames the field that
# exceeds its usual size most
USUAL = {"num_seeds": 3, "num_envs": 64, "buffer_size": 1_000_000, "hidden": 256, "updates_per_step": 20,
         "model_horizon": 50, "task.episode_steps": 3000, "task.observation.lookahead_k": 50,
         "task.tracks.train_tracks": 1}  # fmt: skip


class Need(NamedTuple):
    what: str
    bytes: int
    fields: tuple[tuple[str, object, float], ...]  # (run-spec field, its value, its size) driving it

    @property
    def blamed(self) -> tuple[str, object]:
        """The driving field that exceeds its usual size (:data:`USUAL`) most, and its value."""
        name, value, size = max(self.fields, key=lambda f: f[2] / USUAL.get(f[0], 1))
        return name, value


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


def _track_rows_field(spec: sp.RunSpec, rows: int | None) -> tuple[str, object, float]:
    """The field that sets the track tables' rows, its value and its size."""
    t = spec.task
    if t.tracks.train_tracks and rows is not None and rows > mixture_num_segments(t):
        return "task.tracks.train_tracks", " ".join(t.tracks.train_tracks), rows / mixture_num_segments(t)
    if t.observation.lookahead_k > t.episode_steps:
        return "task.observation.lookahead_k", t.observation.lookahead_k, t.observation.lookahead_k
    return "task.episode_steps", t.episode_steps, t.episode_steps


def needs(spec: sp.RunSpec, obs_size: int, action_size: int, track_rows: int | None = None) -> list[Need]:
    """Every large allocation of ``spec``'s run, with the fields that drive it (``track_rows``:
    the env's track-table rows, see :func:`track_bytes`)."""
    c, n = spec.train, spec.num_seeds
    seeds, envs = ("num_seeds", n, n), ("num_envs", c.num_envs, c.num_envs)
    hidden = ("hidden", " ".join(map(str, c.hidden)), max(c.hidden))
    out = [
        Need("the replay buffers", sp.buffer_bytes(spec, obs_size, action_size),
             (seeds, ("buffer_size", c.buffer_size, c.buffer_size))),
        Need("the networks and optimiser state", network_bytes(spec, obs_size, action_size), (seeds, hidden)),
        Need("the scanned updates' working set", n * c.updates_per_step * PER_UPDATE_BYTES,
             (seeds, ("updates_per_step", c.updates_per_step, c.updates_per_step))),
        Need("the training envs' step", n * c.num_envs * (ENV_STEP_BYTES + 4 * F32 * obs_size),
             (seeds, envs)),
    ]  # fmt: skip
    if spec.is_quadrotor:
        out.append(Need("the track tables", track_bytes(spec, track_rows),
                        (seeds, envs, _track_rows_field(spec, track_rows))))  # fmt: skip
        per_step = ROLLOUT_STEP_BYTES + transition_bytes(obs_size, action_size)
        rollout = c.model_horizon * c.num_envs * per_step
        horizon = ("model_horizon", c.model_horizon, c.model_horizon)
        out.append(Need("the model-based rollout", n * rollout, (seeds, envs, horizon)))
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
        field, value = big.blamed
        raise ValueError(
            f"the run needs about {gib(total)} of memory, {gib(big.bytes)} of it for {big.what} (--"
            f"{field.replace('_', '-')} {value}), but only {gib(free)} is free; lower {field}"
        )
    return total


def check_flights(flights: int, flag: str, value: int, free: int | None = None) -> int:
    """Bytes of ``flights`` evaluation flights run in one batch; refuses (``ValueError``
    naming ``flag``) a batch that would take over ``FRACTION`` of free memory."""
    total = flights * FLIGHT_BYTES
    free = available_memory_bytes() if free is None else free
    if free is not None and total > FRACTION * free:
        most = max(1, int(FRACTION * free // FLIGHT_BYTES) - 1)
        raise ValueError(f"{flag} {value} needs about {gib(total)} of memory for its flights (one batch), "
                         f"but only {gib(free)} is free; {flag} {most} fits")  # fmt: skip
    return total
