"""Spread seed / hyperparameter sweeps and parallel envs over all visible devices.

A vmapped sweep is parallel along its leading axis: on a ``(sweep, env)`` device mesh each
device runs its share of the seeds × hyperparameters with no communication, and each seed's
envs may be split over the ``env`` axis.  One device is the same code with nothing moved.
:func:`shard_vmapped` is ``jit(vmap(fn))`` with the mapped axis on ``sweep`` (a whole sweep
as one program); :func:`runner_fns` gives the runner's functions.  Multi-host sweeps: call
``jax.distributed.initialize()`` on every host first (docs/scaling.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

SWEEP, ENV = "sweep", "env"


def make_mesh(n_sweep: int | None = None, n_env: int = 1, devices: Sequence | None = None) -> Mesh:
    """A 2-D ``(sweep, env)`` mesh over ``devices`` (default: all visible devices).

    ``n_sweep`` defaults to ``len(devices) // n_env``; ``n_sweep * n_env`` devices are used."""
    devices = list(jax.devices() if devices is None else devices)
    if n_env < 1 or len(devices) % n_env:
        raise ValueError(f"n_env ({n_env}) must be >= 1 and divide the {len(devices)} devices")
    n_sweep = len(devices) // n_env if n_sweep is None else n_sweep
    if n_sweep < 1 or n_sweep * n_env > len(devices):
        need = n_sweep * n_env
        raise ValueError(f"a {n_sweep} x {n_env} mesh needs {need} devices; {len(devices)} visible")
    return Mesh(np.array(devices[: n_sweep * n_env]).reshape(n_sweep, n_env), (SWEEP, ENV))


def _leading_size(args, in_axes) -> int:
    sizes = []

    def look(ax, sub):
        if ax is None:
            return
        for x in jax.tree.leaves(sub):
            if jnp.ndim(x) == 0:
                raise ValueError("an argument mapped over axis 0 has a scalar leaf: nothing to map")
            sizes.append(jnp.shape(x)[ax])

    jax.tree.map(look, in_axes, args, is_leaf=lambda x: x is None)
    if not sizes:
        raise ValueError("in_axes maps no argument: nothing to shard")
    if len(set(sizes)) != 1:
        raise ValueError(f"mapped axes have different sizes {sorted(set(sizes))}")
    return sizes[0]


def _pad(x, axis: int, extra: int):
    """Repeat the last entry along ``axis`` ``extra`` times."""
    last = jax.lax.slice_in_dim(x, x.shape[axis] - 1, x.shape[axis], axis=axis)
    return jnp.concatenate([x, jnp.repeat(last, extra, axis=axis)], axis=axis)


def shard_vmapped(fn: Callable, in_axes: tuple, mesh: Mesh | None = None, pad: bool = False,
                  **jit_kw) -> Callable:  # fmt: skip
    """``jit(vmap(fn, in_axes))`` with the mapped axis split over the mesh's ``sweep`` axis;
    the results equal the unsharded ones.  ``in_axes`` entries (prefix trees, e.g. a ``Hyper``
    of 0 / None leaves) must be 0 or ``None``; unmapped arguments are replicated.  The mapped
    size must be a multiple of the sweep devices, or ``pad=True`` repeats its last entry and
    cuts the padding from the outputs (which are then gathered: return metrics, not states)."""
    if not isinstance(in_axes, tuple | list):
        raise ValueError(f"in_axes must be a tuple with one entry per argument, got {in_axes!r}")
    for ax in jax.tree.leaves(in_axes):
        if type(ax) is not int or ax != 0:
            raise ValueError(f"shard_vmapped supports in_axes entries 0 or None, got {ax!r}")
    mesh = make_mesh() if mesh is None else mesh
    n_dev = mesh.shape[SWEEP]
    vf = jax.jit(jax.vmap(fn, in_axes=tuple(in_axes)), out_shardings=NamedSharding(mesh, P(SWEEP)), **jit_kw)
    none = lambda x: x is None

    def call(*args):
        args = tuple(args)
        if len(args) != len(in_axes):
            raise ValueError(f"got {len(args)} arguments for {len(in_axes)} in_axes entries")
        n = _leading_size(args, tuple(in_axes))
        extra = -n % n_dev
        if extra and not pad:
            raise ValueError(
                f"the sweep has {n} entries, not a multiple of the {n_dev} devices on the mesh's "
                f"{SWEEP!r} axis; pass pad=True, or use a mesh with fewer devices (make_mesh(n_sweep=...))"
            )

        def place(ax, sub):
            if ax is None:
                return jax.device_put(sub, NamedSharding(mesh, P()))
            if extra:
                sub = jax.tree.map(lambda x: _pad(jnp.asarray(x), 0, extra), sub)
            return jax.tree.map(lambda x: jax.device_put(x, NamedSharding(mesh, P(SWEEP))), sub)

        out = vf(*jax.tree.map(place, tuple(in_axes), args, is_leaf=none))
        return jax.tree.map(lambda x: x[:n], out) if extra else out

    call.mesh = mesh
    return call


def seed_env_mesh(num_seeds: int, num_envs: int, devices: Sequence | None = None) -> Mesh:
    """The largest ``(sweep, env)`` mesh whose axes divide ``num_seeds`` and ``num_envs``:
    seeds are split first (no communication), then envs with the devices left over."""
    devices = list(jax.devices() if devices is None else devices)
    n = len(devices)
    n_sweep = max(d for d in range(1, n + 1) if n % d == 0 and num_seeds % d == 0)
    rest = n // n_sweep
    n_env = max(d for d in range(1, rest + 1) if rest % d == 0 and num_envs % d == 0)
    return make_mesh(n_sweep, n_env, devices)


def state_shardings(state, mesh: Mesh, num_envs: int):
    """Shardings for a train state with the seed axis in front: every leaf on ``sweep``
    along axis 0; leaves of ``env_state`` and ``ep_return`` also on ``env`` along axis 1."""
    n_env = mesh.shape[ENV]

    def leaf(x, env_axis: bool):
        shape = jnp.shape(x)
        if len(shape) == 0:
            return NamedSharding(mesh, P())
        if env_axis and len(shape) >= 2 and shape[1] == num_envs and num_envs % n_env == 0:
            return NamedSharding(mesh, P(SWEEP, ENV))
        return NamedSharding(mesh, P(SWEEP))

    env_like = {"env_state", "ep_return"}
    fields = {name: getattr(state, name) for name in state.__dataclass_fields__}
    out = {k: jax.tree.map(lambda x, e=(k in env_like): leaf(x, e), v) for k, v in fields.items()}
    return state.replace(**out)


def per_seed(fn: Callable, num_seeds: int, in_axes: tuple) -> Callable:
    """``fn`` mapped over the leading seed axis of the arguments marked 0 in ``in_axes``.  A
    single seed skips ``vmap`` (keeping the axis of length 1), so the trainer's ``lax.cond``
    branches stay branches instead of becoming selects that run both sides."""
    if num_seeds > 1:
        return jax.vmap(fn, in_axes=in_axes)

    def one(*args):
        first = [
            jax.tree.map(lambda x: x[0], a) if ax == 0 else a for a, ax in zip(args, in_axes, strict=True)
        ]
        return jax.tree.map(lambda x: x[None], fn(*first))

    return one


def runner_fns(trainer, keys: jax.Array, hp, mesh: Mesh | None = None):
    """``(init_fn, epoch_fn, eval_fn, place)`` for :func:`ttd3_jax.run.loop.run`: the trainer's
    functions over the seeds of ``keys`` (one per seed).  On one device: ``jit(per_seed(...))``,
    and ``place`` puts a restored (host) state on the device uncommitted, as a fresh one is (a
    committed state would lower to another program, missing the compilation cache).  On several
    devices (single process): seeds split over ``sweep``, envs over ``env``, and ``place`` puts a
    state on that mesh."""
    num_seeds, num_envs = keys.shape[0], trainer.config.num_envs
    mesh = seed_env_mesh(num_seeds, num_envs) if mesh is None else mesh
    if num_seeds % mesh.shape[SWEEP]:
        raise ValueError(
            f"num_seeds ({num_seeds}) must be a multiple of the mesh's {SWEEP!r} axis ({mesh.shape[SWEEP]})"
        )
    init = per_seed(trainer.init, num_seeds, (0, None))
    epoch = per_seed(trainer.epoch, num_seeds, (0, None))
    evaluate = per_seed(trainer.evaluate, num_seeds, (0,))
    if math.prod(mesh.devices.shape) == 1:
        return jax.jit(init), jax.jit(epoch, donate_argnums=0), jax.jit(evaluate), jax.device_put
    st = state_shardings(jax.eval_shape(init, keys, hp), mesh, num_envs)
    seeds, repl = NamedSharding(mesh, P(SWEEP)), NamedSharding(mesh, P())
    init_fn = jax.jit(init, in_shardings=(seeds, repl), out_shardings=st)
    epoch_fn = jax.jit(epoch, in_shardings=(st, repl), out_shardings=(st, seeds), donate_argnums=0)
    eval_fn = jax.jit(evaluate, in_shardings=(st,), out_shardings=seeds)
    return init_fn, epoch_fn, eval_fn, lambda ts: jax.device_put(ts, st)
