"""Checks the command lines share, made before anything loads or compiles: output paths
that can be written (each error names its flag), and true/false given to a switch."""

from __future__ import annotations

import dataclasses
import os
import tempfile
import typing

BOOL_WORDS = ("true", "false", "yes", "no", "on", "off", "1", "0")


def _nearest_existing(path: str) -> str:
    probe = os.path.abspath(path)
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    return probe


def writable_dir(flag: str, path: str, shown: str | None = None) -> None:
    """Refuse ``flag path`` unless ``path`` is, or can be made, a writable directory (its
    nearest existing ancestor is a directory that takes a file).  Creates nothing.  Messages
    quote ``shown`` (default ``path``), the value the user gave."""
    shown = path if shown is None else shown
    if not path:
        raise ValueError(f"{flag} must name a directory, got ''")
    probe = _nearest_existing(path)
    if not os.path.isdir(probe):
        raise ValueError(f"{flag} {shown!r}: {probe!r} is a file, not a directory")
    try:  # os.access says yes to root on read-only file systems (/sys, /proc): try a file
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as e:
        raise ValueError(
            f"{flag} {shown!r}: cannot write in {probe!r} ({e.strerror}); pass {flag} with a writable "
            "directory"
        ) from None


def writable_file(flag: str, path: str) -> None:
    """Refuse ``flag path`` unless ``path`` can be written as a file (not a directory, and
    in a directory that can be written or made)."""
    if not path:
        raise ValueError(f"{flag} must name a file, got ''")
    if os.path.isdir(path):
        raise ValueError(f"{flag} {path!r} is a directory; pass a file name")
    writable_dir(flag, os.path.dirname(os.path.abspath(path)), path)


def bool_flags(cls, prefix: str = "--", flat: tuple[str, ...] = ("train",)) -> set[str]:
    """The switches tyro makes of ``cls``'s bool fields (nested dataclasses as
    ``--group.field``; the groups in ``flat`` without their name, as RunSpec's ``train``)."""
    out, hints = set(), typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        kind, name = hints[f.name], f.name.replace("_", "-")
        if kind is bool:
            out.add(prefix + name)
        elif dataclasses.is_dataclass(kind):
            out |= bool_flags(kind, prefix if f.name in flat else f"{prefix}{name}.", ())
    return out


def refuse_bool_values(argv: list[str], switches: set[str]) -> None:
    """``--switch false`` (tyro would say "Unrecognized options: false"): refused with the
    spelling that works, ``--switch`` or ``--no-switch``."""
    for a, b in zip(argv, argv[1:], strict=False):
        if a in switches and b.lower() in BOOL_WORDS:
            head, _, last = a[2:].rpartition(".")
            off = f"--{head + '.' if head else ''}no-{last}"
            raise ValueError(f"{a} takes no value: write {a} for true or {off} for false (got {a} {b})")
