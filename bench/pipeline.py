"""Benchmark: the live pipeline on this machine, as `make up` runs it.

Starts ``aoi3d up`` on its own ports with the default scene, sets the policy, and after
``--warmup-s`` samples every counter twice, ``--window-s`` apart: frames offered/delivered
per second through camera → network, decisions per second, the dispatcher's steps per second,
the quality of the renders of the window's decisions (mean ± 95% CI), and how late they come:
the render lag (sim ms from the time a render represents to its scoring) and the same in wall
seconds. Writes ``results/pipeline-<policy>-x<time scale>.json``.

    python -m bench.pipeline --policy mat:70 --window-s 60 --time-scale 1
"""

from __future__ import annotations

import argparse
import statistics
import time

import httpx

from aoi3d_cli.common import control_headers
from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

ROOT = common.ROOT
BLOCK = BENCH_BLOCKS["pipeline"]  # apart from a running `make up` (bench/ports.py)
PIPE = Pipeline(BLOCK, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): URLs, REST, /metrics."""
SERVICES = ("camera", "network", "scheduler", "dispatcher", "metrics")  # the ones measured


def scrape(service: str) -> dict[str, float]:
    return PIPE.metrics(service)


def policy_body(spec: str) -> dict:
    """The scheduler's ``PUT /policy`` body: the policy's own JSON form."""
    from aoi3d.policy import parse_policy

    return parse_policy(spec).to_json()


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", default="mat:70", help="all | mat:<ms> | freshest:<k>")
    ap.add_argument("--time-scale", type=float, default=0.1)
    ap.add_argument("--warmup-s", type=float, default=10.0)
    ap.add_argument("--window-s", type=float, default=60.0)
    ap.add_argument("--dataset", default=str(ROOT / "data" / "turbine-rotor"))
    common.add_json_option(ap)
    return ap


def run(args: argparse.Namespace) -> dict:
    """One measurement (``parser()``'s options); writes and returns the result document."""

    log_dir = ROOT / "runs" / "bench-pipeline"
    up = PIPE.start(["--dataset", args.dataset, "--time-scale", str(args.time_scale)],
                    run_id="bench", log_dir=log_dir, cwd=ROOT)
    try:
        up.wait(
            "the pipeline up (see runs/bench-pipeline/)",
            lambda: all(httpx.get(BLOCK.url(s, "/healthz"), timeout=1).status_code == 200
                        for s in SERVICES), 120)
        t_ready = time.monotonic()
        r = httpx.put(BLOCK.url("scheduler", "/policy"),
                      json=policy_body(args.policy), headers=control_headers(), timeout=60)
        r.raise_for_status()
        time.sleep(args.warmup_s)
        first = {s: scrape(s) for s in SERVICES}
        decision = BLOCK.url("scheduler", "/decision")
        id0 = httpx.get(decision, timeout=30).json()["decision_id"]
        t0 = time.monotonic()
        time.sleep(args.window_s)
        last = {s: scrape(s) for s in SERVICES}
        id1 = httpx.get(decision, timeout=30).json()["decision_id"]
        dt = time.monotonic() - t0
        status = httpx.get(BLOCK.url("dispatcher", "/status"), timeout=30).json()
        # the window's last decisions are rendered a render's compute later
        rate_now = status.get("steps_per_s") or 1.0
        time.sleep(min(120.0, 2.0 + 1.5 * (status.get("render_steps") or 0) / rate_now))
        history = httpx.get(BLOCK.url("metrics", "/quality"),
                            params={"limit": 100000}).json()["history"]
    finally:
        up.stop(60)

    def rate(service: str, name: str) -> float:
        return (last[service].get(name, 0.0) - first[service].get(name, 0.0)) / dt

    psnr = [q["psnr_db"] for q in history]
    k = max(1, min(5, len(psnr) // 4))
    window = [q for q in history if id0 <= q["decision_id"] <= id1]

    from aoi3d.stats import mean_ci95

    def stat(values: list) -> dict:  # {"mean", "ci95", "n"}; None-safe
        return mean_ci95(values).to_dict()

    result = {
        "policy": args.policy, "time_scale": args.time_scale, "window_s": round(dt, 1),
        "frames_generated_per_s": rate("camera", "aoi3d_frames_generated_total"),
        "frames_offered_per_s": rate("network", "aoi3d_frames_offered_total"),
        "frames_delivered_per_s": rate("network", "aoi3d_frames_delivered_total"),
        "decisions_per_s": rate("scheduler", "aoi3d_decisions_total"),
        "trainer_steps_per_s": rate("dispatcher", "aoi3d_dispatcher_steps_total"),
        "renders_scored_per_s": rate("metrics", "aoi3d_quality_total"),
        "camera_ticks_skipped_per_s": rate("camera", "aoi3d_camera_ticks_skipped_total"),
        "decisions_skipped_per_s": rate("scheduler", "aoi3d_decisions_skipped_total"),
        "trainer_decisions_applied_per_s": rate("dispatcher", "aoi3d_dispatcher_decisions_total"),
        "trainer_steps_per_decision": (rate("dispatcher", "aoi3d_dispatcher_steps_total")
                                       / max(rate("scheduler", "aoi3d_decisions_total"), 1e-9)),
        "mean_cameras_selected_at_end": last["scheduler"].get("aoi3d_cameras_selected"),
        "renders_scored": len(psnr),
        "psnr_first_renders_db": psnr[:k],
        "psnr_last_renders_db": psnr[-k:],
        "psnr_mean_first_db": statistics.fmean(psnr[:k]) if psnr else None,
        "psnr_mean_last_db": statistics.fmean(psnr[-k:]) if psnr else None,
        "carry": status.get("carry"), "render_steps": status.get("render_steps"),
        "window_renders": len(window),
        "window_psnr_db": stat([q["psnr_db"] for q in window]),
        "window_psnr_dynamic_db": stat([q.get("psnr_dynamic_db") for q in window]),
        "window_ssim": stat([q["ssim"] for q in window]),
        "window_lpips": stat([q["lpips"] for q in window]),
        "window_views": stat([q["n_views"] for q in window]),
        "render_lag_sim_ms": stat([q["lag_ms"] for q in window]),
        "render_lag_wall_s": stat([q["lag_ms"] / 1000.0 / args.time_scale for q in window]),
        "seconds_since_ready": round(time.monotonic() - t_ready, 1),
        "trainer_device": status.get("device"),
    }
    name = f"pipeline-{args.policy.replace(':', '')}-x{args.time_scale:g}.json"
    common.write_json(common.RESULTS / name, result)
    return result


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    common.print_json(run(args))  # the document, with --json or without


if __name__ == "__main__":
    main()
