"""Which renders the metrics service scores with LPIPS (:class:`LpipsSampler`)."""

from __future__ import annotations

import math


class LpipsSampler:
    """Which renders get LPIPS: at most ``per_s`` a wall second, evenly (a render is taken
    when ``1 / per_s`` wall seconds have passed since the last one taken); ``per_s`` 0: every
    render. LPIPS is most of the scoring's cost, so this bounds the metrics service's CPU at any
    render rate while slow runs (a time scale below 1) keep it on every render. Whether a
    render is taken depends on the wall clock only, never on its image: the LPIPS of the
    renders taken is an unbiased sample of every render's."""

    def __init__(self, per_s: float) -> None:
        if not (math.isfinite(per_s) and per_s >= 0):
            raise ValueError(f"per_s must be finite and >= 0, got {per_s}")
        self.interval_s = 1.0 / per_s if per_s > 0 else 0.0
        self._last_s: float | None = None

    def due(self, now_s: float) -> bool:
        """Whether a render scored at ``now_s`` (monotonic seconds) gets LPIPS."""
        return self._last_s is None or now_s - self._last_s >= self.interval_s

    def taken(self, now_s: float) -> None:
        """A render scored at ``now_s`` got LPIPS."""
        self._last_s = now_s
