"""The container deployment matches the code it runs.

Static: no container engine is needed (``make compose-test``, tests/containers/, builds and
runs the stack for real).  ``compose.yaml`` is validated against the Compose
Specification JSON schema (vendored as ``tests/data/compose-spec.json``), then every command,
port, healthcheck, environment variable, volume, scrape target, Grafana provisioning file and
dashboard query is checked against the code it refers to (settings classes, ``__main__``
modules, the CLI, the metric definitions in ``services/``).

The checks are functions that return a list of problems (tests/support/compose_checks.py and
deploy_checks.py), so these tests can also feed them a deliberately broken deployment and see
them fail.
"""

from __future__ import annotations

import copy
import importlib
import json
import os
import re

import pytest

from tests.support.compose_checks import (
    AWAITED,
    COMPOSE_FILE,
    DASHBOARD_FILE,
    LOCK_FILE,
    MULTIHOST_FILE,
    PROMETHEUS_FILE,
    SERVICES,
    allowed_hosts_problems,
    awaited_missing,
    dataset_problems,
    default_port,
    env_problems,
    healthcheck_code,
    kit_routes,
    limits_problems,
    module_file,
    multihost_problems,
    ports_problems,
    published_ports,
    runs_volume_problems,
    schema_problems,
    secrets_problems,
    service_problems,
    shared_env_problems,
    tls_problems,
)
from tests.support.compose_file import (
    _yaml,
    command,
    defined_metrics,
    environment,
    project,
)
from tests.support.deploy_checks import (
    _walk,
    dashboard_problems,
    dockerfile_problems,
    dockerignore_excludes,
    grafana_problems,
    image_problems,
    lock_problems,
    prometheus_problems,
    scrape_labels,
)


def test_compose_file_follows_the_compose_specification(compose, schema):
    assert schema_problems(compose, schema) == []


def test_schema_check_rejects_an_invalid_compose_file(compose, schema):
    broken = copy.deepcopy(compose)
    broken["services"]["camera"]["depends_on"]["router"]["condition"] = "service_ready"
    broken["services"]["metrics"]["helthcheck"] = {"test": ["CMD", "true"]}
    del broken["services"]["prometheus"]["image"]
    problems = "\n".join(schema_problems(broken, schema))
    assert "service_ready" in problems
    assert "helthcheck" in problems
    assert "services/prometheus" in problems


@pytest.mark.parametrize("name", SERVICES)
def test_service_runs_its_module_on_its_port(compose, name):
    assert service_problems(compose, name) == []


def test_healthchecks_probe_routes_every_service_serves(compose):
    routes = kit_routes()
    assert {"/healthz", "/readyz", "/metrics"} <= routes
    for name in SERVICES:
        code = healthcheck_code(compose["services"][name])
        for path in re.findall(r"http://[\d.]+:\d+(/\w*)", code):
            assert path in routes, f"{name}: healthcheck probes {path}, not served"


def test_every_aoi3d_variable_is_a_settings_field(compose):
    assert env_problems(compose, frozenset(awaited_missing())) == []


def test_services_agree_on_the_run_and_reach_the_router(compose):
    assert shared_env_problems(compose) == []


@pytest.mark.parametrize("name", [*SERVICES, "router"])
def test_compose_environment_is_accepted_by_the_settings(compose, monkeypatch, name):
    """The values (defaults of ${VAR:-default}) validate, and the service sees them."""
    for var in [v for v in os.environ if v.startswith("AOI3D_")]:
        monkeypatch.delenv(var)
    env = environment(compose["services"][name])
    for var, value in env.items():
        monkeypatch.setenv(var, value)
    if name == "router":
        from services.router import RouterSettings

        assert RouterSettings().listen == [env["AOI3D_ROUTER_LISTEN"]]
        return
    settings = importlib.import_module(f"services.{name}.settings").Settings()
    assert settings.port == default_port(name)
    assert settings.host == "0.0.0.0"
    assert settings.common.zenoh_connect == [env["AOI3D_ZENOH_CONNECT"]]
    assert settings.common.run_id == env["AOI3D_RUN_ID"]
    assert str(settings.common.dataset) == env["AOI3D_DATASET"]


def test_zenoh_runs_over_mutual_tls(compose):
    assert tls_problems(compose) == []
    broken = copy.deepcopy(compose)
    s = broken["services"]
    s["router"]["environment"]["AOI3D_ROUTER_LISTEN"] = "tcp/0.0.0.0:7447"
    s["camera"]["environment"] = {**s["camera"]["environment"],
                                  "AOI3D_ZENOH_TLS_CERT": "/run/secrets/zenoh_tls_router_cert"}
    s["metrics"]["environment"] = {**s["metrics"]["environment"], "AOI3D_ZENOH_TLS_MTLS": False}
    s["dispatcher"]["secrets"] = ["control_token", "zenoh_password"]
    assert any("want tls/0.0.0.0" in p for p in shared_env_problems(broken))
    assert any("camera: AOI3D_ZENOH_TLS_CERT" in p for p in tls_problems(broken))
    assert any("metrics: AOI3D_ZENOH_TLS_MTLS" in p for p in tls_problems(broken))
    assert any("dispatcher: reads /run/secrets/zenoh_tls_ca" in p for p in secrets_problems(broken))


def test_dataset_job_feeds_camera_and_trainer(compose):
    assert dataset_problems(compose) == []


def test_dataset_job_runs_a_real_cli_command(compose):
    """`aoi3d scene generate --out DIR` exists in the CLI (typer app → click command)."""
    import typer

    from aoi3d_cli import app

    cmd = command(compose["services"]["dataset"])
    assert project()["scripts"].get(cmd[0]), f"{cmd[0]} is not a project script"
    group = typer.main.get_command(app)
    for word in cmd[1:3]:
        assert word in group.commands, f"`aoi3d {word}` is not a CLI command"
        group = group.commands[word]
    options = {opt for param in group.params for opt in param.opts}
    flags = [w for w in cmd[3:] if w.startswith("--")]
    assert set(flags) <= options, f"{flags} not all in {sorted(options)}"


def test_dataset_job_renders_the_rotor_scene_by_default(compose):
    """The one-shot job's command, parsed by the CLI itself, renders the experiments' scene
    (the rotor close-up at 6 rpm) where camera and dispatcher read it, as `aoi3d up` does."""
    import typer

    from aoi3d.experiment.config import EXPERIMENT_SCENE
    from aoi3d.scene import SceneConfig
    from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_SCENES
    from aoi3d_cli import app
    from aoi3d_cli.scene import scene_config

    cmd = command(compose["services"]["dataset"])
    generate = typer.main.get_command(app).commands["scene"].commands["generate"]
    params = generate.make_context("generate", cmd[3:]).params
    fields = {k: v for k, v in params.items() if k in SceneConfig.__dataclass_fields__}
    assert scene_config(**fields) == FRAMING_SCENES[DEFAULT_FRAMING] == EXPERIMENT_SCENE
    assert params["out"].name == "turbine-rotor"
    assert environment(compose["services"]["camera"])["AOI3D_DATASET"] == str(params["out"])


def test_dockerfile_copies_existing_files_and_runs_existing_commands(compose):
    assert dockerfile_problems(compose) == []


def test_images_are_pinned(compose):
    assert image_problems(compose) == []


def test_prometheus_scrapes_the_five_services(compose):
    assert prometheus_problems(compose, _yaml(PROMETHEUS_FILE)) == []


def test_grafana_provisioning_matches_compose_and_dashboard(compose):
    dashboard = json.loads(DASHBOARD_FILE.read_text(encoding="utf-8"))
    assert grafana_problems(compose, dashboard) == []


def test_dashboard_queries_only_defined_metrics():
    dashboard = json.loads(DASHBOARD_FILE.read_text(encoding="utf-8"))
    metrics = defined_metrics()
    assert {"aoi3d_messages_rejected_total", "aoi3d_link_delay_seconds_bucket"} <= set(metrics)
    assert dashboard_problems(dashboard, metrics, scrape_labels(_yaml(PROMETHEUS_FILE))) == []
    panels = [p for p in _walk(dashboard["panels"]) if p.get("targets")]
    assert len({p["id"] for p in _walk(dashboard["panels"]) if "gridPos" in p}) == \
        len([p for p in _walk(dashboard["panels"]) if "gridPos" in p]), "duplicate panel ids"
    assert len(panels) >= 10


def test_checks_catch_a_broken_deployment(compose):
    """Each check fails on a deployment that no longer matches the code."""
    broken = copy.deepcopy(compose)
    camera = broken["services"]["camera"]
    camera["environment"]["AOI3D_CAMERA_PORT"] = 8199
    camera["environment"]["AOI3D_CAMERA_PERIOD"] = 30  # the field is period_ms
    broken["services"]["dispatcher"]["command"] = ["python", "-m", "services.trainr"]
    broken["services"]["network"]["environment"]["AOI3D_RUN_ID"] = "other"
    broken["services"]["scheduler"]["healthcheck"]["test"][3] = (
        "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8103/ready')")
    broken["services"]["metrics"]["depends_on"] = {"router": {"condition": "service_started"}}
    broken["services"]["dispatcher"]["depends_on"].pop("dataset")

    assert any("AOI3D_CAMERA_PORT=8199" in p for p in service_problems(broken, "camera"))
    assert any("services.trainr" in p for p in service_problems(broken, "dispatcher"))
    assert any("/ready," in p for p in service_problems(broken, "scheduler"))
    assert any("service_healthy" in p for p in service_problems(broken, "metrics"))
    assert any("AOI3D_CAMERA_PERIOD" in p for p in env_problems(broken))
    assert any("AOI3D_RUN_ID differs" in p for p in shared_env_problems(broken))
    assert any("dispatcher: must wait for dataset" in p for p in dataset_problems(broken))

    prom = _yaml(PROMETHEUS_FILE)
    prom["scrape_configs"][0]["static_configs"][0]["targets"] = ["camera:9101"]
    assert any("scrape targets" in p for p in prometheus_problems(compose, prom))

    dashboard = {"panels": [{"id": 1, "title": "x", "gridPos": {}, "targets": [
        {"expr": 'sum by (kamera) (rate(aoi3d_frames_droped_total[1m]))',
         "legendFormat": "{{kamera}}"}]}]}
    problems = "\n".join(dashboard_problems(dashboard, defined_metrics(), {"service"}))
    assert "aoi3d_frames_droped_total is not defined" in problems
    assert "label 'kamera'" in problems

    ignore = ["*", "!aoi3d", "**/__pycache__"]
    assert dockerignore_excludes("services/kit/app.py", ignore)
    assert not dockerignore_excludes("aoi3d/sites.py", ignore)
    assert dockerignore_excludes("aoi3d/__pycache__", ignore)


def test_metric_scan_knows_prometheus_client_naming(tmp_path):
    (tmp_path / "w.py").write_text(
        "from prometheus_client import Counter, Gauge, Histogram\n"
        "a = Counter('aoi3d_a_total', 'doc', ['camera'], registry=r)\n"
        "b = Counter('aoi3d_b', 'doc', labelnames=('reason',))\n"
        "c = Histogram('aoi3d_c_seconds', 'doc')\n"
        "d = Gauge('aoi3d_d', 'doc')\n"
        "e = Gauge(name, 'not a literal: ignored')\n")
    metrics = defined_metrics(tmp_path)
    assert metrics["aoi3d_a_total"] == {"camera"}
    assert metrics["aoi3d_b_total"] == {"reason"}
    assert {"aoi3d_c_seconds_bucket", "aoi3d_c_seconds_sum", "aoi3d_c_seconds_count"} <= \
        set(metrics)
    assert "aoi3d_d" in metrics and "aoi3d_b" not in metrics and "aoi3d_a_total_total" not in \
        metrics


def test_awaited_names_report():
    """Lists the names compose.yaml uses for code not (yet) in this tree; fails if a name is
    tolerated that compose.yaml does not even use."""
    text = COMPOSE_FILE.read_text(encoding="utf-8")
    assert all(name in text for name in AWAITED)
    missing = awaited_missing()
    if missing:
        import warnings

        warnings.warn("compose.yaml names code not in this tree yet: "
                      + "; ".join(f"{n} ({AWAITED[n]})" for n in missing), stacklevel=1)


def test_console_runs_its_module_on_its_port(compose):
    console = compose["services"]["console"]
    assert command(console) == ["python", "-m", "services.console"]
    assert (8106, 8106) in published_ports(console)
    assert environment(console)["AOI3D_CONSOLE_PORT"] == "8106"
    if module_file("services.console") is not None:
        assert service_problems(compose, "console") == []


def test_recorder_runs_its_module_on_its_port(compose):
    recorder = compose["services"]["recorder"]
    assert command(recorder) == ["python", "-m", "services.recorder"]
    assert (8107, 8107) in published_ports(recorder)
    env = environment(recorder)
    assert env["AOI3D_RECORDER_PORT"] == "8107" and env["AOI3D_RECORDER_PATH"] == ""
    assert "runs:/app/runs" in recorder["volumes"]  # recordings land in runs/ (files roots)
    assert service_problems(compose, "recorder") == []


def test_runs_volume_covers_checkpoints_and_runs(compose):
    assert runs_volume_problems(compose) == []


def test_every_container_is_limited(compose):
    assert limits_problems(compose) == []


def test_secrets_come_from_files_not_from_compose(compose):
    assert secrets_problems(compose) == []


def test_published_ports_are_local_and_movable(compose):
    assert ports_problems(compose) == []


def test_allowed_hosts_admit_the_service_names(compose):
    assert allowed_hosts_problems(compose) == []


def test_lock_is_current_and_hashed():
    assert lock_problems(LOCK_FILE.read_text(encoding="utf-8")) == []


def test_new_checks_catch_a_broken_deployment(compose):
    broken = copy.deepcopy(compose)
    s = broken["services"]
    s["scheduler"]["volumes"] = []
    s["recon"]["environment"]["AOI3D_RECON_TORCH_THREADS"] = 8
    del s["metrics"]["mem_limit"]
    s["camera"]["environment"]["AOI3D_CONTROL_TOKEN_FILE"] = "/run/secrets/nope"
    s["grafana"]["environment"]["GF_SECURITY_ADMIN_PASSWORD"] = "admin"
    s["network"]["ports"] = ["8102:8102"]
    s["metrics"]["environment"]["AOI3D_ALLOWED_HOSTS"] = "127.0.0.1,localhost"
    assert any("scheduler: /app/runs" in p for p in runs_volume_problems(broken))
    assert any("TORCH_THREADS=8" in p for p in limits_problems(broken))
    assert any("metrics: no cpus/mem_limit" in p for p in limits_problems(broken))
    assert any("camera: reads /run/secrets/nope" in p for p in secrets_problems(broken))
    assert any("written in compose.yaml" in p
               for p in grafana_problems(broken, {"panels": []}))
    assert any("network: port '8102:8102'" in p for p in ports_problems(broken))
    assert any("metrics: AOI3D_ALLOWED_HOSTS lacks" in p for p in allowed_hosts_problems(broken))
    env = dict(s["camera"]["environment"])
    s["camera"]["environment"] = {**env, "AOI3D_CAMERA_PERIOD": 30}
    assert any("AOI3D_CAMERA_PERIOD" in p
               for p in env_problems(broken, frozenset(awaited_missing())))

    lock = LOCK_FILE.read_text(encoding="utf-8")
    stale = lock.replace("#   gymnasium>=1.0\n", "")
    assert any("make lock" in p for p in lock_problems(stale))
    unhashed = re.sub(r"(numpy==\S+) \\\n    --hash=sha256:[0-9a-f]{64}", r"\1", lock)
    assert any("have no sha256" in p for p in lock_problems(unhashed))


def test_multihost_file_follows_the_specification_and_reads_real_settings(schema):
    doc = _yaml(MULTIHOST_FILE)
    assert schema_problems(doc, schema) == []
    assert env_problems(doc) == []
    assert multihost_problems(doc) == []
    broken = copy.deepcopy(doc)
    broken["services"]["recon-a"]["networks"] = ["edge"]
    broken["services"]["camera"]["networks"] = ["edge", "mesh"]
    broken["services"]["router-b"]["environment"]["AOI3D_ROUTER_CONNECT"] = "tls/router-a:7447"
    found = multihost_problems(broken)
    assert any("recon-a: on edge but connects to tls/router-a" in p for p in found), found
    assert any("camera: only routers are on the mesh" in p for p in found), found
    assert any("router-b: must connect" in p for p in found), found
