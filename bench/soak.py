"""Soak: run the whole pipeline for an hour; memory, render rate and the decision ledger.

Starts ``aoi3d up`` (default scene and settings, ``--sites`` 2 and ``--workers`` 2, its own
ports), waits ``--warmup-s`` and then for ``--minutes`` samples, every ``--every-s`` seconds,
the resident memory (RSS, from /proc) of the router, every service and every reconstruction
worker, and the pool's renders so far (the dispatcher's ``GET /status``). At the end it reads the
decision ledger of every site (the metrics service's ``GET /sites/<site>/ledger``).

The JSON (``--out``) gives per process the RSS over the first and over the last window (the
median of its samples there: a worker's RSS rises and falls with each job), the growth (MiB,
%) and a least-squares slope in MiB per hour; renders per second over the first and the
last ``--window-min`` minutes and their ratio; the restarts ``aoi3d up`` made; the load; the
ledger per site. The verdict: every process grew less than 10 % and the last window's render
rate is within 5 % of the first's (exit status 1 otherwise).

    python -m bench.soak --minutes 60        # docs/measurements.md (results/soak.json)
    python -m bench.soak --minutes 3 --window-min 1 --out /tmp/soak.json   # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

ROOT = common.ROOT
PORTS = BENCH_BLOCKS["soak"]  # apart from make up, chaos and the tests (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): its URLs."""
MAX_GROWTH = 0.10
MAX_RATE_CHANGE = 0.05


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def rate(points: list[tuple[float, int]], t0: float, t1: float) -> float:
    """Renders per second between the samples nearest t0 and t1 (seconds since the start)."""
    t = np.array([p[0] for p in points])
    a, b = points[int(np.abs(t - t0).argmin())], points[int(np.abs(t - t1).argmin())]
    return (b[1] - a[1]) / (b[0] - a[0]) if b[0] > a[0] else float("nan")


def window_rates(points: list[tuple[float, int]], window: float) -> list[float]:
    """Renders per second in each whole window of ``window`` seconds from the start (a last,
    partial one — the minute's sampling runs a little past the hour — is left out)."""
    span = points[-1][0]
    whole = int(span // window + 1e-9)
    return [round(rate(points, i * window, (i + 1) * window), 3) for i in range(whole)]


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--sites", type=int, default=2)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--every-s", type=float, default=30.0)
    parser.add_argument("--warmup-s", type=float, default=90.0)
    parser.add_argument("--window-min", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=common.RESULTS / "soak.json")
    common.add_json_option(parser, help="print the result document as JSON (it is printed "
                                        "anyway)")
    return parser


def run(args: argparse.Namespace) -> dict:
    """The soak (``parser()``'s options); writes ``args.out`` and returns the result document
    (its verdict: ``memory_ok`` and ``rate_ok``)."""
    log_dir = ROOT / "runs" / "bench-soak"
    run_id = f"soak{uuid.uuid4().hex[:6]}"
    up = PIPE.start(["--sites", str(args.sites), "--workers", str(args.workers)],
                    run_id=run_id, log_dir=log_dir, cwd=ROOT)
    http = httpx.Client(timeout=60.0)
    samples: dict[str, list[tuple[float, float]]] = {}
    renders: list[tuple[float, int]] = []
    loads: list[float] = []
    try:
        up.wait(
            "soak: the pipeline rendering",
            lambda: http.get(PIPE.url("dispatcher", "/status")).json()["pool"]["rendered"] > 0,
            600, every_s=2.0)
        time.sleep(args.warmup_s)
        t0 = time.monotonic()
        end = t0 + args.minutes * 60.0
        while True:
            state = json.loads((log_dir / "latest" / "up.json").read_text())
            now = time.monotonic() - t0
            for name, child in state["children"].items():
                mib = rss_mib(child["pid"]) if child["pid"] else None
                if mib is not None:
                    samples.setdefault(name, []).append((now, mib))
            status = http.get(PIPE.url("dispatcher", "/status")).json()
            renders.append((now, status["pool"]["rendered"]))
            loads.append(os.getloadavg()[0])
            if time.monotonic() >= end:
                break
            time.sleep(min(args.every_s, max(0.0, end - time.monotonic())))
        restarts = {n: c["restarts"] for n, c in state["children"].items()}
        sites = http.get(PIPE.url("metrics", "/sites")).json()["sites"]
        ledgers = {s: http.get(PIPE.url("metrics", f"/sites/{s}/ledger")).json() for s in sites}
    finally:
        up.stop(90)
    span = renders[-1][0]
    window = min(args.window_min * 60.0, span / 2)
    processes: dict[str, dict[str, Any]] = {}
    for name, points in samples.items():
        t, m = np.array(points).T
        # a worker's RSS rises and falls with each job's model: the median of each window
        start = float(np.median(m[t <= window])) if (t <= window).any() else m[0]
        stop = float(np.median(m[t >= span - window])) if (t >= span - window).any() else m[-1]
        slope = float(np.polyfit(t / 3600.0, m, 1)[0]) if len(t) > 2 else None
        processes[name] = {"rss_start_mib": round(start, 1), "rss_end_mib": round(stop, 1),
                           "growth_mib": round(stop - start, 1),
                           "growth_pct": round(100 * (stop - start) / start, 1),
                           "slope_mib_per_hour": None if slope is None else round(slope, 1),
                           "samples": len(m)}
    first, last = rate(renders, 0.0, window), rate(renders, span - window, span)
    ok_memory = all(p["growth_pct"] < 100 * MAX_GROWTH for p in processes.values())
    ok_rate = abs(last / first - 1) <= MAX_RATE_CHANGE if first > 0 else False
    result = {
        "command": "python bench/soak.py " + " ".join(sys.argv[1:]),
        "minutes": args.minutes, "sites": args.sites, "workers": args.workers,
        "renders_per_s_first": round(first, 3), "renders_per_s_last": round(last, 3),
        "window_min": round(window / 60.0, 1),
        "rate_ratio_last_first": round(last / first, 3) if first > 0 else None,
        "renders_per_s_by_window": window_rates(renders, window),
        "renders": renders[-1][1] - renders[0][1],
        "renders_series": [[round(t, 1), n] for t, n in renders],
        "load_1min_mean": round(float(np.mean(loads)), 2),
        "load_1min_max": round(float(np.max(loads)), 2),
        "restarts": restarts, "processes": processes,
        "ledger": {s: {k: led[k] for k in ("decisions", "scored", "skipped", "lost",
                                           "lost_total", "open", "after_close")}
                   for s, led in ledgers.items()},
        "memory_ok": ok_memory, "rate_ok": ok_rate,
    }
    common.write_json(args.out, result, indent=1)
    return result


def main(argv: list[str] | None = None) -> int:
    result = run(parser().parse_args(argv))
    common.print_json(result, indent=1)
    return 0 if result["memory_ok"] and result["rate_ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
