"""Which renders the metrics service scores with LPIPS (:class:`LpipsSampler`)."""

from __future__ import annotations

import math


class LpipsSampler:
    """Which renders get LPIPS: ``per_s`` a wall second on average, with bursts of up to one
    second's worth (a token bucket of ``max(1, per_s)`` tokens refilled at ``per_s`` a
    second; renders held for their truth come scored together); ``per_s`` 0: every render.
    LPIPS is most of the scoring's cost, so this bounds the metrics service's CPU at any
    render rate while slow runs (a time scale below 1) keep it on every render. Whether a
    render is taken depends on the wall clock only, never on its image: the LPIPS of the
    renders taken is an unbiased sample of every render's."""

    def __init__(self, per_s: float) -> None:
        if not (math.isfinite(per_s) and per_s >= 0):
            raise ValueError(f"per_s must be finite and >= 0, got {per_s}")
        self.per_s = per_s
        self.capacity = max(1.0, per_s)
        self._tokens = self.capacity
        self._at_s: float | None = None

    def _refill(self, now_s: float) -> None:
        if self._at_s is not None:
            self._tokens = min(self.capacity,
                               self._tokens + max(0.0, now_s - self._at_s) * self.per_s)
        self._at_s = now_s

    def due(self, now_s: float) -> bool:
        """Whether a render scored at ``now_s`` (monotonic seconds) gets LPIPS."""
        if self.per_s == 0:
            return True
        self._refill(now_s)
        return self._tokens >= 1.0

    def taken(self, now_s: float) -> None:
        """A render scored at ``now_s`` got LPIPS."""
        if self.per_s > 0:
            self._refill(now_s)
            self._tokens -= 1.0
