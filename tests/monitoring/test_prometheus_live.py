"""A real Prometheus (Debian's `prometheus`) scraping a real pipeline (`aoi3d up` on
loopback, one site, two reconstruction workers): the dashboard's variables (site, worker,
camera) resolve as Grafana resolves them (``label_values`` through Prometheus's series API),
and every panel's every query then returns data through Prometheus's HTTP API, with each
variable at "All" and at one value, unless the source (deploy/monitoring.py) declares it
empty at rest and its panel says why. Every series name the dashboard and the rules use is
one the running services export, the recording and alert rules load and evaluate, and the
service-down alert fires when a service stops answering.

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
import time
import uuid
from pathlib import Path

import pytest
import yaml

from services.kit.keys import Keys
from services.kit.ports import SERVICE_PORTS
from tests.support.deploy_modules import load
from tests.support.pipeline import HTTP, Tap, handle, stop_pipeline, wait_for
from tests.support.ports import block

ROOT = Path(__file__).resolve().parents[2]
PROMETHEUS = shutil.which("prometheus")
pytestmark = [
    pytest.mark.integration, pytest.mark.slow,
    pytest.mark.skipif(PROMETHEUS is None, reason="prometheus not installed (Debian's "
                                                  "prometheus; .ci/setup/30-prometheus.sh)"),
]

PIPE = handle("prometheus")
_PORTS = block("prometheus")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh
PROM_PORT = _PORTS.extra(0)
PORTS = {s: p for s, p in SERVICE_PORTS.items() if s != "console"}
WINDOW = "20s"
"""What the dashboard's $__rate_interval becomes (scrapes every second)."""
WORKERS = 2
MONITORING = load("monitoring")
NEEDS_PPO_LEARNING = {
    "aoi3d_ppo_mean_reward", "aoi3d_ppo_policy_entropy", "aoi3d_ppo_update_seconds_bucket",
    "aoi3d_ppo_rewards_ignored_total",
}
"""Series that hold a value only once a ppo policy learns online (NaN, or no labelled series
before the first ignored reward): the services need not export them at rest."""


def prom(path: str, **params) -> dict:
    r = HTTP.get(f"http://127.0.0.1:{PROM_PORT}{path}", params=params)
    r.raise_for_status()
    return r.json()["data"]


def dashboard() -> dict:
    return json.loads((ROOT / "deploy/grafana/dashboards/aoi3d.json").read_text())


def panels(doc: dict):
    def walk(items):
        for p in items:
            yield p
            yield from walk(p.get("panels", []))

    return [p for p in walk(doc["panels"]) if p.get("targets")]


def grafana_escape(value: str) -> str:
    """A value as Grafana's Prometheus datasource writes it into a regex matcher: regex
    metacharacters get a backslash, itself escaped for PromQL's string."""
    return re.sub(r"([\\^$.|?*+()\[\]{}])", r"\\\\\1", value)


def substitute(expr: str, values: dict[str, list[str]], variables: list[dict]) -> str:
    """``expr`` with the variables as Grafana writes them into a query: ``$__rate_interval``
    at WINDOW; a multi-value variable in a regex matcher at its ``allValue`` when every value
    is selected (None here), else its value, or its values joined as ``(a|b)``, escaped."""
    expr = expr.replace("$__rate_interval", WINDOW)
    for var in sorted(variables, key=lambda v: -len(v["name"])):
        chosen = values[var["name"]]
        text = var["allValue"] if chosen is None else (
            "(" + "|".join(map(grafana_escape, chosen)) + ")" if len(chosen) > 1
            else grafana_escape(chosen[0]))
        expr = expr.replace(f"${var['name']}", text)
    return expr


def resolve_variables(doc: dict, pick_one: bool) -> dict[str, list[str] | None]:
    """Each variable's options as Grafana gets them for ``label_values(metric, label)`` (the
    series API, earlier variables substituted into the selector), then "All" (None) or the
    first option."""
    variables = doc["templating"]["list"]
    chosen: dict[str, list[str] | None] = {}
    for var in variables:
        m = re.fullmatch(r"label_values\((.+), (\w+)\)", var["query"])
        assert m, var["query"]
        selector = substitute(m[1], chosen, [v for v in variables if v["name"] in chosen])
        series = prom("/api/v1/series", **{"match[]": selector})
        options = sorted({s[m[2]] for s in series if m[2] in s})
        assert options, f"variable {var['name']}: {var['query']} has no values"
        chosen[var["name"]] = [options[0]] if pick_one else None
    return chosen


def empty_reasons() -> dict[tuple[str, str], str]:
    """(panel title, expression) → why the source says it may be empty at rest."""
    return {(p.title, q.expr): q.empty_at_rest for p in MONITORING.PANELS
            if isinstance(p, MONITORING.Panel) for q in p.targets if q.empty_at_rest}


def dashboard_queries() -> list[tuple[str, str]]:
    doc = dashboard()
    everything = {v["name"]: None for v in doc["templating"]["list"]}
    return [(p["title"], substitute(t["expr"], everything, doc["templating"]["list"]))
            for p in panels(doc) for t in p["targets"]]


def rule_exprs() -> list[str]:
    return [r["expr"] for f in sorted((ROOT / "deploy/prometheus/rules").glob("*.yml"))
            for g in yaml.safe_load(f.read_text())["groups"] for r in g["rules"]]


def has_number(result: list[dict]) -> bool:
    return any(r["value"][1] not in ("NaN", "+Inf", "-Inf") for r in result)


def write_config(tmp: Path) -> Path:
    rules_dir = tmp / "rules"
    rules_dir.mkdir()
    shortened = 0
    for rule_file in (ROOT / "deploy/prometheus/rules").glob("*.yml"):
        doc = yaml.safe_load(rule_file.read_text())
        for group in doc["groups"]:
            for rule in group["rules"]:
                if rule.get("alert") == "AoI3DServiceDown":
                    rule["for"] = "2s"
                    shortened += 1
        (rules_dir / rule_file.name).write_text(yaml.safe_dump(doc, sort_keys=False))
    assert shortened == 1
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
        small_dataset: Path, tmp_path: Path) -> None:
    run_id = f"prom{uuid.uuid4().hex[:8]}"
    log_dir = tmp_path / "logs"
    up = PIPE.start(
        ["--dataset", str(small_dataset), "--time-scale", "0.1", "--workers", str(WORKERS)],
        run_id=run_id, log_dir=log_dir, output=subprocess.PIPE,
        env=dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="20"))
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

        wait_for(f"{WORKERS} workers in the pool, each with a busy ratio", lambda: len(prom(
            "/api/v1/query", query="aoi3d_pool_worker_busy_ratio")["result"]) == WORKERS,
            timeout_s=120)

        doc = dashboard()
        variables = doc["templating"]["list"]
        reasons = empty_reasons()
        empty, excused = [], []
        for pick_one in (False, True):  # every variable at "All", then at one value
            chosen = resolve_variables(doc, pick_one)
            if not pick_one:
                sites = prom("/api/v1/series", **{"match[]": "aoi3d_dispatcher_decisions_total"})
                assert len({s["site"] for s in sites}) == 1
            for panel in panels(doc):
                for target in panel["targets"]:
                    expr = substitute(target["expr"], chosen, variables)
                    assert "$" not in expr, f"unresolved variable in {expr}"
                    if has_number(prom("/api/v1/query", query=expr)["result"]):
                        continue
                    reason = reasons.get((panel["title"], target["expr"]))
                    if reason is None:
                        empty.append((panel["title"], expr, chosen))
                    else:
                        assert reason in panel["description"], panel["title"]
                        excused.append(panel["title"])
        assert not empty, f"dashboard queries without data: {empty}"
        n_targets = sum(len(p["targets"]) for p in panels(doc))
        assert n_targets >= 60 and len(excused) <= 2 * len(reasons)

        # every series name the dashboard and the alert rules use is one the services'
        # registries export (scraped from the live /metrics, not parsed from the source)
        scraped = set(prom("/api/v1/label/__name__/values"))
        used = {n for expr in [e for _, e in dashboard_queries()] + rule_exprs()
                for n in re.findall(r"(?<![\w:])aoi3d_[A-Za-z0-9_]+", expr)}
        assert used, "no aoi3d series named by the dashboard or the rules"
        # the ingest's series: only a rig pipeline exports them (tests/integration/test_ros2.py
        # checks those names against a live ingest's /metrics)
        unknown = used - scraped - NEEDS_PPO_LEARNING - {
            n for n in used if n.startswith("aoi3d_ingest_")}
        assert not unknown, f"named by the dashboard or rules, exported by no service: {unknown}"

        groups = prom("/api/v1/rules")["groups"]
        loaded = {r["name"] for g in groups for r in g["rules"]}
        assert len(loaded) == len(MONITORING.ALERTS) + len(MONITORING.RECORDS)
        assert {"AoI3DServiceDown", "AoI3DPoolEmpty", "aoi3d:pool_workers_wanted"} <= loaded
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

