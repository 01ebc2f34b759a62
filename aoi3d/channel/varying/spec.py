"""What every channel spec shares: the forms, the error, the durations and the byte sizes."""

from __future__ import annotations

import math
import re

from aoi3d.channel.delay import DelaySpecError
from aoi3d.numbers import format_number

PACKET_BYTES = 1500
"""Bytes one delivery opportunity of a mahimahi trace carries."""
DEFAULT_FRAME_BYTES = 12_000
"""Size of a frame whose size is not known (a trace channel needs one): 12 kB."""
MAX_REGIMES = 64
MAX_TRACE_LINES = 4_000_000
"""Lines a trace may hold (the longest cellular traces hold about 200,000): 32 MB loaded."""
MAX_TRACE_BYTES = 64 * 2**20
"""Bytes a trace file may have; a larger one is refused before it is read."""
MAX_TRACE_PERIOD_MS = 86_400_000
"""A trace's period (its last time, after ``scale``) may be at most a day."""
MAX_TRACE_CACHE_BYTES = 128 * 2**20
"""The loaded traces kept (by path, modification time and scale), in bytes of their times;
the least recently used one goes first."""

CHANNEL_FORMS: tuple[str, ...] = (
    "regimes:SPEC@DUR,SPEC@DUR,…",
    "burst:GOOD,BAD[,good=DUR][,bad=DUR]",
    "trace:PATH[,offset=MS][,spread=MS][,scale=S]",
    "cell:PATH[,offset=MS][,spread=MS][,scale=S]",
)


class ChannelSpecError(DelaySpecError):
    """A channel spec is invalid (a ``DelaySpecError``, so a ``ValueError``)."""

    def __init__(self, problem: str, spec: str | None = None) -> None:
        super().__init__(problem, spec)
        forms = ", ".join(CHANNEL_FORMS)
        self.args = (f"{self.args[0]} Changing channels: {forms} (DUR e.g. 10s or 500ms; "
                     f"a trace is a mahimahi file: one ms timestamp a line, each one "
                     f"1500-byte delivery opportunity).",)


def parse_duration(text: str, spec: str) -> int:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[+-]?[0-9]+)?)\s*(ms|s|min)?\s*", text, re.I)
    if not m:
        raise ChannelSpecError(f"regime duration {text!r} is not a number with an optional "
                               f"unit (ms, s, min)", spec)
    value = float(m.group(1)) * {"ms": 1.0, "s": 1e3, "min": 6e4, None: 1.0}[
        (m.group(2) or "").lower() or None]
    if not math.isfinite(value) or value < 1 or value != round(value) or value > 86_400_000:
        raise ChannelSpecError(f"regime duration {text!r} must be a whole number of ms "
                               f"from 1 ms to 1 day", spec)
    return int(value)


def format_duration(ms: int) -> str:
    return f"{format_number(ms / 1000)}s" if ms % 1000 == 0 else f"{ms}ms"
