"""What a later launch of the same programs reuses: jax's persistent compilation cache (the
compiled XLA executables) and, beside it, the traced programs (:class:`StoredProgram`), so a
warm launch neither traces nor compiles.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import logging
import os
import tempfile
import warnings
from collections.abc import Callable, Sequence

import jax
from jax import export as jax_export

logger = logging.getLogger(__name__)
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
            note = f"warning: no XLA compilation cache ({path!r}: {e.strerror}); pass --compile-cache DIR"
            logger.warning(note)
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
_MAGIC = b"ttd3-traced-program\n"  # a stored file: magic, header length (8 bytes), JSON header, program
_FORMAT = 2  # bump when the stored file's layout changes (1: a pickle, no longer read)
_DEPENDENCIES = (
    "jax",
    "jaxlib",
    "numpy",
    "flax",
    "optax",
    "chex",
    "brax",
    "mujoco",
    "mujoco-mjx",
    "flatbuffers",
)
# the modules whose types an output tree may name; any other type is not stored (nor imported)
_TREE_MODULES = ("builtins", "collections", "ttd3_jax", "flax", "optax", "brax", "jax", "chex")


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
    """sha256 of every file of the ttd3_jax package (not its caches): any edit retraces."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for d, subdirs, files in os.walk(root):
        subdirs[:] = sorted(x for x in subdirs if x != "__pycache__")
        for f in sorted(files):
            h.update(os.path.relpath(os.path.join(d, f), root).encode())
            with open(os.path.join(d, f), "rb") as fh:
                h.update(fh.read())
    return h.hexdigest()


def file_digests(obj) -> tuple[tuple[str, str], ...]:
    """``(path, sha256 of its contents)`` for every string in ``obj`` (dataclasses, tuples,
    lists and dicts, walked recursively) that names an existing file: the files a run spec
    makes the env read at construction (training-track CSVs), whose contents a traced program
    holds as constants.  Part of a stored program's key, so an edited file retraces."""
    found: dict[str, str] = {}

    def walk(x) -> None:
        if isinstance(x, str):
            if x and os.path.isfile(x) and x not in found:
                with open(x, "rb") as fh:
                    found[x] = hashlib.sha256(fh.read()).hexdigest()
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            for f in dataclasses.fields(x):
                walk(getattr(x, f.name))
        elif isinstance(x, list | tuple):
            for v in x:
                walk(v)
        elif isinstance(x, dict):
            for v in x.values():
                walk(v)

    walk(obj)
    return tuple(sorted(found.items()))


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


class _NotStorable(Exception):
    """A program or output tree that a stored file cannot hold."""


def _plain(x):
    """A pytree node's auxiliary data as JSON (``None``, numbers, strings, lists, tuples)."""
    if x is None or isinstance(x, bool | int | float | str):
        return x
    if isinstance(x, list | tuple):
        return {"list" if isinstance(x, list) else "tuple": [_plain(v) for v in x]}
    raise _NotStorable(f"auxiliary data of type {type(x).__name__}")


def _unplain(x):
    if isinstance(x, dict):
        ((kind, items),) = x.items()
        return (list if kind == "list" else tuple)(_unplain(v) for v in items)
    return x


def describe_tree(treedef) -> dict | None:
    """A plain (JSON) description of ``treedef``: each node's type by module and name, its
    auxiliary data and its children; ``None`` for a leaf.  :func:`rebuild_tree` inverts it."""
    node = treedef.node_data()
    if node is None:
        return None
    kind, aux = node
    module = kind.__module__
    if module.split(".")[0] not in _TREE_MODULES or "<" in kind.__qualname__:
        raise _NotStorable(f"a node of type {module}.{kind.__qualname__}")
    return {"type": f"{module}:{kind.__qualname__}", "aux": _plain(aux),
            "children": [describe_tree(c) for c in treedef.children()]}  # fmt: skip


def rebuild_tree(desc: dict | None):
    """The ``PyTreeDef`` that :func:`describe_tree` described; only types of the packages
    that trees are made of (``_TREE_MODULES``) are looked up."""
    if desc is None:
        return jax.tree.structure(0)
    module, name = desc["type"].split(":")
    if module.split(".")[0] not in _TREE_MODULES:
        raise ValueError(f"type {desc['type']!r} is outside {_TREE_MODULES}")
    kind = importlib.import_module(module)
    for part in name.split("."):
        kind = getattr(kind, part)
    children = [rebuild_tree(c) for c in desc["children"]]
    node = (kind, _unplain(desc["aux"]))
    return jax.tree_util.PyTreeDef.from_node_data_and_children(jax.tree_util.default_registry, node, children)


def write_program(path: str, exported_bytes: bytes, out_tree) -> None:
    """Store a serialised program and its output tree at ``path``, whole or not at all (a
    temporary file renamed into place: concurrent launches may race)."""
    header = json.dumps({"format": _FORMAT, "out_tree": describe_tree(out_tree),
                         "sha256": hashlib.sha256(exported_bytes).hexdigest()}).encode()  # fmt: skip
    directory = os.path.dirname(path)
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".tmp-")
    with os.fdopen(fd, "wb") as fh:
        fh.write(_MAGIC + len(header).to_bytes(8, "little") + header + exported_bytes)
    os.replace(tmp, path)


def read_program(path: str):
    """``(Exported, out_tree)`` from a file :func:`write_program` wrote; ``ValueError`` if it is
    anything else (another format, torn, edited), ``FileNotFoundError`` if there is none.
    No pickle: the program is checked against its digest before jax deserialises it."""
    with open(path, "rb") as fh:
        data = fh.read()
    if not data.startswith(_MAGIC):
        raise ValueError("not a stored program of this format")
    n = int.from_bytes(data[len(_MAGIC) : len(_MAGIC) + 8], "little")
    body = len(_MAGIC) + 8 + n
    header = json.loads(data[len(_MAGIC) + 8 : body].decode())
    program = data[body:]
    if header.get("format") != _FORMAT or header.get("sha256") != hashlib.sha256(program).hexdigest():
        raise ValueError("another format, or its program does not match its digest")
    exported = jax_export.deserialize(bytearray(program))
    out_tree = rebuild_tree(header["out_tree"])
    if out_tree.num_leaves != len(exported.out_avals):
        raise ValueError(
            f"its output tree has {out_tree.num_leaves} leaves, the program {len(exported.out_avals)}"
        )
    return exported, out_tree


class StoredProgram:
    """A jitted function whose traced program is kept on disk (StableHLO, via ``jax.export``),
    so that a later process with the same ``context``, arguments and environment skips tracing.

    ``lower(*args).compile()`` gives a callable with ``fn``'s signature, as ``fn.lower`` does;
    the first time it traces ``fn`` and stores the program in ``directory``.  Every launch runs
    the stored program, so the first launch's results are the later ones' bit for bit (and the
    same as ``fn``'s: ``tests/test_cache.py``).

    A stored program is used only if it provably is the one ``fn`` would trace now: its key is
    ``context`` (which must name everything ``fn`` closes over, e.g. the run spec without its
    traced values), the sha256 of every file that ``context_files`` names (:func:`file_digests`:
    the training-track CSVs the env bakes in), the arguments' tree and shapes, this package's
    source, its dependencies' versions, jax's configuration and the device.  A file is read
    without pickle (:func:`read_program`); one that does not parse or match its digest is traced
    again and replaced, with a warning.  A program that calls back to Python
    (``jax.debug.print``) cannot be stored: it runs as plain ``jax.jit`` with a one-line note.
    ``donate_argnums`` as for ``jax.jit``."""

    def __init__(self, fn: Callable, name: str, context: str, directory: str, *,
                 donate_argnums: Sequence[int] = (), context_files=()):  # fmt: skip
        self.fn, self.name, self.directory = fn, name, directory
        self.context = repr((context, file_digests(context_files)))
        self.donate_argnums = tuple(donate_argnums)
        self._env = _environment()
        self._plain_jit = False  # set when fn turns out not to be storable
        self._found = {}  # path: the program loaded or traced there (eval_shape, then lower, read once)

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
            return read_program(path)
        except FileNotFoundError:
            return None
        except Exception as e:  # noqa: BLE001 (a torn, edited or foreign file: trace again)
            warnings.warn(f"stored program {path} does not load ({type(e).__name__}: {e}); tracing it again",
                          stacklevel=3)  # fmt: skip
            return None

    def _trace(self, args: tuple, path: str):
        """Trace and store the program; ``None`` (and plain jit from now on) if it cannot be."""
        leaves, in_tree = jax.tree.flatten(args)
        out_tree = []

        def flat(*xs):
            ys, tree = jax.tree.flatten(self.fn(*jax.tree.unflatten(in_tree, xs)))
            out_tree.append(tree)
            return ys

        try:
            exported = jax_export.export(jax.jit(flat))(*leaves)
            write_program(path, exported.serialize(), out_tree[0])
        except (NotImplementedError, ImportError, _NotStorable) as e:  # e.g. jax.debug.print's callback
            note = f"note: the {self.name} program cannot be stored ({e}); it runs as plain jit"
            logger.warning(note)
            self._plain_jit = True
            return None
        return exported, out_tree[0]

    def _exported(self, args: tuple):
        if self._plain_jit:
            return None
        path = self.path(args)
        if path not in self._found:
            self._found[path] = self._load(path) or self._trace(args, path)
        return self._found[path]

    def lower(self, *args):
        """Load (or trace and store) the program for ``args`` and lower it."""
        found = self._exported(args)
        if found is None:
            return jax.jit(self.fn, donate_argnums=self.donate_argnums).lower(*args)
        exported, out_tree = found
        flat_fn = jax.jit(exported.call, donate_argnums=self._flat_donate(args))
        return _Lowered(flat_fn.lower(*jax.tree.leaves(args)), out_tree)

    def eval_shape(self, *args):
        """The outputs' shapes and dtypes, as ``jax.eval_shape``, from the stored program."""
        found = self._exported(args)
        if found is None:
            return jax.eval_shape(self.fn, *args)
        exported, out_tree = found
        outs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in exported.out_avals]
        return jax.tree.unflatten(out_tree, outs)


class _Lowered:
    def __init__(self, lowered, out_tree):
        self.lowered, self.out_tree = lowered, out_tree

    def compile(self) -> Callable:
        exe, tree = self.lowered.compile(), self.out_tree
        return lambda *args: jax.tree.unflatten(tree, exe(*jax.tree.leaves(args)))
