"""A Gilbert–Elliott good/bad channel per link (``burst:GOOD,BAD[,good=DUR][,bad=DUR]``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import DelayDistribution, DelaySpecError, delay_slots, parse_delay
from aoi3d.channel.varying.base import Channel, Server
from aoi3d.channel.varying.spec import ChannelSpecError, format_duration, parse_duration
from aoi3d.channel.varying.traces import CellQueue


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
        return (f"burst:{self.good.spec},{self.bad.spec},good={format_duration(self.good_ms)},"
                f"bad={format_duration(self.bad_ms)}")

    @property
    def mean_ms(self) -> float:
        """The long-run mean: the states' means weighted by their mean sojourns."""
        return float((self.good_ms * self.good.mean_ms + self.bad_ms * self.bad.mean_ms)
                     / (self.good_ms + self.bad_ms))

    def server(self, rng: np.random.Generator, *, start_ms: int = 0,
               cell: CellQueue | None = None) -> Server:
        return _BurstServer(self, rng, start_ms)


def parse_burst(body: str, spec: str) -> BurstChannel:
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
        times[name] = parse_duration(value, spec)
    return BurstChannel(dists[0], dists[1], times["good"], times["bad"])
