"""The two abstractions of a channel: :class:`Channel`, a parsed spec, and :class:`Server`,
one link's transmission times."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from aoi3d.channel.delay import DelayDistribution
from aoi3d.channel.varying.traces import CellQueue


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
