"""Orbax checkpoints of the whole training state (optimiser state, buffer and key included).

Saves are synchronous and atomic (orbax writes a temporary directory and renames
it), so a run killed at any point keeps its last complete checkpoint.
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

# Orbax refuses zero-size arrays (MJX states carry some, e.g. ``act`` for models without
# actuator state): they are stored as a 1-element placeholder and rebuilt on restore.


def _empty(x) -> bool:
    return math.prod(x.shape) == 0


def _pack(tree):
    return jax.tree.map(lambda x: jnp.zeros((1,), x.dtype) if _empty(x) else x, tree)


def manager(run_dir: str, max_to_keep: int = 2) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=False, cleanup_tmp_directories=True
    )
    return ocp.CheckpointManager(os.path.abspath(os.path.join(run_dir, "checkpoints")), options=options)


def save(mngr: ocp.CheckpointManager, epoch: int, state) -> None:
    """Save ``state`` as checkpoint ``epoch`` (epochs completed) and wait for it."""
    mngr.save(epoch, args=ocp.args.StandardSave(_pack(state)), force=True)
    mngr.wait_until_finished()


def latest_epoch(mngr: ocp.CheckpointManager) -> int | None:
    return mngr.latest_step()


def restore(mngr: ocp.CheckpointManager, epoch: int, like):
    """Restore checkpoint ``epoch`` into the structure, shapes and dtypes of ``like``."""
    abstract = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((1,), x.dtype) if _empty(x) else ocp.utils.to_shape_dtype_struct(x),
        like,
    )
    out = mngr.restore(epoch, args=ocp.args.StandardRestore(abstract))
    return jax.tree.map(lambda o, x: jnp.zeros(x.shape, x.dtype) if _empty(x) else o, out, like)
