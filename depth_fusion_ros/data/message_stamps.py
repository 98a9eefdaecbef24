"""Stamps and headers: ``builtin_interfaces/Time`` <-> integer nanoseconds, ``std_msgs/Header``.

A ``Time`` is converted to *integer nanoseconds* exactly (``stamp_to_ns``); float seconds are for
the core, and ``sec_to_ns`` / ``ns_to_sec`` round-trip a float stamp such as TUM's
``1305031102.175304`` without drift.
"""

from __future__ import annotations

from decimal import ROUND_HALF_EVEN, Decimal
from typing import Any

import numpy as np

from .message_kinds import MessageKind, as_kind

NS_PER_SEC = 1_000_000_000


def sec_to_ns(seconds: float) -> int:
    """Integer nanoseconds of a float stamp, via its shortest decimal repr (no drift).

    ``sec_to_ns(1305031102.175304) == 1305031102175304000`` exactly, whereas
    ``int(1305031102.175304 * 1e9)`` is off by ~100 ns.
    """
    value = float(seconds)
    if not np.isfinite(value):
        raise ValueError(f'stamp must be finite, got {seconds!r}')
    return int(Decimal(repr(value)).scaleb(9).to_integral_value(rounding=ROUND_HALF_EVEN))


def ns_to_sec(ns: int) -> float:
    """Float seconds of integer nanoseconds (int/int division is correctly rounded)."""
    return int(ns) / NS_PER_SEC


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (exact)."""
    return int(stamp.sec) * NS_PER_SEC + int(stamp.nanosec)


def stamp_to_sec(stamp: Any) -> float:
    """Float seconds of a ``builtin_interfaces/Time``."""
    return ns_to_sec(stamp_to_ns(stamp))


def time_msg(ns: int, *, kind: Any) -> Any:
    """A ``builtin_interfaces/Time`` of integer nanoseconds."""
    if isinstance(ns, float | np.floating):
        raise TypeError('time_msg takes integer nanoseconds; convert float seconds with sec_to_ns')
    sec, nanosec = divmod(int(ns), NS_PER_SEC)
    return as_kind(kind).new('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)


def _to_ns(stamp: Any) -> int:
    """Nanoseconds of a Time message (``sec``/``nanosec``), an int (ns) or a float (seconds)."""
    if hasattr(stamp, 'sec') and hasattr(stamp, 'nanosec'):
        return stamp_to_ns(stamp)
    if isinstance(stamp, int | np.integer):
        return int(stamp)
    if isinstance(stamp, float | np.floating):
        return sec_to_ns(float(stamp))
    raise ValueError(f'stamp must be a Time message, int nanoseconds or float seconds, got {stamp!r}')


def header_msg(stamp: Any, frame_id: str, *, kind: Any) -> Any:
    """A ``std_msgs/Header``.

    ``stamp`` is a ``Time`` message of any kind, an **int = nanoseconds**, or a
    **float = seconds**.
    """
    k = as_kind(kind)
    return k.new('std_msgs/msg/Header', stamp=time_msg(_to_ns(stamp), kind=k), frame_id=str(frame_id))


def _header_for(header: Any, kind: MessageKind) -> Any:
    """``header`` rebuilt in ``kind`` (cheap; lets callers pass a header of another kind)."""
    return header_msg(header.stamp, header.frame_id, kind=kind)
