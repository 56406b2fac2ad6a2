"""jax's persistent compilation cache for the CLI: a later launch of the same programs
loads the compiled XLA executables instead of compiling them again.
"""

from __future__ import annotations

import os
import sys

import jax

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
