"""The shared simulation clock of the live pipeline.

``sim_ms = (wall_s - epoch_s) * time_scale * 1000``. A time scale below 1 slows the world
down so that a CPU trainer keeps pace; every service of a run uses the same epoch and scale.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class SimClock:
    epoch_s: float
    time_scale: float = 1.0
    wall: Callable[[], float] = field(default=time.time, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {self.time_scale}")

    def now_ms(self) -> float:
        """Simulation time now, in ms."""
        return (self.wall() - self.epoch_s) * self.time_scale * 1000.0

    def wall_s(self, sim_ms: float) -> float:
        """The wall-clock time (s since the Unix epoch) at which ``sim_ms`` is reached."""
        return self.epoch_s + sim_ms / 1000.0 / self.time_scale

    def sleep_until(self, sim_ms: float) -> None:
        delay = self.wall_s(sim_ms) - self.wall()
        if delay > 0:
            time.sleep(delay)
