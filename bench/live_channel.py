"""A live run on a changing channel (issue 32, section 5): the pipeline (`aoi3d up`) plays a
regime schedule, then a cellular trace set over REST; the console marks every change and
charts the measured mean delay against the regime's mean.

    python bench/live_channel.py [--seconds 90] [--time-scale 0.1]

Writes ``bench/results/live-channel/channel.json`` (the network's GET /channel at the end:
the changes and the measured delay), ``series.json`` (the console's channel series) and a
screenshot of the console, ``docs/figures/console_channel.png`` (needs Chromium and
Playwright; skipped with a message otherwise). Traces come from ``../shared/data/traces``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
TRACES = ROOT.parent / "shared" / "data" / "traces"
OUT = ROOT / "bench" / "results" / "live-channel"
OFFSET = 700
PORTS = {"camera": 8101, "network": 8102, "scheduler": 8103, "trainer": 8104, "metrics": 8105,
         "console": 8106}


def url(service: str, path: str = "/") -> str:
    return f"http://127.0.0.1:{PORTS[service] + OFFSET}{path}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=90.0, help="wall seconds per channel")
    ap.add_argument("--time-scale", type=float, default=0.1)
    ap.add_argument("--regimes", default="regimes:exp:20@3s,exp:200@3s")
    ap.add_argument("--trace", default=str(TRACES / "TMobile-UMTS-driving.up"))
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, AOI3D_NETWORK_DELAY=args.regimes, AOI3D_SCHEDULER_POLICY="mat:100",
               AOI3D_FILES_ROOTS=f"runs,models,{TRACES}")
    cmd = [sys.executable, "-m", "aoi3d", "up", "--time-scale", str(args.time_scale),
           "--port-offset", str(OFFSET), "--zenoh-port", "7747", "--run-id", "livechannel",
           "--quiet"]
    (OUT / "COMMAND").write_text(" ".join(cmd) + f"\n# AOI3D_NETWORK_DELAY={args.regimes}; "
                                 f"then PUT /channel trace:{args.trace}\n")
    up = subprocess.Popen(cmd, cwd=ROOT, env=env, start_new_session=True)
    client = httpx.Client(timeout=10.0)
    try:
        deadline = time.monotonic() + 300
        while True:
            try:
                if all(client.get(url(s, "/healthz")).status_code == 200 for s in PORTS):
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline or up.poll() is not None:
                raise SystemExit("the pipeline did not come up")
            time.sleep(2)
        print("up; playing", args.regimes, flush=True)
        time.sleep(args.seconds)
        r = client.put(url("network", "/channel"), json={"delay": f"trace:{args.trace}"})
        print("PUT trace:", r.status_code, r.json().get("delay", r.text)[:200], flush=True)
        time.sleep(args.seconds)
        channel = client.get(url("network", "/channel")).json()
        (OUT / "channel.json").write_text(json.dumps(channel, indent=1))
        state = client.get(url("console", "/state")).json() if _has(client, "/state") else {}
        (OUT / "series.json").write_text(json.dumps(
            {k: state.get(k) for k in ("channel_series", "markers", "channel_summary")},
            indent=1))
        print("changes:", [(c["cause"], c["spec"]) for c in channel["changes"]][-8:])
        print("measured delay (ms):", channel["measured_delay_ms"])
        _screenshot()
    finally:
        os.killpg(up.pid, signal.SIGINT)
        try:
            up.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)


def _has(client: httpx.Client, path: str) -> bool:
    try:
        return client.get(url("console", path)).status_code == 200
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
        page.goto(url("console"))
        page.wait_for_timeout(4000)
        out = ROOT / "docs" / "figures" / "console_channel.png"
        page.screenshot(path=str(out), full_page=True)
        browser.close()
        print("screenshot:", out)


if __name__ == "__main__":
    main()
