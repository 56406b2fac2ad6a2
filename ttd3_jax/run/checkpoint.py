"""Orbax checkpoints of the whole training state (optimiser state, buffer and key included).

Saves are atomic (orbax writes a temporary directory and renames it), so a run killed at
any point keeps its last complete checkpoint.  Each checkpoint is verified twice on restore:
the digest of its contents (written before the save, :data:`DIGESTS`) and the sha256 of every
file under ``checkpoints/<epoch>/`` (written once orbax has finalised the save, :data:`FILES`),
so damage anywhere in its files, metadata included, is reported.  A manager made with ``asynchronous=True``
(the trainer's, saving with ``wait=False``) copies the state to host memory and writes it in a
background thread while training goes on; the next save, :func:`finish` and
:func:`latest_epoch` wait for it.

orbax is imported inside the functions that use it, not with this module: its import (with
tensorstore) takes a few tenths of a second that importing the trainer, the CLI's argument
checks and a run's memory check need not wait for.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import threading
import time
import weakref
from typing import TYPE_CHECKING

import jax
import numpy as np
from flax import serialization

if TYPE_CHECKING:
    import orbax.checkpoint as ocp

# Orbax refuses zero-size arrays (MJX states carry some, e.g. ``act`` for models without
# actuator state): they are stored as a 1-element placeholder and rebuilt on restore.

logger = logging.getLogger(__name__)
DIGESTS = "checkpoint_digests.json"  # in the run directory: {epoch: digest of the saved state}
FILES = "checkpoint_files.json"  # in the run directory: {epoch: {file under checkpoints/<epoch>/: sha256}}


def _empty(x) -> bool:
    return math.prod(x.shape) == 0


def _pack(tree):
    """Empty leaves as one zero each (put on the device, so that nothing compiles)."""
    return jax.tree.map(lambda x: jax.device_put(np.zeros((1,), x.dtype)) if _empty(x) else x, tree)


def manager(run_dir: str, max_to_keep: int = 2, asynchronous: bool = False,
            read_only: bool = False) -> ocp.CheckpointManager:  # fmt: skip
    """The checkpoints of ``run_dir`` (``run_dir/checkpoints``), the newest ``max_to_keep``
    kept; ``asynchronous``: saves return once the state is copied, then write in the
    background.  ``read_only`` (evaluation, export): nothing under ``checkpoints/`` is
    created, cleaned or deleted (a writer's manager removes unfinished ``*-tmp`` saves when
    it opens, which would delete the save a running trainer is writing)."""
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=asynchronous,
        cleanup_tmp_directories=not read_only, read_only=read_only, create=not read_only,
    )  # fmt: skip
    return ocp.CheckpointManager(os.path.abspath(os.path.join(run_dir, "checkpoints")), options=options)


def digest(tree) -> str:
    """A hash of a pytree of host arrays: every leaf's dtype, shape and bytes, in tree order."""
    h = hashlib.blake2b(digest_size=16)
    for x in jax.tree.leaves(tree):
        a = np.ascontiguousarray(np.asarray(x))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.view(np.uint8).reshape(-1).data if a.size else b"")
    return h.hexdigest()


def _run_dir(mngr: ocp.CheckpointManager) -> str:
    return os.path.dirname(str(mngr.directory))


def _read_record(run_dir_or_mngr, name: str) -> dict | None:
    """``{epoch: entry}`` of record ``name`` in the run directory: empty when missing, ``None``
    when the file does not read as a record (damaged)."""
    is_dir = isinstance(run_dir_or_mngr, str | os.PathLike)
    run_dir = run_dir_or_mngr if is_dir else _run_dir(run_dir_or_mngr)
    try:
        with open(os.path.join(run_dir, name)) as fh:
            return {int(k): v for k, v in json.load(fh).items()}
    except FileNotFoundError:
        return {}
    except (ValueError, AttributeError):
        return None


def _record(run_dir_or_mngr, name: str) -> dict:
    """:func:`_read_record`, with a damaged record read as empty: it verifies nothing, and every
    checkpoint then loads unverified."""
    return _read_record(run_dir_or_mngr, name) or {}


def _record_damaged(run_dir: str, name: str) -> bool:
    return _read_record(run_dir, name) is None


def _write_record(run_dir: str, name: str, record: dict) -> None:
    _atomic_write(os.path.join(run_dir, name), json.dumps({str(k): v for k, v in sorted(record.items())}))


def digests(run_dir_or_mngr) -> dict[int, str]:
    """``{epoch: digest}`` of a run's checkpoints (empty for runs saved before digests)."""
    return _record(run_dir_or_mngr, DIGESTS)


def file_digests(run_dir_or_mngr) -> dict[int, dict[str, str]]:
    """``{epoch: {path under checkpoints/<epoch>/: sha256}}`` of a run's finalised checkpoints."""
    return _record(run_dir_or_mngr, FILES)


def hash_files(folder: str) -> dict[str, str]:
    """``{path relative to folder: sha256}`` of every file under ``folder``."""
    out = {}
    for d, _, names in os.walk(folder):
        for name in names:
            path, h = os.path.join(d, name), hashlib.sha256()
            with open(path, "rb") as fh:
                for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    h.update(block)
            out[os.path.relpath(path, folder)] = h.hexdigest()
    return dict(sorted(out.items()))


def _saved_steps(mngr: ocp.CheckpointManager) -> set[int]:
    folder = str(mngr.directory)
    return {int(n) for n in os.listdir(folder) if n.isdigit()} if os.path.isdir(folder) else set()


def _record_files(mngr: ocp.CheckpointManager, epoch: int) -> None:
    """Add checkpoint ``epoch``'s file hashes to :data:`FILES` (if it was saved), keeping
    only the checkpoints still on disk."""
    folder = os.path.join(str(mngr.directory), str(epoch))
    if not os.path.isdir(folder):  # the save failed: its error is raised by the manager's wait
        return
    kept = _saved_steps(mngr)
    record = {e: f for e, f in file_digests(mngr).items() if e in kept}
    record[epoch] = hash_files(folder)
    _write_record(_run_dir(mngr), FILES, record)


class _Recorder(threading.Thread):
    """Writes the file hashes of an asynchronous save once orbax has finalised it (renamed
    its directory and removed the checkpoints past ``max_to_keep``), while training goes on."""

    def __init__(self, mngr: ocp.CheckpointManager, epoch: int):
        super().__init__(name=f"ttd3-checkpoint-files-{epoch}", daemon=True)
        self.mngr, self.epoch, self.error = mngr, epoch, None

    def run(self) -> None:
        try:
            while self.mngr.is_saving_in_progress():  # orbax's finalisation runs in its own thread
                time.sleep(0.02)
            _record_files(self.mngr, self.epoch)
        except Exception as e:  # e.g. a full disk: raised by the next wait (:func:`_settle`)
            self.error = e


_recorders: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # manager -> its _Recorder


def _settle(mngr: ocp.CheckpointManager) -> None:
    """Wait for ``mngr``'s save in flight and for its file hashes (raising what failed)."""
    recorder = _recorders.pop(mngr, None)
    try:
        mngr.wait_until_finished()
    finally:
        if recorder is not None:
            recorder.join()
    if recorder is not None and recorder.error is not None:
        raise recorder.error


def save(mngr: ocp.CheckpointManager, epoch: int, state, wait: bool = True) -> None:
    """Save ``state`` as checkpoint ``epoch`` (epochs completed): its content digest is
    recorded first (:data:`DIGESTS`), its files' hashes once orbax has finalised it
    (:data:`FILES`); both are checked on restore.  ``wait``: return once it is on disk.
    Otherwise (with an ``asynchronous`` manager) return once ``state`` is copied to host
    memory: a private copy, so the caller may donate ``state`` right away."""
    import orbax.checkpoint as ocp

    host = _pack(jax.tree.map(np.array, jax.device_get(state)))  # np.array copies
    _settle(mngr)  # the previous save (orbax waits for it here anyway) and its file hashes
    kept, run_dir = _saved_steps(mngr) | {epoch}, _run_dir(mngr)
    record = {e: d for e, d in digests(mngr).items() if e in kept}
    record[epoch] = digest(host)
    _write_record(run_dir, DIGESTS, record)
    files = file_digests(mngr)
    if epoch in files:  # a checkpoint of this epoch deleted earlier (resume): its hashes go
        _write_record(run_dir, FILES, {e: f for e, f in files.items() if e in kept and e != epoch})
    mngr.save(epoch, args=ocp.args.StandardSave(host), force=True)
    _recorders[mngr] = recorder = _Recorder(mngr, epoch)
    recorder.start()
    if wait:
        _settle(mngr)


def finish(mngr: ocp.CheckpointManager) -> None:
    """Wait until every save of ``mngr`` is on disk, with its file hashes."""
    _settle(mngr)


def close(mngr: ocp.CheckpointManager) -> None:
    """Wait for ``mngr``'s saves, then shut its background threads down (left running, they
    print tracebacks when the interpreter exits)."""
    try:
        _settle(mngr)
    finally:
        mngr.close()


def latest_epoch(mngr: ocp.CheckpointManager) -> int | None:
    """The newest checkpoint on disk (a save still being written is waited for)."""
    _settle(mngr)
    return mngr.latest_step()


class CorruptCheckpoint(ValueError):
    """A checkpoint or selected policy whose contents differ from the digest written with it."""


def check_files(mngr: ocp.CheckpointManager, epoch: int) -> bool:
    """Compare checkpoint ``epoch``'s files with the hashes recorded when it was saved:
    ``False`` when none were recorded; raises :class:`CorruptCheckpoint` naming the first
    file that changed, went missing or appeared."""
    expected = file_digests(mngr).get(epoch)
    if expected is None:
        return False
    found = hash_files(os.path.join(str(mngr.directory), str(epoch)))
    for path in sorted(set(expected) | set(found)):
        if expected.get(path) != found.get(path):
            how = (
                "is missing"
                if path not in found
                else "is not one of its files"
                if path not in expected
                else "changed"
            )
            raise CorruptCheckpoint(f"its file {path} {how} since it was saved ({FILES})")
    return True


def restore(mngr: ocp.CheckpointManager, epoch: int, like):
    """Restore checkpoint ``epoch`` into the structure, shapes and dtypes of ``like``, as
    host (numpy) arrays: the caller places them (``jax.device_put``, or onto a mesh).
    Raises :class:`CorruptCheckpoint` when its files differ from the hashes recorded when it
    was saved, or its contents from their recorded digest."""
    import orbax.checkpoint as ocp

    check_files(mngr, epoch)
    abstract = jax.tree.map(lambda x: np.zeros((1,) if _empty(x) else x.shape, x.dtype), like)
    out = mngr.restore(epoch, args=ocp.args.StandardRestore(abstract))
    check_shapes(out, abstract, f"checkpoint {epoch}")
    expected = digests(mngr).get(epoch)
    if expected is not None and digest(out) != expected:
        raise CorruptCheckpoint(f"its contents do not match the digest written with it ({DIGESTS})")
    return jax.tree.map(lambda o, x: np.zeros(x.shape, x.dtype) if _empty(x) else o, out, like)


TRACK_TABLE = ("env_state", "pipeline_state", "track", "seg")  # the training envs' track tables


def saved_track_rows(run_dir: str, epoch: int | None = None) -> int | None:
    """The rows of the training envs' track tables (:data:`TRACK_TABLE`, its third axis from
    the end) in checkpoint ``epoch`` of ``run_dir`` (default: the newest whose metadata reads),
    from orbax's metadata alone; ``None`` when none reads."""
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(read_only=True, create=False)
    folder = os.path.abspath(os.path.join(run_dir, "checkpoints"))
    with _orbax_quiet():
        mngr = ocp.CheckpointManager(folder, options=options, item_handlers=ocp.StandardCheckpointHandler())
        try:
            for e in sorted(mngr.all_steps(), reverse=True) if epoch is None else [epoch]:
                try:  # orbax raises many kinds for a damaged checkpoint
                    meta = mngr.item_metadata(e)
                    for key in TRACK_TABLE:
                        meta = meta[key]
                    return int(meta.shape[-3])
                except Exception:
                    continue
        finally:
            mngr.close()
    return None


_EDITED = "config.json does not describe this run (was it edited?); put back the one it was trained with"


class SpecMismatch(ValueError):
    """A saved state whose shapes are not those its run's ``config.json`` gives: the file was
    edited (or belongs to another run); no older checkpoint would load either."""


def check_shapes(saved, like, what: str) -> None:
    """Refuse (:class:`SpecMismatch`) ``saved`` arrays whose shapes differ from ``like``'s,
    naming the first leaf that differs."""
    got = jax.tree_util.tree_flatten_with_path(saved)[0]
    want = jax.tree_util.tree_leaves(like)
    for (path, a), b in zip(got, want, strict=False):
        if np.shape(a) != np.shape(b):
            name = jax.tree_util.keystr(path)
            raise SpecMismatch(f"{what} holds {name} of shape {np.shape(a)}, but config.json gives "
                               f"{np.shape(b)}: {_EDITED}")  # fmt: skip
    if len(got) != len(want):
        raise SpecMismatch(f"{what} holds {len(got)} arrays, but config.json gives {len(want)}: {_EDITED}")


def _reason(e: Exception) -> str:
    """An exception as one short line (orbax and tensorstore errors run to many lines)."""
    text = " ".join(str(e).split()) or type(e).__name__
    return f"{type(e).__name__}: {text[:160]}{'...' if len(text) > 160 else ''}"


def _note(message: str) -> None:
    logger.warning(f"note: {message}")


@contextlib.contextmanager
def _orbax_quiet():
    """orbax logs (absl, ERROR) each damaged file it meets, e.g. a step's metadata while
    listing the steps; the fallback says what did not load, in one line."""
    absl = logging.getLogger("absl")
    level = absl.level
    absl.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        absl.setLevel(level)


def restore_newest(run_dir: str, like, epoch: int | None = None, note=_note):
    """The newest checkpoint of ``run_dir`` that loads (or checkpoint ``epoch``):
    ``(epoch, state, skipped)``, where ``skipped`` lists ``(epoch, reason)`` of newer
    checkpoints that did not load (corrupt, half deleted, or files that differ from their
    hashes).  Raises ``FileNotFoundError`` when none loads.

    A checkpoint with a content digest but no file hashes (the process was killed between
    orbax finalising the save and the hashes being written) loads when its contents match
    the digest, and ``note`` says so: the state restored is then bit for bit the one saved,
    so the run continues exactly; only damage that changes no restored value would go
    unreported."""
    with _orbax_quiet():
        return _restore_newest(run_dir, like, epoch, note)


def _restore_newest(run_dir: str, like, epoch: int | None, note):
    mngr = manager(run_dir, read_only=True)
    try:
        saved = sorted(mngr.all_steps(), reverse=True)
    finally:
        mngr.close()
    if epoch is not None:
        if epoch not in saved:
            raise FileNotFoundError(f"no checkpoint {epoch} in {mngr.directory}; saved: {sorted(saved)}")
        saved = [epoch]
    skipped = []
    for e in saved:
        m = manager(
            run_dir, read_only=True
        )  # a fresh manager each time: orbax's is not usable after a failure
        try:
            state = restore(m, e, like)
        except SpecMismatch:  # not damage: every checkpoint was saved with the run's real config
            raise
        except Exception as err:  # orbax raises many kinds (ValueError, OSError, KeyError, ...)
            skipped.append((e, _reason(err)))
            continue
        finally:
            m.close()
        if e not in file_digests(run_dir) and e in digests(run_dir):
            damaged = _record_damaged(run_dir, FILES)
            why = f"{FILES} is damaged" if damaged else f"{FILES}; the run stopped before they were written"
            note(f"checkpoint {e} has no file hashes ({why}); its contents match their digest, so it is "
                 "loaded")  # fmt: skip
        return e, state, skipped
    why = "; ".join(f"epoch {e}: {r}" for e, r in skipped) or "none saved"
    raise FileNotFoundError(f"no checkpoint in {mngr.directory} loads ({why})")


# --------------------------------------------------------------------------- selected policy
# The policy chosen on the validation tracks (spec T8) is kept apart from the rolling train-
# state checkpoints (which keep only the last two epochs): per seed, the actor parameters
# and observation statistics as flax msgpack, plus ``best/best.json`` with its epoch and
# validation error.  Writes are atomic (temporary file, then rename).
# Hand-written, not orbax's ``best_fn``: that ranks whole steps by one scalar, while each vmapped
# seed keeps its own best epoch, skips non-finite errors and keeps the earlier epoch on a tie.


def _atomic_write(path: str, data: bytes | str) -> None:
    tmp = path + ".tmp"
    with open(tmp, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)
    os.replace(tmp, path)


def _bytes_digest(data: bytes) -> str:
    return hashlib.blake2b(data, digest_size=16).hexdigest()


def best_record(run_dir: str) -> dict[int, dict]:
    """``{seed: {"epoch": e, "val_tracking_error": v}}`` of the saved selected policies."""
    path = os.path.join(run_dir, "best", "best.json")
    if not os.path.exists(path):
        return {}
    try:
        with open(path) as fh:
            return {int(k): v for k, v in json.load(fh).items()}
    except (ValueError, AttributeError) as e:
        raise ValueError(f"{path} is not a valid record of selected policies ({_reason(e)})") from None


def save_policy(run_dir: str, seed: int, epoch: int, value: float, policy) -> None:
    """Store ``policy`` (a pytree: actor parameters, observation statistics) as seed
    ``seed``'s selected policy, chosen at ``epoch`` with validation error ``value``."""
    folder = os.path.join(run_dir, "best")
    os.makedirs(folder, exist_ok=True)
    data = serialization.to_bytes(jax.device_get(policy))
    _atomic_write(os.path.join(folder, f"seed{seed}.msgpack"), data)
    record = best_record(run_dir)
    record[seed] = {"epoch": int(epoch), "val_tracking_error": float(value), "digest": _bytes_digest(data)}
    _atomic_write(
        os.path.join(folder, "best.json"), json.dumps({str(k): v for k, v in sorted(record.items())})
    )


def load_policy(run_dir: str, seed: int, like):
    """Seed ``seed``'s selected policy, restored into the structure of ``like``."""
    path = os.path.join(run_dir, "best", f"seed{seed}.msgpack")
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"no selected policy for seed {seed} in {run_dir!r} (best/ is written by quadrotor runs)"
        )
    with open(path, "rb") as fh:
        data = fh.read()
    expected = best_record(run_dir).get(seed, {}).get("digest")
    if expected is not None and _bytes_digest(data) != expected:
        raise CorruptCheckpoint(f"{path} does not match the digest in best/best.json (the file is damaged)")
    try:
        out = serialization.from_bytes(like, data)
    except Exception as e:
        raise ValueError(f"{path} does not load ({_reason(e)})") from None
    check_shapes(out, like, path)
    return out
