"""Benchmark: does ``aoi3d up`` keep real time? The default pipeline at time scale 1.

For each worker count of ``--workers`` (default ``1,2``), one after the other, it starts
``aoi3d up --time-scale T --workers N`` on its own ports with nothing else changed (the
default scene, policy ``mat:70``, the stream carry at 25 steps), waits until it is up, lets it
run ``--settle-s`` wall seconds and reads a window of ``--measure-s`` (90 by default):

- **renders/s**: renders scored in the window (distinct ``decision_id`` in the metrics
  service's ``GET /quality`` among the window's decisions, read every 20 s: it keeps only
  its last 1000) per wall second;
- **rendered**: their share of the window's decisions (the scheduler's ``GET /decision`` ids
  at the window's start and end); the rest were coalesced (a newer decision replaced them
  before a worker was free: ``superseded``, the dispatcher's ``aoi3d_pool_decisions_total``) or
  lost;
- **display lag**: median and p90 of ``display_time_ms − time_ms`` of those renders, in scene
  ms (how long after its decision a render is shown);
- **PSNR at display**: median and mean ± 95 % CI of ``psnr_display_db``;
- **CPU**: every process of the run (``up.json``'s children and ``aoi3d up`` itself), its
  ``utime + stime`` from ``/proc/<pid>/stat`` (with its descendants') at the window's start
  and end: percent of one core, and its share of everything the pipeline burnt;
  ``recon_share`` is the reconstruction workers' share.

It records the machine's load average before and after each run: a figure taken beside other
work is not a figure of this machine (two cores: another busy process halves it). The
document goes to ``--out`` (default ``results/realtime/realtime.json``); ``--json``
prints it.

    python -m bench.realtime                        # 1 and 2 workers, 90 s each (about 5 min)
    python -m bench.realtime --workers 1,2,1,2      # twice each, interleaved (about 11 min)
    python -m bench.realtime --workers 2 --measure-s 30 --json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import httpx

from aoi3d_cli.pipeline import Pipeline
from bench import common, live_default
from bench.ports import BENCH_BLOCKS

PORTS = BENCH_BLOCKS["realtime"]  # apart from make up and the other benches (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): URLs, REST, /metrics."""
OUT = common.RESULTS / "realtime" / "realtime.json"
HTTP = httpx.Client(timeout=30)
WORKER_PREFIX = "recon-"
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _ticks(pid: int) -> tuple[int, int] | None:
    """(utime + stime in clock ticks, parent pid) of ``pid``, None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return int(fields[11]) + int(fields[12]), int(fields[1])


def cpu_ticks(roots: dict[str, int]) -> dict[str, int]:
    """Clock ticks burnt so far by each named process with all its descendants."""
    parent: dict[int, int] = {}
    own: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            got = _ticks(int(entry))
            if got is not None:
                own[int(entry)], parent[int(entry)] = got
    named = {pid: name for name, pid in roots.items()}
    out = dict.fromkeys(roots, 0)
    for pid, ticks in own.items():
        p, seen = pid, 0
        while p not in named and p in parent and seen < 64:  # up the tree to a named root
            p, seen = parent[p], seen + 1
        if p in named:
            out[named[p]] += ticks
    return out


def cpu_table(before: dict[str, int], after: dict[str, int], seconds: float) -> dict:
    """Percent of one core per process over ``seconds`` and each one's share of the total;
    the reconstruction workers' share beside them."""
    used = {name: max(0, after.get(name, 0) - ticks) / CLK_TCK for name, ticks in
            before.items()}
    total = sum(used.values())
    per = {name: {"core_pct": round(100.0 * s / seconds, 1),
                  "share": round(s / total, 3) if total else None}
           for name, s in sorted(used.items(), key=lambda kv: -kv[1])}
    recon = sum(s for name, s in used.items() if name.startswith(WORKER_PREFIX))
    return {"processes": per, "total_core_pct": round(100.0 * total / seconds, 1),
            "recon_share": round(recon / total, 3) if total else None}


def window_stats(history: list[dict], first_id: int, last_id: int, window_s: float) -> dict:
    """What a viewer got from the decisions ``first_id < id ≤ last_id`` (the metrics
    service's quality ``history``; :func:`bench.live_default.window_stats`), with the window's
    wall seconds: renders/s, the share rendered, the display lag (median, p90) and the PSNR at
    display time."""
    w = live_default.window_stats(history, first_id, last_id)

    def r(x: float | None, digits: int = 1) -> float | None:
        return None if x is None else round(x, digits)

    return {
        "decisions": w["decisions"], "renders": w["scored"],
        "renders_per_s": round(w["scored"] / window_s, 2) if window_s > 0 else None,
        "rendered_share": r(w["scored_share"], 3),
        "display_lag_ms_median": r(w["display_lag_ms_median"]),
        "display_lag_ms_p90": r(w["display_lag_ms_p90"]),
        "psnr_display_db_median": r(w["psnr_display_db_median"], 2),
        "psnr_display_db": w["psnr_display_db"],
    }


def _get(service: str, path: str, **params: int) -> dict:
    return PIPE.get(service, path, **params)


def _pool() -> dict[str, float]:
    """The pool's counters so far (the dispatcher's /metrics): decisions superseded (every site),
    and the sums and counts of the hand-out wait and the render age (wall seconds)."""
    series = PIPE.metrics("dispatcher")
    out = {"superseded": sum(v for k, v in series.items()
                             if k.startswith("aoi3d_pool_decisions_total{")
                             and 'outcome="superseded"' in k)}
    for name in ("wait", "render_age"):
        for part in ("sum", "count"):
            out[f"{name}_{part}"] = series.get(f"aoi3d_pool_{name}_seconds_{part}", 0.0)
    return out


def _pool_window(before: dict[str, float], after: dict[str, float]) -> dict:
    """The window's superseded decisions and mean hand-out wait and render age (wall ms)."""
    out: dict = {"superseded": int(after["superseded"] - before["superseded"])}
    for name in ("wait", "render_age"):
        n = after[f"{name}_count"] - before[f"{name}_count"]
        s = after[f"{name}_sum"] - before[f"{name}_sum"]
        out[f"pool_{name}_ms_mean"] = round(1000.0 * s / n, 1) if n > 0 else None
    return out


HISTORY_POLL_S = 20.0
"""How often the window's quality is read: the metrics service keeps its last ``history``
(1000 by default) results, 70 s of renders at 14 a second, so one read after a 90 s window
would miss its first renders."""


def _collect(scored: dict[int, dict]) -> None:
    """The metrics service's quality history so far, merged into ``scored`` by decision."""
    for q in _get("metrics", "/quality", limit=1_000_000)["history"]:
        scored[q["decision_id"]] = q


def _children(log_dir: Path) -> dict[str, int]:
    doc = json.loads((log_dir / "latest" / "up.json").read_text())
    return {name: c["pid"] for name, c in doc["children"].items() if c["pid"]}


def run_one(workers: int, args: argparse.Namespace) -> dict:
    """One worker count: ``aoi3d up`` started, measured and stopped; its row."""
    log_dir = common.ROOT / "runs" / "bench-realtime"
    load_before = os.getloadavg()
    up = PIPE.start(["--time-scale", str(args.time_scale), "--workers", str(workers)],
                    run_id="realtime", log_dir=log_dir, cwd=common.ROOT)
    try:
        up.wait(
            f"the pipeline up (see {log_dir}/latest/)",
            lambda: len(_get("dispatcher", "/workers")["workers"]) >= workers
            and _get("scheduler", "/decision")["decision_id"] >= 0,
            args.ready_timeout_s)
        time.sleep(args.settle_s)
        procs = {**_children(log_dir), "up": up.pid}
        first_id = _get("scheduler", "/decision")["decision_id"]
        pool0 = _pool()
        ticks0, t0 = cpu_ticks(procs), time.monotonic()
        scored: dict[int, dict] = {}
        while (left := args.measure_s - (time.monotonic() - t0)) > 0:
            time.sleep(min(left, HISTORY_POLL_S))
            _collect(scored)
        ticks1, window_s = cpu_ticks(procs), time.monotonic() - t0
        last = _get("scheduler", "/decision")
        pool1 = _pool()
        time.sleep(args.grace_s)  # the window's last renders are scored later
        _collect(scored)
        status = _get("dispatcher", "/status")
    finally:
        up.stop(90)
    return {
        "workers": workers, "time_scale": args.time_scale, "carry": status["carry"],
        "render_steps": status["render_steps"], "policy": last["policy"],
        "fresh_fraction": (status.get("pool") or {}).get("fresh_fraction"),
        "window_s": round(window_s, 1), "first_id": first_id, "last_id": last["decision_id"],
        **window_stats(list(scored.values()), first_id, last["decision_id"], window_s),
        **_pool_window(pool0, pool1),
        "cpu": cpu_table(ticks0, ticks1, window_s),
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
    }


def speedup(rows: list[dict]) -> dict:
    """``speedup``: the mean renders/s of the largest worker count over the smallest's (their
    runs in any order, e.g. ``--workers 1,2,1,2``); ``speedup_pairs``: each run of the
    largest over the run of the smallest before it. Empty until both counts ran."""
    by: dict[int, list[float]] = {}
    for r in rows:
        if r["renders_per_s"]:
            by.setdefault(r["workers"], []).append(r["renders_per_s"])
    if len(by) < 2:
        return {}
    lo, hi = min(by), max(by)
    out: dict = {"speedup": round(statistics.mean(by[hi]) / statistics.mean(by[lo]), 2)}
    pairs, base = [], None
    for r in rows:
        if r["workers"] == lo and r["renders_per_s"]:
            base = r["renders_per_s"]
        elif r["workers"] == hi and base and r["renders_per_s"]:
            pairs.append(round(r["renders_per_s"] / base, 2))
    out["speedup_pairs"] = pairs
    return out


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", default="1,2",
                    help="comma-separated worker counts (aoi3d up --workers), run back to back")
    ap.add_argument("--time-scale", type=float, default=1.0, help="aoi3d up --time-scale")
    ap.add_argument("--settle-s", type=float, default=30.0,
                    help="wall seconds from the pipeline's start-up to the window")
    ap.add_argument("--measure-s", type=float, default=90.0, help="the window, wall seconds")
    ap.add_argument("--grace-s", type=float, default=5.0,
                    help="wall seconds after the window before the quality is read")
    ap.add_argument("--ready-timeout-s", type=float, default=240.0)
    ap.add_argument("--out", type=Path, default=OUT, help="the JSON file written")
    common.add_json_option(ap, help="print the result document as JSON")
    return ap


def run(args: argparse.Namespace) -> dict:
    """Every worker count of ``args.workers`` (``parser()``'s options), back to back; writes
    ``args.out`` and returns the result document (with :func:`speedup`'s figures)."""
    counts = [int(w) for w in str(args.workers).split(",")]
    if any(w < 1 for w in counts):
        raise SystemExit(f"--workers {args.workers}: counts must be >= 1")
    out = Path(args.out).resolve()
    rows: list[dict] = []
    doc: dict = {"rows": rows,
                 "command": " ".join(["python", "-m", "bench.realtime", *sys.argv[1:]]),
                 "cpus": os.cpu_count(),
                 "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    for workers in counts:
        row = run_one(workers, args)
        rows.append(row)
        doc.update(speedup(rows))
        common.write_json(out, doc)  # after each run: a cut run keeps its rows
        top = ", ".join(f"{name} {p['core_pct']}" for name, p in
                        list(row["cpu"]["processes"].items())[:6])
        print(f"{workers} worker(s) at x{args.time_scale}: {row['renders_per_s']} renders/s, "
              f"{(row['rendered_share'] or 0) * 100:.1f} % of {row['decisions']} decisions "
              f"rendered, display lag median {row['display_lag_ms_median']} / p90 "
              f"{row['display_lag_ms_p90']} ms, PSNR at display median "
              f"{row['psnr_display_db_median']} dB; recon {row['cpu']['recon_share']} of the "
              f"CPU ({top} % of a core); load {row['load_before'][0]} → "
              f"{row['load_after'][0]}", flush=True)
    return doc


def main(argv: list[str] | None = None) -> None:
    common.bench_main(parser(), run, argv)


if __name__ == "__main__":
    main()
