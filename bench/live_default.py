"""Benchmark: what a viewer of ``aoi3d up`` gets with a configuration (issue 40, §4).

For each configuration of ``--configs``, one after the other, it starts ``aoi3d up
--time-scale T`` on its own ports with no other option (the default scene, policy and
``--workers auto``): ``default`` is the dispatcher's defaults as they are, ``CARRY@STEPS`` sets
``AOI3D_DISPATCHER_CARRY`` and ``AOI3D_DISPATCHER_RENDER_STEPS`` (``stream@25``, ``fresh@100``),
and either followed by ``/POLICY`` sets the scheduler's ``AOI3D_SCHEDULER_POLICY``
(``default/all``, ``stream@25/mat:130``), exactly as a user of the environment would. It
waits until the pipeline is up, lets it run ``--settle-s`` wall seconds and reads a window of
``--measure-s`` (so ``--settle-s 40 --measure-s 60`` is "100 s, the last 60 read"):

- **scored**: the share of the window's decisions (the ids the scheduler's ``GET /decision``
  gave at the window's start and end) whose render was scored (distinct ``decision_id`` in the
  metrics service's ``GET /quality``, read ``--grace-s`` after the window so that its last
  renders are in); beside it the same count over the span of the scored ids, and the
  ledger's change over the window (``GET /ledger``);
- **display lag**: the median (and mean) of ``display_time_ms − time_ms`` of those renders, in
  scene ms: how long after its decision a render is shown;
- **PSNR** at decision and at display time: median and mean ± 95 % CI of those renders.

It records what the run had in force (the dispatcher's ``GET /status``: carry and render steps;
the policy of the last decision; the pool's workers) and the machine's load average before
and after each configuration. The document goes to ``--out`` (default
``results/live-default/live-default.json``); ``--json`` prints it.

    python -m bench.live_default                                # the defaults as they are
    python -m bench.live_default --configs default,stream@25 --out \\
        results/live-default/before.json                  # defaults beside stream@25
    python -m bench.live_default --configs fresh@100 --time-scale 0.3 --json
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import httpx

from aoi3d.policy import parse_policy
from aoi3d.stats import mean_ci95
from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

PORTS = BENCH_BLOCKS["live_default"]  # apart from make up and the other benches (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): URLs, REST, /metrics."""
OUT = common.RESULTS / "live-default" / "live-default.json"
HTTP = httpx.Client(timeout=30)
CARRY_ENV = ("AOI3D_DISPATCHER_CARRY", "AOI3D_DISPATCHER_RENDER_STEPS")
POLICY_ENV = "AOI3D_SCHEDULER_POLICY"


def parse_config(text: str) -> tuple[str, dict[str, str]]:
    """``default`` or ``CARRY@STEPS``, optionally ``/POLICY``: the configuration's label and
    the environment it sets (``ValueError`` for anything else)."""
    text = text.strip()
    render, slash, policy = text.partition("/")
    env: dict[str, str] = {}
    if slash:
        try:
            parse_policy(policy)
        except ValueError as err:
            raise ValueError(f"configuration {text!r}: {err}") from None
        env[POLICY_ENV] = policy
    if render == "default":
        return text, env
    carry, sep, steps = render.partition("@")
    if not sep or not carry or not steps.isdigit() or int(steps) < 1:
        raise ValueError(f"configuration {text!r}: expected 'default' or CARRY@STEPS "
                         "(stream@25, fresh@100), optionally /POLICY (default/all)")
    return text, {**dict(zip(CARRY_ENV, (carry, steps), strict=True)), **env}


def window_stats(history: list[dict], first_id: int, last_id: int) -> dict:
    """What the viewer got from the decisions ``first_id < id ≤ last_id``, given the metrics
    service's quality entries (``history``): the share scored, the display lag and the PSNR at
    decision and at display time (median; mean ± 95 % CI)."""
    made = last_id - first_id
    entries = {q["decision_id"]: q for q in history if first_id < q["decision_id"] <= last_id}
    rows = list(entries.values())
    span = (max(entries) - min(entries) + 1) if entries else 0
    lags = [q["display_time_ms"] - q["time_ms"] for q in rows
            if q.get("display_time_ms") is not None]
    psnr = [q["psnr_db"] for q in rows]
    display = [q["psnr_display_db"] for q in rows if q.get("psnr_display_db") is not None]

    def median(xs: list[float]) -> float | None:
        return statistics.median(xs) if xs else None

    return {
        "decisions": made, "scored": len(entries),
        "scored_share": len(entries) / made if made > 0 else None,
        "scored_share_of_span": len(entries) / span if span else None,
        "display_lag_ms_median": median(lags),
        "display_lag_ms_p90": (float(statistics.quantiles(lags, n=10)[8]) if len(lags) >= 2
                               else None),
        "display_lag_ms_mean": mean_ci95(lags).to_dict(),
        "psnr_db_median": median(psnr), "psnr_db": mean_ci95(psnr).to_dict(),
        "psnr_display_db_median": median(display),
        "psnr_display_db": mean_ci95(display).to_dict(),
    }


def _get(service: str, path: str, **params: int) -> dict:
    return PIPE.get(service, path, **params)


def _ledger() -> dict:
    doc = _get("metrics", "/ledger")
    return {"decisions": doc["decisions"], "scored": doc["scored"],
            "skipped": sum(doc["skipped"].values()), "lost": doc["lost_total"]}


def run_one(label: str, env_extra: dict[str, str], args: argparse.Namespace) -> dict:
    """One configuration: ``aoi3d up`` started, measured and stopped; its row."""
    log_dir = common.ROOT / "runs" / "bench-live-default"
    load_before = os.getloadavg()
    env = {k: v for k, v in os.environ.items() if k not in (*CARRY_ENV, POLICY_ENV)}
    env.update(env_extra)
    up = PIPE.start(["--time-scale", str(args.time_scale)], run_id="livedefault",
                    log_dir=log_dir, env=env, cwd=common.ROOT)
    try:
        up.wait(
            f"the pipeline up (see {log_dir}/latest/)",
            lambda: _get("dispatcher", "/workers")["workers"]
            and _get("metrics", "/healthz") is not None
            and _get("scheduler", "/decision")["decision_id"] >= 0,
            args.ready_timeout_s)
        time.sleep(args.settle_s)
        first_id = _get("scheduler", "/decision")["decision_id"]
        ledger0 = _ledger()
        t0 = time.monotonic()
        time.sleep(args.measure_s)
        last = _get("scheduler", "/decision")
        window_s = time.monotonic() - t0
        ledger1 = _ledger()
        time.sleep(args.grace_s)  # the window's last renders are scored later
        history = _get("metrics", "/quality", limit=1_000_000)["history"]
        status = _get("dispatcher", "/status")
        pool = _get("dispatcher", "/workers")
    finally:
        up.stop(90)
    return {
        "config": label, "env": env_extra, "time_scale": args.time_scale,
        "carry": status["carry"], "render_steps": status["render_steps"],
        "policy": last["policy"], "workers": len(pool["workers"]),
        "window_s": round(window_s, 1), "first_id": first_id, "last_id": last["decision_id"],
        **window_stats(history, first_id, last["decision_id"]),
        "ledger_window": {k: ledger1[k] - ledger0[k] for k in ledger0},
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
    }


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default="default",
                    help="comma-separated: 'default' (the dispatcher's defaults) or CARRY@STEPS "
                         "(AOI3D_DISPATCHER_CARRY, AOI3D_DISPATCHER_RENDER_STEPS), optionally "
                         "/POLICY (AOI3D_SCHEDULER_POLICY), run back to back")
    ap.add_argument("--time-scale", type=float, default=0.3, help="aoi3d up --time-scale")
    ap.add_argument("--settle-s", type=float, default=40.0,
                    help="wall seconds from the pipeline's start-up to the window")
    ap.add_argument("--measure-s", type=float, default=60.0, help="the window, wall seconds")
    ap.add_argument("--grace-s", type=float, default=5.0,
                    help="wall seconds after the window before the quality is read")
    ap.add_argument("--ready-timeout-s", type=float, default=240.0)
    ap.add_argument("--out", type=Path, default=OUT, help="the JSON file written")
    common.add_json_option(ap, help="print the result document as JSON")
    return ap


def run(args: argparse.Namespace) -> dict:
    """Every configuration of ``args.configs`` (``parser()``'s options), back to back; writes
    ``args.out`` and returns the result document."""
    configs = [parse_config(c) for c in args.configs.split(",")]
    out = Path(args.out).resolve()  # before anything runs: a relative path, from here
    rows: list[dict] = []
    doc = {"rows": rows,
           "command": " ".join(["python", "-m", "bench.live_default", *sys.argv[1:]]),
           "cpus": os.cpu_count(),
           "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    with common.progress_to_stderr(args.json):
        for label, env in configs:
            row = run_one(label, env, args)
            rows.append(row)
            common.write_json(out, doc)  # after each configuration: a cut run keeps its rows
            print(f"{label} ({row['carry']}@{row['render_steps']}, {row['policy']}, "
                  f"{row['workers']} workers): scored {row['scored']} of {row['decisions']} "
                  f"({(row['scored_share'] or 0) * 100:.1f} %), display lag median "
                  f"{row['display_lag_ms_median']} ms, PSNR median {row['psnr_db_median']} "
                  f"dB, at display {row['psnr_display_db_median']} dB; load "
                  f"{row['load_before'][0]} → {row['load_after'][0]}", flush=True)
    return doc


def main(argv: list[str] | None = None) -> None:
    common.bench_main(parser(), run, argv)


if __name__ == "__main__":
    main()
