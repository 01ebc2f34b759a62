"""bench/soak.py's arithmetic: the render rate over a window from the samples, and one rate per
whole window (the hour's sampling runs a little past the hour: no partial last window)."""

from __future__ import annotations

import math

from bench import soak


def test_one_rate_per_whole_window() -> None:
    # 4 renders/s for 20 min, then 2/s; sampled every 30 s, a little past 40 min
    points = [(t, int(4 * min(t, 1200) + 2 * max(0.0, t - 1200))) for t in range(0, 2431, 30)]
    rates = soak.window_rates(points, 600.0)
    assert rates == [4.0, 4.0, 2.0, 2.0]
    assert all(math.isfinite(r) for r in rates)
    assert soak.rate(points, 0.0, 600.0) == 4.0
