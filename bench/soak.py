"""Soak: run the whole pipeline for a long time and record each process's memory.

Starts ``aoi3d up`` (default scene and settings, its own ports), samples the resident memory
(RSS, from /proc) of the router and every service every ``--every-s`` seconds for
``--minutes``, and checks that Quality keeps flowing. The JSON gives, per process, the RSS
after the warm-up, at the end, the growth and a least-squares slope in MiB per hour, plus the
restarts `aoi3d up` made and the Quality count.

    python bench/soak.py                  # 30 min, JSON to bench/results/soak.json
    python bench/soak.py --minutes 3      # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OFFSET, ZENOH = 4000, 9467


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--every-s", type=float, default=30.0)
    parser.add_argument("--warmup-s", type=float, default=60.0)
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/soak.json")
    args = parser.parse_args()
    log_dir = ROOT / "runs" / "bench-soak"
    up = subprocess.Popen([sys.executable, "-m", "aoi3d", "up", "--run-id", "soak",
                           "--port-offset", str(OFFSET), "--zenoh-port", str(ZENOH),
                           "--log-dir", str(log_dir), "--quiet"], cwd=ROOT,
                          stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                          start_new_session=True)
    quality = f"http://127.0.0.1:{8105 + OFFSET}/quality"
    samples: dict[str, list[tuple[float, float]]] = {}
    try:
        time.sleep(args.warmup_s)
        t0 = time.monotonic()
        end = t0 + args.minutes * 60.0
        scored0 = None
        while True:
            state = json.loads((log_dir / "latest" / "up.json").read_text())
            now = time.monotonic() - t0
            for name, child in state["children"].items():
                mib = rss_mib(child["pid"])
                if mib is not None:
                    samples.setdefault(name, []).append((now, mib))
            summary = httpx.get(quality, timeout=30).json()["summary"]
            scored0 = summary["scored_total"] if scored0 is None else scored0
            if time.monotonic() >= end:
                break
            time.sleep(min(args.every_s, max(0.0, end - time.monotonic())))
        restarts = {n: c["restarts"] for n, c in state["children"].items()}
        scored = summary["scored_total"] - scored0
    finally:
        up.send_signal(signal.SIGTERM)
        up.wait(timeout=60)
    processes = {}
    for name, points in samples.items():
        t, m = np.array(points).T
        slope = float(np.polyfit(t / 3600.0, m, 1)[0]) if len(t) > 2 else None
        processes[name] = {"rss_start_mib": round(m[0], 1), "rss_end_mib": round(m[-1], 1),
                           "growth_mib": round(m[-1] - m[0], 1),
                           "slope_mib_per_hour": None if slope is None else round(slope, 1),
                           "samples": len(m)}
    result = {"command": " ".join(sys.argv), "minutes": args.minutes,
              "load_1min_at_end": os.getloadavg()[0], "quality_scored": scored,
              "restarts": restarts, "processes": processes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
