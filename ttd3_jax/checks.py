"""Checks of user input, made before anything loads or compiles.  Configuration values, shared
by every config (``EnvConfig``, ``TrainConfig``, ``Hyper``, ``RunSpec``, ``QuadParams``, the
NMPC's): each raises ``ValueError`` with one message shape, "<field> must be <what is
allowed>, got <value>".  And what the command lines share: output paths that can be written
(each error names its flag), and true/false given to a switch.

Layer 0: imports nothing of the package, so the trainer, the simulator and the application
can all use it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import typing
from collections.abc import Iterable
from typing import NoReturn


def fail(field: str, allowed: str, value) -> NoReturn:
    raise ValueError(f"{field} must be {allowed}, got {shown(value)}")


def shown(value, limit: int = 200) -> str:
    """``repr(value)``, cut to about ``limit`` characters (a 2,000-value list stays one line)."""
    text = repr(value)
    if len(text) <= limit:
        return text
    count = f", {len(value):,} values" if isinstance(value, tuple | list) else ""
    return f"{text[: limit - 40]}... ({len(text):,} characters{count})"


def is_integer(v) -> bool:
    """An ``int`` that is not a ``bool`` (JSON and the command line tell them apart)."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_number(v) -> bool:
    """A finite ``int`` or ``float`` that is not a ``bool``."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def integer(field: str, v, lo: int, hi: int | None = None, unit: str = "") -> int:
    """``v`` as an integer in [lo, hi] (``hi=None``: no upper bound)."""
    if not is_integer(v) or v < lo or (hi is not None and v > hi):
        fail(
            field, f"an integer >= {lo:,}{unit}" if hi is None else f"an integer in [{lo:,}, {hi:,}]{unit}", v
        )
    return v


def interval(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    """``(0, 1]``-style text of a range; ``None`` ends are unbounded."""
    if hi is None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if lo is None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def number(field: str, v, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, unit: str = "") -> float:  # fmt: skip
    """``v`` as a finite number in the range the bounds give (``None``: unbounded)."""
    ok = is_number(v)
    ok = (
        ok
        and (lo is None or (v > lo if lo_open else v >= lo))
        and (hi is None or (v < hi if hi_open else v <= hi))
    )
    if not ok:
        bounds = "" if lo is None and hi is None else " " + interval(lo, hi, lo_open, hi_open)
        fail(field, f"a finite number{bounds}{unit}", v)
    return v


def one_of(field: str, v, allowed: Iterable) -> None:
    allowed = tuple(allowed)
    if isinstance(v, bool) or v not in allowed:
        fail(field, f"one of {allowed}", v)


def boolean(field: str, v) -> None:
    if not isinstance(v, bool):
        fail(field, "true or false", v)


def instance(field: str, v, kind: type) -> None:
    if not isinstance(v, kind):
        raise ValueError(f"{field} must be a {kind.__name__}, got {type(v).__name__}")


# -- the command lines' checks -------------------------------------------------------------

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
