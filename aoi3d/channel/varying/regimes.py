"""Piecewise-stationary regimes that cycle (``regimes:SPEC@DUR,…``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import DelayDistribution, DelaySpecError, delay_slots, parse_delay
from aoi3d.channel.varying.base import Channel, Server
from aoi3d.channel.varying.spec import (
    MAX_REGIMES,
    ChannelSpecError,
    format_duration,
    parse_duration,
)
from aoi3d.channel.varying.traces import CellQueue


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
        return "regimes:" + ",".join(f"{d.spec}@{format_duration(t)}"
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


def parse_regimes(body: str, spec: str) -> RegimeChannel:
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
        durations.append(parse_duration(dur, spec))
    return RegimeChannel(tuple(dists), tuple(durations))
