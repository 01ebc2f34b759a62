"""Trace I/O: a mahimahi trace read from its file (:func:`load_trace`, cached), and
:class:`CellQueue`, one cell's capacity on a trace that its cameras share."""

from __future__ import annotations

import math
import os
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aoi3d.channel.varying.spec import (
    MAX_TRACE_BYTES,
    MAX_TRACE_CACHE_BYTES,
    MAX_TRACE_LINES,
    MAX_TRACE_PERIOD_MS,
    PACKET_BYTES,
    ChannelSpecError,
)


@dataclass(frozen=True, eq=False)
class Trace:
    """A mahimahi trace, loaded: ``times_ms`` sorted opportunity times in [0, period]."""

    path: str
    times_ms: np.ndarray  # (n,) float64, sorted
    period_ms: float
    mtime_ns: int = 0
    """The file's modification time when it was read: what a cache of results keys on."""

    @property
    def n(self) -> int:
        return len(self.times_ms)

    def first_at_or_after(self, tau: float) -> int:
        """Global index (over the repeated trace) of the first opportunity at or after
        ``tau``."""
        c = math.floor(tau / self.period_ms)
        r = tau - c * self.period_ms
        return c * self.n + int(np.searchsorted(self.times_ms, r, side="left"))

    def time_of(self, j: int) -> float:
        c, i = divmod(j, self.n)
        return c * self.period_ms + float(self.times_ms[i])


_TRACES: OrderedDict[tuple[str, int, float], Trace] = OrderedDict()


def load_trace(path: str | os.PathLike[str], scale: float = 1.0) -> Trace:
    """Read a mahimahi trace (cached by path, modification time and scale, at most
    ``MAX_TRACE_CACHE_BYTES`` of times, least recently used out first). Refused with a
    ``ChannelSpecError`` naming the file: over ``MAX_TRACE_BYTES`` or ``MAX_TRACE_LINES``,
    times that are not finite, negative or decreasing, a period (the last time, scaled) over
    ``MAX_TRACE_PERIOD_MS``."""
    p = Path(path).expanduser()
    try:
        stat = p.stat()
    except OSError as err:
        raise ChannelSpecError(f"cannot read trace {str(p)!r}: {err.strerror}") from None
    if not p.is_file():
        raise ChannelSpecError(f"trace {str(p)!r} is not a file")
    if stat.st_size > MAX_TRACE_BYTES:
        raise ChannelSpecError(f"trace {str(p)!r} has {stat.st_size} bytes, over the "
                               f"{MAX_TRACE_BYTES} a trace may have")
    key = (str(p.resolve()), stat.st_mtime_ns, float(scale))
    if key in _TRACES:
        _TRACES.move_to_end(key)
        return _TRACES[key]
    try:
        with warnings.catch_warnings():  # an empty file: refused below, not warned about
            warnings.simplefilter("ignore", UserWarning)
            raw = np.loadtxt(p, dtype=np.float64, ndmin=1, max_rows=MAX_TRACE_LINES + 1)
    except (ValueError, OSError):  # the reader's message may quote the file: left out
        raise ChannelSpecError(f"trace {str(p)!r} is not a mahimahi trace (one integer ms "
                               f"a line)") from None
    if raw.ndim != 1 or raw.size == 0:
        raise ChannelSpecError(f"trace {str(p)!r} has no opportunities")
    if raw.size > MAX_TRACE_LINES:
        raise ChannelSpecError(f"trace {str(p)!r} has over {MAX_TRACE_LINES} lines")
    if not np.all(np.isfinite(raw)) or np.any(raw < 0) or np.any(np.diff(raw) < 0):
        raise ChannelSpecError(f"trace {str(p)!r} must hold non-decreasing times >= 0")
    times = raw * float(scale)
    period = max(float(times[-1]), 1.0)
    if not period <= MAX_TRACE_PERIOD_MS:
        raise ChannelSpecError(f"trace {str(p)!r} lasts {format(period, '.6g')} ms "
                               f"(scaled), over the {MAX_TRACE_PERIOD_MS} ms (a day) a trace "
                               f"may last")
    trace = Trace(str(p), times, period, stat.st_mtime_ns)
    _TRACES[key] = trace
    while sum(t.times_ms.nbytes for t in _TRACES.values()) > MAX_TRACE_CACHE_BYTES:
        _TRACES.popitem(last=False)
    return trace


def cached_trace_bytes() -> int:
    """Bytes of the traces' times held by the cache now."""
    return sum(t.times_ms.nbytes for t in _TRACES.values())


@dataclass
class CellQueue:
    """One cell's capacity shared by its cameras: a FIFO of packets over one trace."""

    trace: Trace
    shift: int  # trace time = slot + shift
    next_index: int = -(2**62)

    def serve(self, gen_slot: int, size_bytes: int) -> float:
        tau = gen_slot + self.shift
        packets = max(1, -(-int(size_bytes) // PACKET_BYTES))
        j0 = max(self.trace.first_at_or_after(tau), self.next_index)
        j = j0 + packets - 1
        self.next_index = j + 1
        return self.trace.time_of(j) - tau
