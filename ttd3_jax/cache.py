"""What a later launch of the same programs reuses: jax's persistent compilation cache (the
compiled XLA executables) and, beside it, the traced programs (:class:`StoredProgram`), so a
warm launch neither traces nor compiles.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import os
import pickle
import sys
import tempfile
import warnings
from collections.abc import Callable, Sequence

import jax
from jax import export as jax_export

COMPILE_CACHE_OFF = "none"


def default_compile_cache() -> str:
    """``$JAX_COMPILATION_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/ttd3_jax/xla``
    (``~/.cache/ttd3_jax/xla``)."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "ttd3_jax", "xla")


def use_compile_cache(path: str | None = None) -> str | None:
    """Turn on jax's persistent compilation cache in directory ``path`` for this process
    (``None``: :func:`default_compile_cache`; ``"none"``: off); returns the directory, or
    ``None`` when off.  An explicit ``path`` that cannot be created is a ``ValueError``; the
    default one only warns.  Cached executables are the compiled ones, so results do not
    change.  Call it before anything compiles (the CLI does: ``--compile-cache``)."""
    chosen = path is not None
    if path is None:
        path = default_compile_cache()
    if path.strip().lower() == COMPILE_CACHE_OFF:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    path = os.path.abspath(os.path.expanduser(path))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        if not chosen:  # the default place is not writable here: run without a cache
            print(
                f"warning: no XLA compilation cache ({path!r}: {e.strerror}); pass --compile-cache DIR",
                file=sys.stderr,
            )
            jax.config.update("jax_enable_compilation_cache", False)
            return None
        raise ValueError(
            f"compile cache directory {path!r} cannot be created ({e.strerror}); "
            f"pass --compile-cache DIR with a writable DIR, or --compile-cache {COMPILE_CACHE_OFF}"
        ) from e
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", path)
    return path


TRACED_SUBDIR = "traced"
_FORMAT = 1  # bump when the stored file's layout changes
_DEPENDENCIES = ("jax", "jaxlib", "numpy", "flax", "optax", "chex", "brax", "mujoco", "mujoco-mjx")


def program_store() -> str | None:
    """Where :class:`StoredProgram` keeps traced programs: ``traced/`` inside jax's compilation
    cache directory while that cache is on (:func:`use_compile_cache`), else ``None`` (also
    under ``jax.debug_key_reuse``, whose checks run while tracing)."""
    path = jax.config.jax_compilation_cache_dir
    if not (jax.config.jax_enable_compilation_cache and path) or jax.config.jax_debug_key_reuse:
        return None
    return os.path.join(path, TRACED_SUBDIR)


@functools.cache
def _source_digest() -> str:
    """sha256 of every ``.py`` file of the ttd3_jax package: any edit retraces."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for d, subdirs, files in os.walk(root):
        subdirs.sort()
        for f in sorted(files):
            if f.endswith(".py"):
                h.update(os.path.relpath(os.path.join(d, f), root).encode())
                with open(os.path.join(d, f), "rb") as fh:
                    h.update(fh.read())
    return h.hexdigest()


def _environment() -> str:
    """Everything outside the caller's context that changes what tracing produces: this
    package's source, the versions of what it traces through, jax's configuration, the
    device and ``XLA_FLAGS``."""
    versions = []
    for name in _DEPENDENCIES:
        try:
            versions.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{name}=-")
    config = sorted((k, repr(v)) for k, v in jax.config.values.items() if "_cache" not in k)
    dev = jax.devices()[0]
    return repr((_source_digest(), versions, config, dev.platform, dev.device_kind,
                 os.environ.get("XLA_FLAGS", "")))  # fmt: skip


class StoredProgram:
    """A jitted function whose traced program is kept on disk (StableHLO, via ``jax.export``),
    so that a later process with the same ``context``, arguments and environment skips tracing.

    ``lower(*args).compile()`` gives a callable with ``fn``'s signature, as ``fn.lower`` does;
    the first time it traces ``fn`` and stores the program in ``directory``.  Every launch runs
    the stored program, so the first launch's results are the later ones' bit for bit (and the
    same as ``fn``'s: ``tests/test_cache.py``).  ``context`` must name everything ``fn`` closes
    over (e.g. the run spec without its traced values); the key adds the arguments' tree and
    shapes, this package's source, its dependencies' versions, jax's configuration and the
    device.  ``fn`` must not call back to Python (``jax.debug.callback``): such programs cannot
    be stored.  A stored file that does not load is traced again and replaced, with a warning.
    ``donate_argnums`` as for ``jax.jit``."""

    def __init__(self, fn: Callable, name: str, context: str, directory: str,
                 donate_argnums: Sequence[int] = ()):  # fmt: skip
        self.fn, self.name, self.context, self.directory = fn, name, context, directory
        self.donate_argnums = tuple(donate_argnums)
        self._env = _environment()

    def path(self, args: tuple) -> str:
        """The file that holds the program for ``args``."""
        leaves, tree = jax.tree.flatten(args)
        avals = [str(jax.typeof(x)) for x in leaves]  # shape, dtype and weak type, e.g. "~float32[]"
        key = repr((_FORMAT, self.name, self.context, str(tree), avals, self._env))
        digest = hashlib.sha256(key.encode()).hexdigest()[:32]
        return os.path.join(self.directory, f"{self.name}-{digest}.bin")

    def _flat_donate(self, args: tuple) -> tuple[int, ...]:
        out, i = [], 0
        for k, a in enumerate(args):
            n = len(jax.tree.leaves(a))
            out += list(range(i, i + n)) if k in self.donate_argnums else []
            i += n
        return tuple(out)

    def _load(self, path: str):
        try:
            with open(path, "rb") as fh:
                rec = pickle.load(fh)
            return jax_export.deserialize(bytearray(rec["exported"])), rec["out_tree"]
        except FileNotFoundError:
            return None
        except Exception as e:  # noqa: BLE001 (a torn or foreign file: trace again)
            warnings.warn(f"stored program {path} does not load ({type(e).__name__}: {e}); tracing it again",
                          stacklevel=3)  # fmt: skip
            return None

    def _trace(self, args: tuple, path: str):
        leaves, in_tree = jax.tree.flatten(args)
        out_tree = []

        def flat(*xs):
            ys, tree = jax.tree.flatten(self.fn(*jax.tree.unflatten(in_tree, xs)))
            out_tree.append(tree)
            return ys

        exported = jax_export.export(jax.jit(flat))(*leaves)
        os.makedirs(self.directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-")
        with os.fdopen(fd, "wb") as fh:  # whole or not at all: concurrent launches may race
            pickle.dump({"exported": exported.serialize(), "out_tree": out_tree[0]}, fh)
        os.replace(tmp, path)
        return exported, out_tree[0]

    def _exported(self, args: tuple):
        path = self.path(args)
        return self._load(path) or self._trace(args, path)

    def lower(self, *args) -> _Lowered:
        """Load (or trace and store) the program for ``args`` and lower it."""
        exported, out_tree = self._exported(args)
        flat_fn = jax.jit(exported.call, donate_argnums=self._flat_donate(args))
        return _Lowered(flat_fn.lower(*jax.tree.leaves(args)), out_tree)

    def eval_shape(self, *args):
        """The outputs' shapes and dtypes, as ``jax.eval_shape``, from the stored program."""
        exported, out_tree = self._exported(args)
        outs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in exported.out_avals]
        return jax.tree.unflatten(out_tree, outs)


class _Lowered:
    def __init__(self, lowered, out_tree):
        self.lowered, self.out_tree = lowered, out_tree

    def compile(self) -> Callable:
        exe, tree = self.lowered.compile(), self.out_tree
        return lambda *args: jax.tree.unflatten(tree, exe(*jax.tree.leaves(args)))
