"""A virtual clock for code that paces itself by a clock and a stop event (the test robot,
the player): call it for the time; hand it over as the stop event too, and every wait
advances the clock instead of sleeping."""

from __future__ import annotations


class FakeClock:
    def __init__(self, start_s: float) -> None:
        self.now = float(start_s)

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds

    # a threading.Event that is never set, whose waits take no wall time
    def is_set(self) -> bool:
        return False

    def wait(self, seconds: float) -> bool:
        self.advance(seconds)
        return False
