"""A live run on a changing channel (issue 32, section 5): the pipeline (`aoi3d up`) plays a
regime schedule, then a cellular trace set over REST, under a policy (default the adaptive
plug-in); the console marks every change, charts the measured mean delay against the regime's
mean and the policy's Γ over time.

    python -m bench.live_channel [--seconds 90] [--time-scale 0.1] [--policy adaptive:plugin]

Writes ``results/live-channel/channel.json`` (the network's GET /channel at the end:
the changes and the measured delay), ``series.json`` (the console's channel series) and a
screenshot of the console, ``docs/figures/console_channel.png`` (needs Chromium and
Playwright; skipped with a message otherwise). Traces come from ``../shared/data/traces``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time

import httpx

from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

ROOT = common.ROOT

TRACES = ROOT.parent / "shared" / "data" / "traces"
OUT = common.RESULTS / "live-channel"
PORTS = BENCH_BLOCKS["live_channel"]  # apart from make up and the other benches (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): its URLs."""
WATCHED = ("camera", "network", "scheduler", "dispatcher", "metrics", "console")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=90.0, help="wall seconds per channel")
    ap.add_argument("--time-scale", type=float, default=0.1)
    ap.add_argument("--regimes", default="regimes:exp:20@3s,exp:200@3s")
    ap.add_argument("--trace", default=str(TRACES / "TMobile-UMTS-driving.up"))
    ap.add_argument("--policy", default="adaptive:plugin",
                    help="the scheduler's policy (adaptive:plugin draws its Γ on the console)")
    common.add_json_option(ap, help="print the result document (channel.json's) as JSON")
    return ap


def run(args: argparse.Namespace) -> dict:
    """The live run (``parser()``'s options); writes under results/live-channel and
    returns the result document: the network's ``GET /channel`` at the end."""
    OUT.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, AOI3D_NETWORK_DELAY=args.regimes, AOI3D_SCHEDULER_POLICY=args.policy,
               AOI3D_FILES_ROOTS=f"runs,models,{TRACES}")
    up_args = ["--time-scale", str(args.time_scale)]
    (OUT / "COMMAND").write_text(
        f"python bench/live_channel.py --seconds {args.seconds:g} --time-scale "
        f"{args.time_scale:g} --regimes {args.regimes} --policy {args.policy}\n"
        f"# aoi3d up {' '.join([*PORTS.up_args(), *up_args])} with "
        f"AOI3D_NETWORK_DELAY={args.regimes} AOI3D_SCHEDULER_POLICY={args.policy}; "
        f"then PUT /channel trace:{args.trace}\n")
    up = PIPE.start(up_args, run_id="livechannel", log_dir=ROOT / "runs" / "bench-live-channel",
                    env=env, cwd=ROOT)
    client = httpx.Client(timeout=10.0)
    try:
        up.wait("the pipeline", lambda: all(
            client.get(PIPE.url(s, "/healthz")).status_code == 200 for s in WATCHED), 300)
        print("up; playing", args.regimes, "under", args.policy, flush=True)
        time.sleep(args.seconds)
        r = client.put(PIPE.url("network", "/channel"), json={"delay": f"trace:{args.trace}"})
        print("PUT trace:", r.status_code, r.json().get("delay", r.text)[:200], flush=True)
        time.sleep(args.seconds)
        channel = client.get(PIPE.url("network", "/channel")).json()
        (OUT / "channel.json").write_text(json.dumps(channel, indent=1))
        state = client.get(PIPE.url("console", "/state")).json() if _has(client, "/state") else {}
        (OUT / "series.json").write_text(json.dumps(
            {k: state.get(k) for k in ("channel_series", "markers", "channel_summary")},
            indent=1))
        print("changes:", [(c["cause"], c["spec"]) for c in channel["changes"]][-8:])
        print("measured delay (ms):", channel["measured_delay_ms"])
        _screenshot()
    finally:
        up.stop(90)
    return channel


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        channel = run(args)
    if args.json:
        common.print_json(channel, indent=1)


def _has(client: httpx.Client, path: str) -> bool:
    try:
        return client.get(PIPE.url("console", path)).status_code == 200
    except httpx.HTTPError:
        return False


def _screenshot() -> None:
    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        chromium = None
    if chromium is None:
        print("no Chromium/Playwright: no screenshot")
        return
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                     args=["--no-sandbox", "--disable-gpu"])
        page = browser.new_page(viewport={"width": 1280, "height": 1100})
        page.goto(PIPE.url("console"))
        page.wait_for_timeout(4000)
        out = ROOT / "docs" / "figures" / "console_channel.png"
        page.screenshot(path=str(out), full_page=True)
        browser.close()
        print("screenshot:", out)


if __name__ == "__main__":
    main()
