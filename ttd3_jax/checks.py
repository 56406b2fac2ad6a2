"""Checks of configuration values, shared by every config (``EnvConfig``, ``TrainConfig``,
``Hyper``, ``RunSpec``, ``QuadParams``, the NMPC's): each raises ``ValueError`` with one message
shape, "<field> must be <what is allowed>, got <value>", before anything compiles.

Layer 0: imports nothing of the package, so the trainer, the simulator and the application
can all use it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import NoReturn


def fail(field: str, allowed: str, value) -> NoReturn:
    raise ValueError(f"{field} must be {allowed}, got {value!r}")


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
