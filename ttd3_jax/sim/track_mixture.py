"""Which tracks an env of a config trains and is selected on: the paper's training mixture and
its 10 validation tracks, or, with ``tracks.wide_mix`` set, the wide mixture of
``sim.track_families`` and its validation bank.
"""

from __future__ import annotations

import jax

from ttd3_jax.sim import track_families as tf
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import EnvConfig


def mixture_num_segments(cfg: EnvConfig) -> int:
    """Track-table size of the training mixture and the validation tracks of ``cfg``: the paper
    mixture's, or the wide mixture's when ``tracks.wide_mix`` is set (users' tracks may need more)."""
    if cfg.tracks.wide_mix:
        return tf.wide_num_segments(cfg.horizon_steps, cfg.dt)
    return tr.train_num_segments(cfg.horizon_steps, cfg.dt)


def mixture_track(cfg: EnvConfig, rng: jax.Array, num_segments: int) -> tr.Track:
    """A track of the training mixture of ``cfg`` drawn from ``rng``: the paper's
    (``trajectories.sample_train_track``) or, with ``tracks.wide_mix`` set, the wide one
    (``track_families.sample_wide_track``)."""
    t = cfg.tracks
    if t.wide_mix:
        return tf.sample_wide_track(rng, t.wide_mix, cfg.dt, cfg.horizon_steps, num_segments, cfg=t.generator)
    return tr.sample_train_track(rng, t.generator, cfg.dt, cfg.horizon_steps, num_segments)


def validation_tracks(cfg: EnvConfig, num_segments: int | None = None) -> tr.Track:
    """The fixed validation tracks of ``cfg`` (batched; the only tracks a policy is selected
    on): the paper mixture's 10, or the wide mixture's (``track_families.wide_validation_tracks``,
    2 per family of positive weight) when ``tracks.wide_mix`` is set."""
    t, n = cfg.tracks, num_segments or mixture_num_segments(cfg)
    if t.wide_mix:
        return tf.wide_validation_tracks(t.wide_mix, cfg.dt, cfg.horizon_steps, n, cfg=t.generator)
    return tr.validation_tracks(t.generator, cfg.dt, cfg.horizon_steps, n)


def num_validation_tracks(cfg: EnvConfig) -> int:
    """How many tracks :func:`validation_tracks` holds."""
    if cfg.tracks.wide_mix:
        return len(tf.wide_validation_families(cfg.tracks.wide_mix))
    return tr.NUM_VALIDATION_TRACKS
