"""The trace-driven channels: a mahimahi trace replayed per camera (``trace:``) or one
cell's capacity shared by every camera (``cell:``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import MAX_DELAY_MS, delay_slots
from aoi3d.channel.varying.base import Channel, Server
from aoi3d.channel.varying.spec import DEFAULT_FRAME_BYTES, PACKET_BYTES, ChannelSpecError
from aoi3d.channel.varying.traces import CellQueue, Trace, load_trace
from aoi3d.numbers import format_number

_MEANS: dict[tuple[str, int, float, int, int, float], float] = {}


class _TraceServer(Server):
    """One camera's replay of the trace, at its own phase."""

    def __init__(self, trace: Trace, phase_ms: int, start_ms: int) -> None:
        self._trace = trace
        self._shift = int(phase_ms) - int(start_ms)  # trace time = slot + shift
        self._next = -(2**62)  # global index of the first opportunity not yet used

    def slots(self, gen_slot: int, size_bytes: int) -> int:
        tau = gen_slot + self._shift
        packets = max(1, -(-int(size_bytes) // PACKET_BYTES))
        j0 = max(self._trace.first_at_or_after(tau), self._next)
        j = j0 + packets - 1
        self._next = j + 1
        y = self._trace.time_of(j) - tau
        self.last_ms = max(y, 1.0)
        return delay_slots(min(y, MAX_DELAY_MS))


class _CellServer(Server):
    def __init__(self, cell: CellQueue) -> None:
        self._cell = cell

    def slots(self, gen_slot: int, size_bytes: int) -> int:
        y = self._cell.serve(gen_slot, size_bytes)
        self.last_ms = max(y, 1.0)
        return delay_slots(min(y, MAX_DELAY_MS))


@dataclass(frozen=True)
class TraceChannel(Channel):
    """A mahimahi trace replayed per camera (``trace:``)."""

    path: str
    offset_ms: int = 0
    spread_ms: int | None = None  # None: the trace's length
    scale: float = 1.0
    kind: ClassVar[str] = "trace"
    size_dependent: ClassVar[bool] = True

    @property
    def trace(self) -> Trace:
        return load_trace(self.path, self.scale)

    @property
    def spec(self) -> str:
        opts = [self.path]
        if self.offset_ms:
            opts.append(f"offset={self.offset_ms}")
        if self.spread_ms is not None:
            opts.append(f"spread={self.spread_ms}")
        if self.scale != 1.0:
            opts.append(f"scale={format_number(self.scale)}")
        return f"{self.kind}:" + ",".join(opts)

    def _phase(self, rng: np.random.Generator) -> int:
        spread = (math.ceil(self.trace.period_ms) if self.spread_ms is None
                  else self.spread_ms)
        return self.offset_ms + (int(rng.integers(0, spread)) if spread > 0 else 0)

    @property
    def mean_ms(self) -> float:
        """Mean transmission time of a 12-kB frame offered every 30 ms over the whole trace
        by one camera from phase ``offset`` (the traces README's table); computed once per
        trace file (as modified) and options."""
        trace = self.trace
        key = (trace.path, trace.mtime_ns, self.scale, self.offset_ms, trace.n, trace.period_ms)
        if key not in _MEANS:
            if len(_MEANS) > 64:
                _MEANS.clear()
            _MEANS[key] = transmission_summary(self, DEFAULT_FRAME_BYTES, 30)["mean_ms"]
        return _MEANS[key]

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        return _TraceServer(self.trace, self._phase(rng), start_ms)


@dataclass(frozen=True)
class CellChannel(TraceChannel):
    """One cell's capacity shared by every camera (``cell:``)."""

    kind: ClassVar[str] = "cell"
    shared: ClassVar[bool] = True

    def new_cell(self, rng: np.random.Generator, *, start_ms: int = 0) -> CellQueue:
        return CellQueue(self.trace, self._phase(rng) - int(start_ms))

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        if cell is None:
            raise ValueError("a cell: channel's links share one CellQueue (new_cell)")
        return _CellServer(cell)


def transmission_summary(channel: TraceChannel, frame_bytes: int, period_ms: int,
                         duration_ms: int | None = None) -> dict[str, float]:
    """One camera at phase ``offset`` offering a ``frame_bytes`` frame every ``period_ms``
    over the trace's length (or ``duration_ms``) through a D/G/1/0 link: mean / p50 / p90 /
    p99 transmission time (ms) and the drop ratio.

    The work is one step per *accepted* frame, not per offered one: a frame offered while
    the previous one is in flight is dropped, so the next accepted frame is the first offer
    at or after the link frees. Each accepted frame uses at least one opportunity of the
    trace or takes up to ``MAX_DELAY_MS``, so the steps are at most the trace's
    opportunities plus duration / ``MAX_DELAY_MS``, whatever its period."""
    if period_ms < 1:
        raise ValueError(f"period_ms must be >= 1, got {period_ms!r}")
    trace = channel.trace
    server = _TraceServer(trace, channel.offset_ms, 0)
    end = int(duration_ms if duration_ms is not None else math.ceil(trace.period_ms))
    offered = max(0, -(-end // period_ms))  # len(range(0, end, period_ms))
    ys: list[int] = []
    g = 0
    while g < end:
        y = server.slots(g, frame_bytes)
        ys.append(y)
        g = -(-(g + y) // period_ms) * period_ms  # the first offer at or after g + y
    arr = np.asarray(ys, dtype=np.float64)
    return {"mean_ms": float(arr.mean()), "p50_ms": float(np.percentile(arr, 50)),
            "p90_ms": float(np.percentile(arr, 90)), "p99_ms": float(np.percentile(arr, 99)),
            "drop_ratio": 1.0 - len(ys) / offered}


def parse_trace(kind: str, body: str, spec: str) -> TraceChannel:
    parts = [p.strip() for p in body.split(",")]
    path = parts[0]
    if not path:
        raise ChannelSpecError(f"{kind} needs a trace path ({kind}:PATH)", spec)
    opts: dict[str, str] = {}
    for part in parts[1:]:
        name, eq, value = part.partition("=")
        name = name.strip().lower()
        if not eq or name not in ("offset", "spread", "scale"):
            raise ChannelSpecError(f"unknown {kind} option {part!r} (offset=MS, spread=MS, "
                                   f"scale=S)", spec)
        if name in opts:
            raise ChannelSpecError(f"option {name} given twice", spec)
        opts[name] = value.strip()

    def whole(name: str) -> int | None:
        if name not in opts:
            return None
        try:
            v = float(opts[name].removesuffix("ms"))
        except ValueError:
            raise ChannelSpecError(f"{name} must be a number of ms, got {opts[name]!r}",
                                   spec) from None
        if not math.isfinite(v) or v < 0 or v != round(v) or v > 1e10:
            raise ChannelSpecError(f"{name} must be a whole number of ms >= 0, got "
                                   f"{opts[name]!r}", spec)
        return int(v)

    scale = 1.0
    if "scale" in opts:
        try:
            scale = float(opts["scale"])
        except ValueError:
            raise ChannelSpecError(f"scale must be a number, got {opts['scale']!r}",
                                   spec) from None
        if not (math.isfinite(scale) and 0.01 <= scale <= 100):
            raise ChannelSpecError(f"scale must be in [0.01, 100], got {opts['scale']!r}",
                                   spec)
    cls = CellChannel if kind == "cell" else TraceChannel
    channel = cls(path, whole("offset") or 0, whole("spread"), scale)
    try:
        channel.trace  # noqa: B018 - read (and cache) it now, so a bad path is refused here
    except ChannelSpecError as err:
        raise ChannelSpecError(err.problem, spec) from None
    return channel
