"""The stationary channel: a delay distribution, every frame draws Y afresh."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import DelayDistribution, delay_slots
from aoi3d.channel.varying.base import Channel, Server
from aoi3d.channel.varying.traces import CellQueue


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
