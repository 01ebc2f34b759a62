"""Channels that change: the channel spec of a link, stationary or not.

A **channel spec** says how long each accepted frame stays on its camera's D/G/1/0 link. It
is one of:

- a delay distribution (``exp:60``, ``const:40``, … — :mod:`aoi3d.channel.delay`): every
  frame draws Y afresh, whatever its size and whenever it is sent (stationary);
- ``regimes:SPEC@DUR,SPEC@DUR,…`` — piecewise regimes that cycle: the first SPEC (a delay
  distribution) holds for DUR, then the next, …, then the first again. DUR is ``10s``,
  ``500ms`` or a number of ms. A frame draws Y from the regime in force at the slot it enters
  its link, e.g. ``regimes:exp:20@10s,exp:200@10s``;
- ``trace:PATH[,offset=MS][,spread=MS][,scale=S]`` — a mahimahi uplink trace replayed per
  camera (each camera its own subchannel, M = N). A frame of B bytes entering at slot g is
  delivered at the ⌈B/1500⌉-th delivery opportunity at or after g that its link has not used,
  at least one slot later. Each camera plays the trace from its own phase, ``offset`` plus a
  uniform draw in [0, ``spread``) from its own random stream (``spread`` defaults to the
  trace's length; ``spread=0`` puts every camera at ``offset``);
- ``burst:GOOD,BAD[,good=DUR][,bad=DUR]`` — a Gilbert–Elliott channel: each link is in a
  good or a bad state, draws Y from GOOD or BAD (delay distributions), and stays in a state
  for an exponential time of mean ``good`` (default 5s) or ``bad`` (default 1s), drawn from
  its own stream; every link starts good, e.g. ``burst:exp:20,exp:300,good=4s,bad=1s``;
- ``cell:PATH[,offset=MS][,spread=MS][,scale=S]`` — the cameras share one cell's capacity:
  one trace, one FIFO of packets. A frame's packets take the next opportunities not used by
  any camera's earlier frame, in the order the frames were offered. The cell's phase is
  ``offset`` plus a draw in [0, ``spread``) from the first camera's stream.

``scale=S`` stretches the trace's time axis by S (S = 2: half the capacity, transmission
times about twice as long). The trace format (mahimahi): one integer a line, a time in ms
from the start of the trace; each line is one opportunity for one 1500-byte packet; a
repeated time is several packets in that ms; the trace repeats with the period of its last
time. Frames without a size (the stationary kinds never need one) count as
:data:`DEFAULT_FRAME_BYTES`.

**Which trace model.** ``trace:`` is right when every camera has an uplink of its own — its
own modem, or the paper's M = N orthogonal subchannels — and the trace stands for one such
uplink's capacity; the cameras' delays are then independent replays of one kind of link.
``cell:`` is right when the cameras sit behind one cellular uplink (one modem, or one cell
sector whose scheduler shares its capacity): their frames compete, so with N cameras each
sees about N times the delay of one camera alone.

Time. A channel is *started* at a slot (``start_ms``): the regimes' cycle and the trace's
playback count from there. The virtual-clock experiments and :func:`aoi3d.channel.simulate`
start at slot 0; the network service starts a channel at the clock's time when it is set.
Every link is served by a :class:`Server` made by :meth:`Channel.server`; ``Link`` and
``simulate`` use the same servers, so they agree draw for draw.
"""

from __future__ import annotations

import math
import os
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import (
    MAX_DELAY_MS,
    DelayDistribution,
    DelaySpecError,
    delay_slots,
    parse_delay,
)
from aoi3d.numbers import format_number

__all__ = [
    "CHANNEL_FORMS",
    "DEFAULT_FRAME_BYTES",
    "PACKET_BYTES",
    "BurstChannel",
    "CellChannel",
    "CellQueue",
    "Channel",
    "ChannelSpecError",
    "RegimeChannel",
    "Server",
    "StationaryChannel",
    "TraceChannel",
    "load_trace",
    "parse_channel",
    "trace_path_of",
    "transmission_summary",
]

PACKET_BYTES = 1500
"""Bytes one delivery opportunity of a mahimahi trace carries."""
DEFAULT_FRAME_BYTES = 12_000
"""Size of a frame whose size is not known (a trace channel needs one): 12 kB."""
MAX_REGIMES = 64
MAX_TRACE_LINES = 20_000_000

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


class Server(ABC):
    """One link's transmission times: what a frame of ``size_bytes`` entering at ``gen_slot``
    spends on the link (slots >= 1). Called once per accepted frame, in order."""

    @abstractmethod
    def slots(self, gen_slot: int, size_bytes: int) -> int: ...

    #: The transmission time of the last frame, in ms (for a distribution: the Y drawn).
    last_ms: float = math.nan


class Channel(ABC):
    """A channel spec, parsed. ``server`` makes one link's server; ``mean_ms`` is the mean
    transmission time a 12-kB frame sees (stationary: E[Y])."""

    kind: ClassVar[str]
    #: Whether a frame's size changes its transmission time.
    size_dependent: ClassVar[bool] = False
    #: Whether the cameras share one capacity (``server`` then needs a :class:`CellQueue`).
    shared: ClassVar[bool] = False

    @property
    @abstractmethod
    def spec(self) -> str:
        """Canonical spec: ``parse_channel(c.spec) == c``."""

    @property
    @abstractmethod
    def mean_ms(self) -> float: ...

    @property
    def stationary(self) -> DelayDistribution | None:
        """The distribution when the channel is a stationary one, else None."""
        return None

    @abstractmethod
    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        """A fresh server for one link that draws from ``rng`` (a trace draws its phase
        here, at once)."""

    def new_cell(self, rng: np.random.Generator, *, start_ms: int = 0) -> CellQueue | None:
        """The shared queue of a ``cell:`` channel (its phase drawn from ``rng``); None for
        the others."""
        return None

    def regime_at(self, t_ms: float, start_ms: float = 0.0) -> str:
        """The spec in force at ``t_ms`` for a channel started at ``start_ms``."""
        return self.spec

    def changes_between(self, a_ms: float, b_ms: float,
                        start_ms: float = 0.0) -> list[tuple[float, str]]:
        """The regime changes in (a_ms, b_ms]: (time, spec now in force)."""
        return []

    def __str__(self) -> str:
        return self.spec


# ---------------------------------------------------------------------------- stationary
class _DistServer(Server):
    def __init__(self, dist: DelayDistribution, rng: np.random.Generator) -> None:
        self._dist = dist
        self._rng = rng

    def slots(self, gen_slot: int, size_bytes: int) -> int:
        y = float(self._dist.sample(self._rng, 1)[0])
        self.last_ms = y
        return delay_slots(y)


@dataclass(frozen=True)
class StationaryChannel(Channel):
    dist: DelayDistribution
    kind: ClassVar[str] = "stationary"

    @property
    def spec(self) -> str:
        return self.dist.spec

    @property
    def mean_ms(self) -> float:
        return float(self.dist.mean_ms)

    @property
    def stationary(self) -> DelayDistribution:
        return self.dist

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        return _DistServer(self.dist, rng)


# ---------------------------------------------------------------------------- regimes
def _parse_duration(text: str, spec: str) -> int:
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


def _format_duration(ms: int) -> str:
    return f"{format_number(ms / 1000)}s" if ms % 1000 == 0 else f"{ms}ms"


class _RegimeServer(Server):
    def __init__(self, channel: RegimeChannel, rng: np.random.Generator, start_ms: int) -> None:
        self._channel = channel
        self._rng = rng
        self._start = int(start_ms)

    def slots(self, gen_slot: int, size_bytes: int) -> int:
        dist = self._channel.regime_dist(gen_slot - self._start)
        y = float(dist.sample(self._rng, 1)[0])
        self.last_ms = y
        return delay_slots(y)


@dataclass(frozen=True)
class RegimeChannel(Channel):
    """Piecewise-stationary regimes that cycle: ``regimes[i]`` holds for ``durations_ms[i]``."""

    regimes: tuple[DelayDistribution, ...]
    durations_ms: tuple[int, ...]
    kind: ClassVar[str] = "regimes"
    _ends: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.regimes or len(self.regimes) != len(self.durations_ms):
            raise ChannelSpecError("regimes need one duration per regime and at least one")
        object.__setattr__(self, "_ends", np.cumsum(np.asarray(self.durations_ms, np.int64)))

    @property
    def cycle_ms(self) -> int:
        return int(self._ends[-1])

    @property
    def spec(self) -> str:
        return "regimes:" + ",".join(f"{d.spec}@{_format_duration(t)}"
                                     for d, t in zip(self.regimes, self.durations_ms,
                                                     strict=True))

    @property
    def mean_ms(self) -> float:
        """The time-weighted mean of the regimes' means."""
        w = np.asarray(self.durations_ms, dtype=np.float64)
        return float(np.dot(w, [d.mean_ms for d in self.regimes]) / w.sum())

    def index_at(self, t_ms: float) -> int:
        """The regime in force ``t_ms`` after the start (cycling; t < 0 counts backwards)."""
        phase = math.floor(t_ms) % self.cycle_ms
        return int(np.searchsorted(self._ends, phase, side="right"))

    def regime_dist(self, t_ms: float) -> DelayDistribution:
        return self.regimes[self.index_at(t_ms)]

    def regime_at(self, t_ms: float, start_ms: float = 0.0) -> str:
        return self.regime_dist(t_ms - start_ms).spec

    def changes_between(self, a_ms: float, b_ms: float,
                        start_ms: float = 0.0) -> list[tuple[float, str]]:
        out: list[tuple[float, str]] = []
        if len(self.regimes) < 2 or b_ms <= a_ms:
            return out
        bounds = np.concatenate(([0], self._ends[:-1]))
        a, b = a_ms - start_ms, b_ms - start_ms
        cycle = self.cycle_ms
        k0 = math.floor(a / cycle)
        for k in range(k0, math.floor(b / cycle) + 1):
            for i, lo in enumerate(bounds):
                t = k * cycle + int(lo)
                if a < t <= b:
                    out.append((t + start_ms, self.regimes[i].spec))
                if len(out) > 10_000:
                    return out
        return out

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        return _RegimeServer(self, rng, start_ms)


def _parse_regimes(body: str, spec: str) -> RegimeChannel:
    parts = [p.strip() for p in body.split(",")]
    if not body.strip() or any(not p for p in parts):
        raise ChannelSpecError("regimes need SPEC@DUR entries separated by commas", spec)
    if len(parts) > MAX_REGIMES:
        raise ChannelSpecError(f"at most {MAX_REGIMES} regimes, got {len(parts)}", spec)
    dists: list[DelayDistribution] = []
    durations: list[int] = []
    for part in parts:
        if "@" not in part:
            raise ChannelSpecError(f"regime {part!r} lacks its duration (SPEC@DUR, e.g. "
                                   f"exp:20@10s)", spec)
        inner, dur = part.rsplit("@", 1)
        try:
            dists.append(parse_delay(inner))
        except DelaySpecError as err:
            raise ChannelSpecError(f"regime {part!r}: {err.problem} (a regime is a delay "
                                   f"distribution)", spec) from None
        durations.append(_parse_duration(dur, spec))
    return RegimeChannel(tuple(dists), tuple(durations))


# ---------------------------------------------------------------------------- bursts
class _BurstServer(Server):
    def __init__(self, channel: BurstChannel, rng: np.random.Generator, start_ms: int) -> None:
        self._channel = channel
        self._rng = rng
        self._bad = False
        self._until = int(start_ms) + self._sojourn()

    def _sojourn(self) -> int:
        mean = self._channel.bad_ms if self._bad else self._channel.good_ms
        return max(1, math.ceil(float(self._rng.exponential(mean))))

    def slots(self, gen_slot: int, size_bytes: int) -> int:
        while gen_slot >= self._until:  # the states the link went through since
            self._bad = not self._bad
            self._until += self._sojourn()
        dist = self._channel.bad if self._bad else self._channel.good
        y = float(dist.sample(self._rng, 1)[0])
        self.last_ms = y
        return delay_slots(y)


@dataclass(frozen=True)
class BurstChannel(Channel):
    """A Gilbert–Elliott good/bad channel per link (``burst:``)."""

    good: DelayDistribution
    bad: DelayDistribution
    good_ms: int = 5000
    bad_ms: int = 1000
    kind: ClassVar[str] = "burst"

    @property
    def spec(self) -> str:
        return (f"burst:{self.good.spec},{self.bad.spec},good={_format_duration(self.good_ms)},"
                f"bad={_format_duration(self.bad_ms)}")

    @property
    def mean_ms(self) -> float:
        """The long-run mean: the states' means weighted by their mean sojourns."""
        return float((self.good_ms * self.good.mean_ms + self.bad_ms * self.bad.mean_ms)
                     / (self.good_ms + self.bad_ms))

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        return _BurstServer(self, rng, start_ms)


def _parse_burst(body: str, spec: str) -> BurstChannel:
    parts = [p.strip() for p in body.split(",")]
    if len(parts) < 2 or not parts[0] or not parts[1]:
        raise ChannelSpecError("burst needs two delay specs, GOOD,BAD (e.g. "
                               "burst:exp:20,exp:300,good=4s,bad=1s)", spec)
    dists = []
    for name, part in zip(("GOOD", "BAD"), parts[:2], strict=True):
        try:
            dists.append(parse_delay(part))
        except DelaySpecError as err:
            raise ChannelSpecError(f"burst {name} {part!r}: {err.problem}", spec) from None
    times = {"good": 5000, "bad": 1000}
    seen: set[str] = set()
    for part in parts[2:]:
        name, eq, value = part.partition("=")
        name = name.strip().lower()
        if not eq or name not in times or name in seen:
            raise ChannelSpecError(f"burst option {part!r}: good=DUR and bad=DUR, once each",
                                   spec)
        seen.add(name)
        times[name] = _parse_duration(value, spec)
    return BurstChannel(dists[0], dists[1], times["good"], times["bad"])


# ---------------------------------------------------------------------------- traces
@dataclass(frozen=True, eq=False)
class Trace:
    """A mahimahi trace, loaded: ``times_ms`` sorted opportunity times in [0, period]."""

    path: str
    times_ms: np.ndarray  # (n,) float64, sorted
    period_ms: float

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


_TRACES: dict[tuple[str, float, float], Trace] = {}


def load_trace(path: str | os.PathLike[str], scale: float = 1.0) -> Trace:
    """Read a mahimahi trace (cached by path, modification time and scale)."""
    p = Path(path).expanduser()
    try:
        stat = p.stat()
    except OSError as err:
        raise ChannelSpecError(f"cannot read trace {str(p)!r}: {err.strerror}") from None
    if not p.is_file():
        raise ChannelSpecError(f"trace {str(p)!r} is not a file")
    key = (str(p.resolve()), stat.st_mtime, float(scale))
    if key in _TRACES:
        return _TRACES[key]
    try:
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
    trace = Trace(str(p), times, period)
    if len(_TRACES) > 32:
        _TRACES.clear()
    _TRACES[key] = trace
    return trace


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

    @cached_property
    def mean_ms(self) -> float:  # type: ignore[override]
        """Mean transmission time of a 12-kB frame offered every 30 ms over the whole trace
        by one camera from phase ``offset`` (the traces README's table)."""
        return transmission_summary(self, DEFAULT_FRAME_BYTES, 30)["mean_ms"]

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
    p99 transmission time (ms) and the drop ratio."""
    trace = channel.trace
    server = _TraceServer(trace, channel.offset_ms, 0)
    end = int(duration_ms if duration_ms is not None else math.ceil(trace.period_ms))
    busy = -math.inf
    ys: list[int] = []
    offered = 0
    for g in range(0, end, period_ms):
        offered += 1
        if g < busy:
            continue
        y = server.slots(g, frame_bytes)
        busy = g + y
        ys.append(y)
    arr = np.asarray(ys, dtype=np.float64)
    return {"mean_ms": float(arr.mean()), "p50_ms": float(np.percentile(arr, 50)),
            "p90_ms": float(np.percentile(arr, 90)), "p99_ms": float(np.percentile(arr, 99)),
            "drop_ratio": 1.0 - len(ys) / offered}


def _parse_trace(kind: str, body: str, spec: str) -> TraceChannel:
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


# ---------------------------------------------------------------------------- parsing
def trace_path_of(spec: str) -> str | None:
    """The trace path a ``trace:`` or ``cell:`` spec names (read from the text alone, no file
    touched: a service checks where it lies before reading it); None for the other kinds."""
    kind, _, body = str(spec).strip().partition(":")
    if kind.strip().lower() not in ("trace", "cell"):
        return None
    return body.split(",")[0].strip()


def parse_channel(spec: str | Channel | DelayDistribution) -> Channel:
    """Parse any channel spec (a delay distribution, ``regimes:``, ``trace:``, ``cell:``);
    a channel passes through, a distribution is wrapped. Raises ``DelaySpecError``."""
    if isinstance(spec, Channel):
        return spec
    if isinstance(spec, DelayDistribution):
        return StationaryChannel(spec)
    if not isinstance(spec, str):
        raise DelaySpecError(f"expected a string, got {type(spec).__name__}", repr(spec))
    text = spec.strip()
    kind, _, body = text.partition(":")
    kind = kind.strip().lower()
    if kind == "regimes":
        return _parse_regimes(body, spec)
    if kind == "burst":
        return _parse_burst(body, spec)
    if kind in ("trace", "cell"):
        return _parse_trace(kind, body, spec)
    try:
        return StationaryChannel(parse_delay(text))
    except ChannelSpecError:
        raise
    except DelaySpecError as err:
        raise ChannelSpecError(err.problem, spec) from None
