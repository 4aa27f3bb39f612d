"""Range rules of numeric options, declared where the option is (a config dataclass field).

A field carries its rule in its metadata (``field(metadata=rule(ge=1))``, or the ``rule=`` argument of
:func:`sdp_cli.policy.config.opt`); :func:`check_fields` checks every field of a config object against its
rule, so that a flag of ``sdp train``/``sdp loop``, a key of an experiment file and a config built in Python
obey the same rule and get the same one-line error naming the option. Every number must be finite (``nan``
and ``inf`` are refused by every rule); a list is checked item by item; ``None`` passes (an optional option
left at its default). Options that no config declares (``sdp plot-dataset --dpi``) call :func:`check_value`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from sdp_cli.errors import SdpError


@dataclass(frozen=True)
class Range:
    """``ge``/``gt`` (lower bound, closed/open), ``le``/``lt`` (upper), ``odd`` (an odd integer)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    odd: bool = False

    def ok(self, v) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return False
        return ((self.ge is None or v >= self.ge) and (self.gt is None or v > self.gt)
                and (self.le is None or v <= self.le) and (self.lt is None or v < self.lt)
                and (not self.odd or (float(v).is_integer() and int(v) % 2 == 1)))

    def text(self, integer: bool = False) -> str:
        lo = f"[{_n(self.ge)}" if self.ge is not None else (f"({_n(self.gt)}" if self.gt is not None else None)
        hi = f"{_n(self.le)}]" if self.le is not None else (f"{_n(self.lt)})" if self.lt is not None else None)
        if lo and hi:
            s = f"a finite number in {lo}, {hi}"
        elif lo:
            s = f"a finite number {'>=' if self.ge is not None else '>'} {_n(self.ge if self.ge is not None else self.gt)}"
        elif hi:
            s = f"a finite number {'<=' if self.le is not None else '<'} {_n(self.le if self.le is not None else self.lt)}"
        else:
            s = "a finite number"
        return s.replace("a finite number", "an odd integer" if self.odd else "an integer" if integer else
                         "a finite number")


def _n(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(x)


def rule(**bounds) -> dict:
    """Field metadata carrying a :class:`Range` (``field(default=1, metadata=rule(ge=1))``)."""
    return {"rule": Range(**bounds)}


def check_value(name: str, value: Any, r: Range) -> None:
    """One-line :class:`SdpError` naming ``name`` unless ``value`` (or each item of a list) obeys ``r``."""
    if value is None:
        return
    items = value if isinstance(value, (list, tuple)) else [value]
    for v in items:
        if not r.ok(v):
            shown = list(value) if isinstance(value, (list, tuple)) else value
            integer = all(isinstance(x, int) and not isinstance(x, bool) for x in items)
            raise SdpError(f"{name} must be {r.text(integer)}{' (each)' if items is value else ''}, got {shown!r}")


def check_fields(obj, prefix: str = "") -> None:
    """Check every field of the dataclass instance ``obj`` that declares a rule; the error names the
    field as ``prefix + name`` (``sobolev_`` for the Sobolev section's options)."""
    for f in fields(obj):
        r = f.metadata.get("rule")
        if r is not None:
            check_value(prefix + f.name, getattr(obj, f.name), r)
