"""Benchmark: the vectorised channel + AoI simulation, in camera-slots per second.

Simulates N = 18 cameras for 600 s (1 ms slots) with the default channel (exp:60,
C = 30 ms), five times, in two ways:

- ``statistics``: ``simulate`` + ``channel_statistics`` (AoI mean/percentiles counted exactly
  per delivery cycle, the `aoi3d channel simulate` path);
- ``trace``: ``simulate`` + ``ChannelRun.aoi_trace`` (the AoI vector materialised at every
  slot, what a per-slot consumer such as a scheduler replay needs).

Reports best and median throughput and writes ``results/channel.json``; exits 1 when
the median of either way is below :data:`TARGET` camera-slots/s (the experiments issue's bar).
Run: ``make bench`` (or ``python -m bench.channel``).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

from aoi3d.channel import channel_statistics, parse_delay, simulate
from bench import common

N_CAMERAS, DURATION_MS, PERIOD_MS, REPEATS = 18, 600_000, 30, 5
TARGET = 1e7
"""Camera-slots per second the channel + AoI simulation must reach."""


def timed(work) -> list[float]:
    times = []
    for seed in range(REPEATS):
        t0 = time.perf_counter()
        work(seed)
        times.append(time.perf_counter() - t0)
    return times


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_json_option(ap)
    return ap


def run() -> dict:
    """The measurement; writes ``results/channel.json`` and returns its document."""
    delay = parse_delay("exp:60")
    slots = N_CAMERAS * DURATION_MS
    stats = channel_statistics(simulate(delay, PERIOD_MS, N_CAMERAS, DURATION_MS, 0))
    cases = {
        "statistics": timed(lambda s: channel_statistics(
            simulate(delay, PERIOD_MS, N_CAMERAS, DURATION_MS, s))),
        "trace": timed(lambda s: simulate(delay, PERIOD_MS, N_CAMERAS, DURATION_MS, s)
                       .aoi_trace()),
    }
    result = {
        "benchmark": "channel+aoi simulation",
        "cameras": N_CAMERAS, "duration_ms": DURATION_MS, "period_ms": PERIOD_MS,
        "delay": delay.spec, "repeats": REPEATS, "mean_aoi_ms": stats["mean_aoi_ms"],
        "cases": {name: {"seconds_best": min(t), "seconds_median": statistics.median(t),
                         "camera_slots_per_s_best": slots / min(t),
                         "camera_slots_per_s_median": slots / statistics.median(t)}
                  for name, t in cases.items()},
        "machine": {"python": platform.python_version(), "machine": platform.machine()},
    }
    common.write_json(common.RESULTS / "channel.json", result)
    return result


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        result = run()
        slots = result["cameras"] * result["duration_ms"]
        for name, r in result["cases"].items():
            print(f"channel+AoI ({name}): {slots:,} camera-slots in {r['seconds_best']:.3f} s "
                  f"(best of {REPEATS}) = {r['camera_slots_per_s_best']:.3g} camera-slots/s "
                  f"(median {r['camera_slots_per_s_median']:.3g})")
        print(f"written to {common.RESULTS / 'channel.json'}")
    if args.json:
        common.print_json(result)
    slow = [name for name, r in result["cases"].items()
            if r["camera_slots_per_s_median"] < TARGET]
    if slow:
        raise SystemExit(f"below the target of {TARGET:.0e} camera-slots/s: {', '.join(slow)}")
    with common.progress_to_stderr(args.json):
        print(f"both at least {TARGET:.0e} camera-slots/s (the target)")


if __name__ == "__main__":
    main()
