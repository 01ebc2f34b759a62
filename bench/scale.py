"""Benchmark: how the live pipeline scales with reconstruction workers (issue 22, part 4).

For each configuration in ``--configs`` (``KxS``: K workers, S sites; default 1x1,2x1,3x1,2x2)
it starts ``aoi3d up --workers K --sites S`` on its own ports with the default scene and
policy, lets it settle ``--settle-s``, then measures
``--measure-s`` wall seconds from the services' counters: renders per wall second, the
fraction of decisions rendered, the mean wait from a decision to its hand-out and the mean
render age (the dispatcher's pool summaries), each worker's busy fraction, the decisions lost,
the PSNR of the window's renders (mean ± 95 % CI, from the metrics service), and the Zenoh
bytes per second of the run (a subscriber on ``aoi3d/<run>/**`` counting payload bytes: the
traffic one site puts through a router; in a window of its own after the renders', since the
subscriber costs CPU), and the cores each process of the pipeline used in the window. It
ends with the arithmetic for a larger farm from the measured per-worker throughput and
per-site bytes.

    python -m bench.scale --json                  # results/scale.json, and one JSON object
    python -m bench.scale --configs 1x1,2x1 --measure-s 90 --repeats 2
    python -m bench.scale --configs 2x1:fresh@100,2x1:stream@25 --time-scale 0.3

A configuration may name the dispatcher's carry and render steps (``KxS:carry@steps``): the
streaming warm start (``stream``, the default since issue 40) beside ``fresh`` in the same
run (issue 33); without, the dispatcher's defaults (the row's ``carry`` says which); and its field
backend (``KxS:carry@steps:backend``, ``AOI3D_DISPATCHER_BACKEND``): the time-aware ``flow``
field, rendered at the display time, beside the static grid (issue 41):

    python -m bench.scale --configs 2x1:stream@25,2x1:stream@16:flow --time-scale 0.3

The machine's other load is recorded (load average before and after each run).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import httpx

from aoi3d.stats import mean_ci95
from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

ROOT = common.ROOT
PORTS = BENCH_BLOCKS["scale"]  # apart from a running `make up` (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): URLs, REST, /metrics."""
DEFAULT_DATASET = ROOT / "data" / "turbine-rotor"
HTTP = httpx.Client(timeout=30)


def scrape(service: str) -> dict[str, float]:
    """Series of a service's /metrics, summed over labels, plus each labelled sample."""
    return PIPE.metrics(service)


class ByteTap(common.Tap):
    """Counts the payload bytes of every message of the run (all keys)."""

    def __init__(self, run_id: str) -> None:
        self.bytes = 0
        self.messages = 0
        super().__init__(PORTS, {f"aoi3d/{run_id}/**": self._on})

    def _on(self, sample) -> None:
        n = len(sample.payload)
        with self.lock:
            self.bytes += n
            self.messages += 1

    def read(self) -> tuple[int, int]:
        with self.lock:
            return self.bytes, self.messages


def tree_cpu_s(root: int) -> dict[str, float]:
    """CPU seconds (user + system) so far of every process under ``root``, by a short name
    (the module it runs, numbered when repeated): where the machine's cores go."""
    tick = os.sysconf("SC_CLK_TCK")
    procs: dict[int, tuple[int, float, str]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            argv = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        ppid, cpu = int(fields[1]), (int(fields[11]) + int(fields[12])) / tick
        args_ = [a.decode(errors="replace") for a in argv if a]
        name = next((args_[i + 1] for i, a in enumerate(args_[:-1]) if a == "-m"),
                    Path(args_[0]).name if args_ else d.name)
        procs[int(d.name)] = (ppid, cpu, name.removeprefix("services."))
    keep, frontier = {}, [root]
    while frontier:
        pid = frontier.pop()
        for child, (ppid, cpu, name) in procs.items():
            if ppid == pid and child not in keep:
                keep[child] = (cpu, name)
                frontier.append(child)
    out: dict[str, float] = {}
    for _pid, (cpu, name) in sorted(keep.items()):
        key, i = name, 2
        while key in out:
            key, i = f"{name}-{i}", i + 1
        out[key] = cpu
    return out


def parse_config(text: str) -> tuple[int, int, str | None, int | None, str | None]:
    """``KxS``, ``KxS:carry@steps`` (e.g. ``2x1:stream@25``) or ``KxS:carry@steps:backend``
    (``2x1:stream@16:flow``): workers, sites and the dispatcher's carry, render steps and field
    backend (None: the dispatcher's defaults)."""
    size, _, render = text.partition(":")
    render, _, backend = render.partition(":")
    k, _, sites = size.partition("x")
    carry, steps = None, None
    if render:
        carry, _, budget = render.partition("@")
        steps = int(budget) if budget else None
    return int(k), int(sites), carry or None, steps, backend or None


def run_one(workers: int, sites: int, args: argparse.Namespace, carry: str | None = None,
            render_steps: int | None = None, backend: str | None = None) -> dict:
    run_id = f"scale{workers}x{sites}"
    log_dir = ROOT / "runs" / "bench-scale"
    load_before = os.getloadavg()
    env = dict(os.environ)
    if backend is not None:
        env["AOI3D_DISPATCHER_BACKEND"] = backend
    if carry is not None:
        env["AOI3D_DISPATCHER_CARRY"] = carry
    if render_steps is not None:
        env["AOI3D_DISPATCHER_RENDER_STEPS"] = str(render_steps)
    up = PIPE.start([
        "--dataset", str(args.dataset), "--time-scale", str(args.time_scale),
        "--workers", str(workers), "--sites", str(sites)], run_id=run_id, log_dir=log_dir,
        env=env, cwd=ROOT)
    tap = None
    try:
        up.wait(
            f"the pipeline with {workers} workers up (see {log_dir}/latest/)",
            lambda: len(HTTP.get(PORTS.url("dispatcher", "/workers")).json()["workers"]) == workers
            and HTTP.get(PORTS.url("metrics", "/healthz")).status_code == 200,
            args.ready_timeout_s)
        time.sleep(args.settle_s)
        first = {s: scrape(s) for s in ("dispatcher", "scheduler", "metrics")}
        cpu0 = tree_cpu_s(up.pid)
        names = [f"site{i}" for i in range(1, sites + 1)]

        def ids() -> dict[str, int]:
            return {n: HTTP.get(PORTS.url("scheduler", f"/sites/{n}/decision")
                                ).json()["decision_id"] for n in names}

        decision0 = ids()
        t0 = time.monotonic()
        time.sleep(args.measure_s)
        last = {s: scrape(s) for s in ("dispatcher", "scheduler", "metrics")}
        cpu1 = tree_cpu_s(up.pid)
        decision1 = ids()
        dt = time.monotonic() - t0
        pool = HTTP.get(PORTS.url("dispatcher", "/workers")).json()
        in_force = HTTP.get(PORTS.url("dispatcher", "/status")).json()["carry"]
        # Bytes in a window of their own, after the renders' window: a subscriber to every key
        # makes the router send everything twice and costs this process CPU, which the
        # workers would otherwise have had.
        tap = ByteTap(run_id)
        time.sleep(1.0)
        bytes0, msgs0 = tap.read()
        tb = time.monotonic()
        time.sleep(args.bytes_s)
        bytes1, msgs1 = tap.read()
        dtb = time.monotonic() - tb
        time.sleep(max(0.0, 5.0 - args.bytes_s))  # the window's last renders are scored later
        history = {n: HTTP.get(PORTS.url("metrics", f"/sites/{n}/quality"),
                               params={"limit": 100000}).json()["history"] for n in names}
    finally:
        if tap is not None:
            tap.close()
        up.stop(90)

    def delta(service: str, name: str) -> float:
        return last[service].get(name, 0.0) - first[service].get(name, 0.0)

    window = [q for n in names for q in history[n]
              if decision0[n] < q["decision_id"] <= decision1[n]]
    series = 'aoi3d_pool_decisions_total{{outcome="rendered",site="{}"}}'
    by_site = {n: delta("dispatcher", series.format(n)) for n in names}
    rendered = sum(by_site.values())
    taken = delta("dispatcher", "aoi3d_dispatcher_decisions_total")
    wait_n = delta("dispatcher", "aoi3d_pool_wait_seconds_count")
    age_n = delta("dispatcher", "aoi3d_pool_render_age_seconds_count")
    return {
        "workers": workers, "sites": sites, "window_s": round(dt, 1),
        "carry": carry or f"{in_force} (default)", "render_steps": render_steps,
        "backend": backend or "grid (default)",
        "time_scale": args.time_scale,
        "renders_per_s": rendered / dt,
        "decisions_per_s": taken / dt,
        "fraction_rendered": rendered / taken if taken else None,
        "fraction_warm_start": (delta("dispatcher", "aoi3d_renders_warm_start_total")
                                / delta("dispatcher", "aoi3d_renders_total")
                                if delta("dispatcher", "aoi3d_renders_total") else None),
        "scored_per_s": delta("metrics", "aoi3d_quality_total") / dt,
        "wait_s_mean": (delta("dispatcher", "aoi3d_pool_wait_seconds_sum") / wait_n
                        if wait_n else None),
        "render_age_s_mean": (delta("dispatcher", "aoi3d_pool_render_age_seconds_sum") / age_n
                              if age_n else None),
        "busy_fraction": {w["worker_id"]: w["busy_fraction"] for w in pool["workers"]},
        "lost": pool["lost"],
        "psnr_db": mean_ci95([q["psnr_db"] for q in window]).to_dict(),
        "psnr_dynamic_db": mean_ci95([q.get("psnr_dynamic_db") for q in window]).to_dict(),
        "psnr_display_db": mean_ci95([q.get("psnr_display_db") for q in window]).to_dict(),
        "psnr_dynamic_display_db": mean_ci95([q.get("psnr_dynamic_display_db")
                                              for q in window]).to_dict(),
        "display_lag_ms_mean": mean_ci95([q["display_time_ms"] - q["time_ms"] for q in window
                                          if q.get("display_time_ms") is not None]
                                         ).to_dict()["mean"],
        "views": mean_ci95([q["n_views"] for q in window]).to_dict(),
        "renders_per_s_by_site": {n: v / dt for n, v in by_site.items()},
        "zenoh_bytes_per_s": (bytes1 - bytes0) / dtb,
        "zenoh_messages_per_s": (msgs1 - msgs0) / dtb,
        "cores_by_process": {k: round((cpu1[k] - cpu0.get(k, 0.0)) / dt, 3)
                             for k in cpu1 if k in cpu0},
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
    }


def farm(rows: list[dict], sites: int, cameras: int, time_scale: float) -> dict:
    """The arithmetic for ``sites`` sites from the measured rows (the medians of the ``1x1``
    passes): worker cores to render every decision, and router bandwidth."""
    ones = [r for r in rows if r["workers"] == 1 and r["sites"] == 1]
    per_worker = statistics.median(r["renders_per_s"] for r in ones)
    decisions = statistics.median(r["decisions_per_s"] for r in ones) * sites
    site_bytes = statistics.median(r["zenoh_bytes_per_s"] for r in ones) * cameras / 18
    return {
        "sites": sites, "cameras_per_site": cameras, "time_scale": time_scale,
        "renders_per_s_per_worker": per_worker,
        "decisions_per_s": decisions,
        "workers_to_render_every_decision": math.ceil(decisions / per_worker)
        if per_worker else None,
        "router_bytes_per_s": site_bytes * sites,
        "note": "one worker = one core at one torch thread (measured on this machine, beside "
                "the rest of the pipeline); bytes scale with cameras and sites, renders with "
                "decisions; at time scale 1 multiply decisions and bytes by 1/time_scale",
    }


def speedups(rows: list[dict]) -> dict | None:
    """Renders/s of each configuration over ``1x1``'s: of the medians over the passes, and
    pass by pass (each pass's configurations ran back to back, so a pass shares its load)."""
    def label(r: dict) -> str:
        render = f":{r['carry']}@{r['render_steps']}" if r.get("render_steps") else ""
        backend = r.get("backend", "")
        field = f":{backend}" if backend and not backend.startswith("grid") else ""
        return f"{r['workers']}x{r['sites']}{render}{field}"

    by: dict[str, list[float]] = {}
    for r in rows:
        by.setdefault(label(r), []).append(r["renders_per_s"])
    if not by.get("1x1") or not statistics.median(by["1x1"]):
        return None
    base = statistics.median(by["1x1"])
    out: dict = {name: statistics.median(v) / base for name, v in by.items()}
    passes = sorted({r.get("pass", 1) for r in rows})
    if len(passes) > 1:
        per = {}
        for p in passes:
            one = {label(r): r["renders_per_s"] for r in rows if r.get("pass", 1) == p}
            if one.get("1x1"):
                per[str(p)] = {name: v / one["1x1"] for name, v in one.items()}
        out["by_pass"] = per
    return out


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default="1x1,2x1,3x1,2x2",
                    help="KxS: K workers, S sites, optionally :carry@steps (the dispatcher's "
                         "carry and render steps, e.g. 2x1:stream@25) and :backend (its "
                         "field, e.g. 2x1:stream@16:flow); comma-separated")
    ap.add_argument("--time-scale", type=float, default=0.1)
    ap.add_argument("--settle-s", type=float, default=20.0)
    ap.add_argument("--measure-s", type=float, default=60.0)
    ap.add_argument("--repeats", type=int, default=1,
                    help="passes over --configs (interleaved, so drift hits every one); the "
                         "speedup is of the medians")
    ap.add_argument("--bytes-s", type=float, default=10.0,
                    help="wall seconds of the Zenoh byte count, after the renders' window")
    ap.add_argument("--ready-timeout-s", type=float, default=180.0)
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET,
                    help="the scene (default: the live pipeline's, generated when missing)")
    ap.add_argument("--out", type=Path, default=common.RESULTS / "scale.json",
                    help="the JSON file written")
    common.add_json_option(ap, help="print one JSON object")
    return ap


def run(args: argparse.Namespace) -> dict:
    """Every configuration of ``args.configs`` (``parser()``'s options); writes ``args.out``
    and returns the result document."""
    if Path(args.dataset) == DEFAULT_DATASET:  # generated when missing ("up to date" if not)
        subprocess.run([sys.executable, "-m", "aoi3d_cli", "scene", "generate", "--out",
                        args.dataset], check=True,
                       stdout=sys.stderr if getattr(args, "json", False) else None)  # --json:
        # stdout is the result document alone
    elif not Path(args.dataset).is_dir():
        raise SystemExit(f"no dataset at {args.dataset} (aoi3d scene generate --out …)")
    configs = [parse_config(c) for c in args.configs.split(",")]
    rows = []
    for rep in range(args.repeats):
        for k, sites, carry, steps, backend in configs:
            row = run_one(k, sites, args, carry, steps, backend)
            row["pass"] = rep + 1
            rows.append(row)
            if not args.json:
                print(f"pass {rep + 1}, workers {k}, sites {sites}, {row['carry']}"
                      f"{'@' + str(steps) if steps else ''}, {row['backend']}: "
                      f"{row['renders_per_s']:.3f} renders/s, "
                      f"{row['fraction_rendered']:.2f} of decisions, age "
                      f"{row['render_age_s_mean']:.2f} s, PSNR {row['psnr_db']['mean']:.2f} ± "
                      f"{row['psnr_db']['ci95'] or 0:.2f} dB (at display "
                      f"{row['psnr_display_db']['mean'] or math.nan:.2f}), load "
                      f"{row['load_after'][0]}",
                      flush=True)
    base = next((r for r in rows if r["workers"] == 1 and r["sites"] == 1), None)
    doc = {"rows": rows,
           "speedup": speedups(rows),
           "farm": farm(rows, 10, 18, args.time_scale) if base else None,
           "command": " ".join(["python", "bench/scale.py", *sys.argv[1:]]),
           "cpus": os.cpu_count()}
    common.write_json(args.out, doc)
    return doc


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    doc = run(args)
    if args.json:
        common.print_json(doc)
    else:
        print(f"written: {args.out}")


if __name__ == "__main__":
    main()
