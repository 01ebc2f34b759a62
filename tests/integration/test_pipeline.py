"""The real pipeline: `aoi3d up` starts a Zenoh router and the five services as processes.

Everything is real — processes, uvicorn servers, Zenoh on 127.0.0.1 — on ports of its own
so it does not collide with a pipeline a developer has running. The test talks to it the
way an operator would: REST calls, /metrics scrapes and a Zenoh client session.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from aoi3d.lpips import weights_path
from services.kit.keys import Keys
from tests.support.pipeline import (
    HTTP,
    PIPE,
    PORT_OFFSET,
    SCALE,
    SERVICES,
    Tap,
    assert_clean_exit,
    metric,
    stop_pipeline,
    wait_for,
)

pytestmark = [pytest.mark.integration, pytest.mark.slow]


# The series each service documents (docs/operations.md, "Metrics (Prometheus)"); every one
# must be exposed.
DOCUMENTED_SERIES = {
    "camera": ["aoi3d_frames_generated_total", "aoi3d_camera_ticks_skipped_total"],
    "network": ["aoi3d_frames_offered_total", "aoi3d_frames_dropped_total",
                "aoi3d_frames_delivered_total", "aoi3d_link_delay_seconds_bucket"],
    "scheduler": ["aoi3d_aoi_seconds", "aoi3d_cameras_selected", "aoi3d_decisions_total"],
    "dispatcher": ["aoi3d_dispatcher_steps_total", "aoi3d_dispatcher_steps_per_second",
                "aoi3d_dispatcher_loss", "aoi3d_dispatcher_views", "aoi3d_renders_total",
                "aoi3d_render_age_seconds", "aoi3d_render_lag_sim_seconds",
                "aoi3d_render_frames_age_seconds", "aoi3d_render_steps"],
    "metrics": ["aoi3d_render_psnr_db", "aoi3d_render_ssim", "aoi3d_reward",
                "aoi3d_quality_total"],
}


















def test_pipeline_end_to_end(small_dataset: Path, tmp_path: Path) -> None:
    run_id = f"it{uuid.uuid4().hex[:8]}"
    log_dir = tmp_path / "logs"
    cmd = ["--dataset", str(small_dataset),
           "--run-id", run_id, "--log-dir", str(log_dir), "--time-scale", "0.1"]
    env = dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="30")
    up = PIPE.start(cmd, env=env, output=subprocess.PIPE)
    tap = None
    try:
        for name in SERVICES:
            wait_for(f"{name} /healthz",
                     lambda n=name: HTTP.get(PIPE.url(n, "/healthz")).status_code == 200)
        tap = Tap(run_id)

        # frames flow end to end: offered → delivered → decisions → training → quality
        wait_for("frames delivered", lambda: metric("network", "aoi3d_frames_delivered_total") > 20)
        wait_for("decisions", lambda: metric("scheduler", "aoi3d_decisions_total") > 5)
        wait_for("training steps",
                 lambda: HTTP.get(PIPE.url("dispatcher", "/status")).json()["steps"] > 0)
        entries = wait_for("quality history",
                           lambda: HTTP.get(PIPE.url("metrics", "/quality")).json()["history"],
                           timeout_s=90)
        assert all(math.isfinite(q["psnr_db"]) for q in entries)
        # LPIPS is on exactly when its weights are cached (`make install` fetches them)
        lpips_on = HTTP.get(PIPE.url("metrics", "/quality")).json()["summary"]["lpips_available"]
        assert lpips_on == weights_path("alex").is_file()
        assert all((q["lpips"] is not None) == lpips_on
                   and ("lpips" in q["reward_terms"]) == lpips_on for q in entries)
        wait_for("Quality messages on Zenoh", lambda: tap.qualities)
        assert all(math.isfinite(q.psnr_db) for q in tap.qualities)

        # MAT 0 selects no camera; a large MAT selects most of them
        r = HTTP.put(PIPE.url("scheduler", "/policy"), json={"kind": "mat", "mat_ms": 0})
        assert r.status_code == 200, r.text
        spec0 = r.json()["spec"]
        zero = wait_for("decisions under MAT 0", lambda: [
            d for d in tap.decisions_after(0) if d.policy == spec0][:5])
        assert all(len(d.selected) == 0 for d in zero)
        r = HTTP.put(PIPE.url("scheduler", "/policy"), json={"kind": "mat", "mat_ms": 10_000})
        assert r.status_code == 200, r.text
        spec1 = r.json()["spec"]
        big = wait_for("decisions under MAT 10 s", lambda: [
            d for d in tap.decisions_after(0) if d.policy == spec1][:5])
        n_cams = len(big[-1].camera_ids)
        assert all(len(d.selected) >= n_cams // 2 for d in big), [len(d.selected) for d in big]

        # REST errors say what is wrong
        r = HTTP.put(PIPE.url("scheduler", "/policy"), json={"kind": "mat", "mat_ms": -5})
        assert r.status_code == 422 and "mat_ms" in r.text
        r = HTTP.put(PIPE.url("network", "/channel"), json={"delay": "weird:1"})
        assert r.status_code in (400, 422) and "exp:" in r.text

        # malformed frames are dropped and counted, and nothing stops
        for _ in range(5):
            tap.publish(Keys(run_id).cam_frame(3), b"\x00garbage\xff")
        wait_for("rejections counted", lambda: metric("network", "aoi3d_messages_rejected_total")
                 >= 5)
        before = metric("network", "aoi3d_frames_delivered_total")
        wait_for("frames still delivered",
                 lambda: metric("network", "aoi3d_frames_delivered_total") > before)

        # `aoi3d live sweep` measures policies on this pipeline, Quality by decision id
        scale = SCALE
        sweep = subprocess.run(
            [sys.executable, "-m", "aoi3d_cli", "live", "sweep", "--policies", "mat:70,all",
             "--settle-s", "1", "--measure-s", str(10 * scale), "--port-offset",
             str(PORT_OFFSET), "--no-sim", "--json", "--out", str(tmp_path / "sweep"),
             "--dataset", str(small_dataset),
             "--timeout-s", str(30 * scale)],
            capture_output=True, text=True, timeout=300 * scale)
        assert sweep.returncode == 0, sweep.stderr[-3000:]
        doc = json.loads(sweep.stdout)
        assert [r["policy"] for r in doc["results"]] == ["mat:70", "all"]
        for r in doc["results"]:
            assert r["n"] >= 1 and math.isfinite(r["psnr_db"]["mean"]), r
        assert doc["results"][1]["cameras_used"]["mean"] == len(big[-1].camera_ids)
        assert doc["settings"]["carry"] == "stream"  # the default (AOI3D_DISPATCHER_CARRY)
        assert {"points.csv", "renders.csv", "results.json", "live_sweep.png"} <= {
            f.name for f in (tmp_path / "sweep").iterdir()}

        # every service exposes its documented series
        for name, series in DOCUMENTED_SERIES.items():
            text = HTTP.get(PIPE.url(name, "/metrics")).text
            missing = [s for s in series if s not in text]
            assert not missing, f"{name} /metrics lacks {missing}"

        # a crashed service is restarted, and the restart is logged
        state = json.loads((log_dir / "latest" / "up.json").read_text())
        os.kill(state["children"]["metrics"]["pid"], signal.SIGKILL)
        wait_for("metrics restarted", lambda: json.loads(
            (log_dir / "latest" / "up.json").read_text())["children"]["metrics"]["restarts"] == 1,
                 timeout_s=30)
        wait_for("metrics healthy again",
                 lambda: HTTP.get(PIPE.url("metrics", "/healthz")).status_code == 200)
    finally:
        if tap is not None:
            tap.close()
        out = stop_pipeline(up)
    assert_clean_exit(up, out, run_id)  # and every process is gone afterwards
    assert "restarted" in out and "metrics" in out
