"""A real Prometheus (Debian's `prometheus`) scraping a real pipeline (`aoi3d up` on
loopback): every expression of the Grafana dashboard returns data through Prometheus's HTTP
API, every series name the dashboard and the rules use is one the running services export,
the alert rules load, and the service-down alert fires when a service stops answering.

Prometheus runs with the project's own rules (deploy/prometheus/rules/), with one change: the
service-down rule's `for:` is shortened so the test need not wait 30 s (scrapes every second).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml

from aoi3d.ports import SERVICE_PORTS
from services.kit.keys import Keys
from tests.integration.test_pipeline import (
    HTTP,
    Tap,
    small_dataset,  # noqa: F401  (module fixture)
    stop_pipeline,
    wait_for,
)
from tests.ports import block

ROOT = Path(__file__).resolve().parents[2]
PROMETHEUS = shutil.which("prometheus")
pytestmark = [
    pytest.mark.integration, pytest.mark.slow,
    pytest.mark.skipif(PROMETHEUS is None, reason="prometheus not installed (Debian's "
                                                  "prometheus; .ci/setup/30-prometheus.sh)"),
]

_PORTS = block("prometheus")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh
PROM_PORT = _PORTS.extra(0)
PORTS = {s: p for s, p in SERVICE_PORTS.items() if s != "console"}
WINDOW = "20s"
"""What the dashboard's $__rate_interval becomes (scrapes every second)."""
NEEDS_PPO_LEARNING = {
    "aoi3d_ppo_mean_reward", "aoi3d_ppo_policy_entropy", "aoi3d_ppo_update_seconds_bucket",
    "aoi3d_ppo_rewards_ignored_total",
}
"""Series that hold a value only once a ppo policy learns online (NaN, or no labelled series
before the first ignored reward): an expression over them may return no number here."""


def prom(path: str, **params) -> dict:
    r = HTTP.get(f"http://127.0.0.1:{PROM_PORT}{path}", params=params)
    r.raise_for_status()
    return r.json()["data"]


def dashboard_queries() -> list[tuple[str, str]]:
    doc = json.loads((ROOT / "deploy/grafana/dashboards/aoi3d.json").read_text())
    out = []

    def walk(panels):
        for p in panels:
            yield p
            yield from walk(p.get("panels", []))

    for panel in walk(doc["panels"]):
        for target in panel.get("targets", []):
            expr = target["expr"].replace("$__rate_interval", WINDOW)
            out.append((panel["title"], expr.replace("$camera", ".*")))
    return out


def rule_exprs() -> list[str]:
    return [r["expr"] for f in sorted((ROOT / "deploy/prometheus/rules").glob("*.yml"))
            for g in yaml.safe_load(f.read_text())["groups"] for r in g["rules"]]


def has_number(result: list[dict]) -> bool:
    return any(r["value"][1] not in ("NaN", "+Inf", "-Inf") for r in result)


def write_config(tmp: Path) -> Path:
    rules_dir = tmp / "rules"
    rules_dir.mkdir()
    for rule_file in (ROOT / "deploy/prometheus/rules").glob("*.yml"):
        text = rule_file.read_text().replace("expr: up{job=\"aoi3d\"} == 0\n        for: 30s",
                                             "expr: up{job=\"aoi3d\"} == 0\n        for: 2s")
        (rules_dir / rule_file.name).write_text(text)
    config = {
        "global": {"scrape_interval": "1s", "scrape_timeout": "900ms",
                   "evaluation_interval": "1s"},
        "rule_files": ["rules/*.yml"],
        "scrape_configs": [{"job_name": "aoi3d", "static_configs": [
            {"targets": [f"127.0.0.1:{port + PORT_OFFSET}"], "labels": {"service": name}}
            for name, port in PORTS.items()]}],
    }
    path = tmp / "prometheus.yml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_prometheus_evaluates_the_dashboard_and_fires_service_down(
        small_dataset: Path, tmp_path: Path) -> None:  # noqa: F811
    run_id = f"prom{uuid.uuid4().hex[:8]}"
    log_dir = tmp_path / "logs"
    up = subprocess.Popen(
        [sys.executable, "-m", "aoi3d", "up", "--dataset", str(small_dataset), "--run-id",
         run_id, "--zenoh-port", str(ZENOH_PORT), "--port-offset", str(PORT_OFFSET),
         "--log-dir", str(log_dir), "--quiet", "--time-scale", "0.1"],
        env=dict(os.environ, AOI3D_TRAINER_RENDER_PERIOD_S="0.5",
                 AOI3D_TRAINER_RENDER_STEPS="20"),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    prometheus = None
    stopped_pid = None
    try:
        config = write_config(tmp_path)
        prometheus = subprocess.Popen(
            [PROMETHEUS, f"--config.file={config}", f"--storage.tsdb.path={tmp_path / 'tsdb'}",
             f"--web.listen-address=127.0.0.1:{PROM_PORT}", "--log.level=warn"],
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
        wait_for("every target up", lambda: len([t for t in prom("/api/v1/targets")[
            "activeTargets"] if t["health"] == "up"]) == len(PORTS), timeout_s=120)
        wait_for("Quality scraped", lambda: prom(
            "/api/v1/query", query="aoi3d_quality_psnr_db_count")["result"] and float(prom(
                "/api/v1/query", query="aoi3d_quality_psnr_db_count")["result"][0]["value"][1])
            >= 5, timeout_s=120)
        # one malformed frame, so the rejection counter has a labelled series (a reason)
        tap = Tap(run_id, zenoh_port=ZENOH_PORT)
        try:
            tap.publish(Keys(run_id).cam_frame(1), b"\x00not a frame")
        finally:
            tap.close()
        time.sleep(25)  # a full rate window of scrapes after Quality started

        empty = []
        for title, expr in dashboard_queries():
            result = prom("/api/v1/query", query=expr)["result"]
            if not has_number(result):
                empty.append((title, expr))
        needs_ppo = [e for e in empty
                     if any(name in e[1] for name in NEEDS_PPO_LEARNING)]
        others = [e for e in empty if e not in needs_ppo]
        assert not others, f"dashboard expressions without data: {others}"

        # every series name the dashboard and the alert rules use is one the services'
        # registries export (scraped from the live /metrics, not parsed from the source)
        scraped = set(prom("/api/v1/label/__name__/values"))
        used = {n for expr in [e for _, e in dashboard_queries()] + rule_exprs()
                for n in re.findall(r"(?<![\w:])aoi3d_[A-Za-z0-9_]+", expr)}
        assert used, "no aoi3d series named by the dashboard or the rules"
        unknown = used - scraped - NEEDS_PPO_LEARNING
        assert not unknown, f"named by the dashboard or rules, exported by no service: {unknown}"

        groups = prom("/api/v1/rules")["groups"]
        loaded = {r["name"] for g in groups for r in g["rules"]}
        assert len(loaded) == 8 and {"AoI3DServiceDown", "AoI3DPoolEmpty"} <= loaded
        assert all(r["health"] == "ok" for g in groups for r in g["rules"])

        # the camera stops answering (frozen, so `aoi3d up` does not restart it)
        stopped_pid = json.loads((log_dir / "latest" / "up.json").read_text())[
            "children"]["camera"]["pid"]
        os.kill(stopped_pid, signal.SIGSTOP)

        def firing():
            alerts = prom("/api/v1/alerts")["alerts"]
            return [a for a in alerts if a["labels"]["alertname"] == "AoI3DServiceDown"
                    and a["state"] == "firing" and a["labels"].get("service") == "camera"]

        wait_for("AoI3DServiceDown firing for the camera", firing, timeout_s=60)
    finally:
        if stopped_pid is not None:
            os.kill(stopped_pid, signal.SIGCONT)
        if prometheus is not None:
            prometheus.terminate()
            try:
                prometheus.wait(timeout=30)
            except subprocess.TimeoutExpired:
                prometheus.kill()
        stop_pipeline(up)

