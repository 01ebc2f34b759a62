"""Benchmark: the vectorised channel + AoI simulation, in camera-slots per second.

Simulates N = 18 cameras for 600 s (1 ms slots) with the default channel (exp:60, C = 30 ms)
and computes the AoI statistics, five times; reports the best and median throughput and
writes ``bench/results/channel.json``. Run: ``make bench`` (or ``python bench/channel.py``).
"""

from __future__ import annotations

import json
import platform
import statistics
import time
from pathlib import Path

from aoi3d.channel import channel_statistics, parse_delay, simulate

N_CAMERAS, DURATION_MS, PERIOD_MS, REPEATS = 18, 600_000, 30, 5


def main() -> None:
    delay = parse_delay("exp:60")
    times = []
    for seed in range(REPEATS):
        t0 = time.perf_counter()
        run = simulate(delay, PERIOD_MS, N_CAMERAS, DURATION_MS, seed)
        stats = channel_statistics(run)
        times.append(time.perf_counter() - t0)
    slots = N_CAMERAS * DURATION_MS
    result = {
        "benchmark": "channel+aoi simulation",
        "cameras": N_CAMERAS, "duration_ms": DURATION_MS, "period_ms": PERIOD_MS,
        "delay": delay.spec, "repeats": REPEATS,
        "seconds_best": min(times), "seconds_median": statistics.median(times),
        "camera_slots_per_s_best": slots / min(times),
        "camera_slots_per_s_median": slots / statistics.median(times),
        "mean_aoi_ms": stats["mean_aoi_ms"],
        "machine": {"python": platform.python_version(), "processor": platform.processor(),
                    "machine": platform.machine()},
    }
    out = Path(__file__).parent / "results" / "channel.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"channel+AoI: {slots:,} camera-slots in {min(times):.3f} s (best of {REPEATS}) = "
          f"{result['camera_slots_per_s_best']:.3g} camera-slots/s "
          f"(median {result['camera_slots_per_s_median']:.3g}); written to {out}")


if __name__ == "__main__":
    main()
