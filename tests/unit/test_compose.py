"""The container deployment matches the code it runs.

No container engine is needed: ``compose.yaml`` is validated against the Compose
Specification JSON schema (vendored as ``tests/data/compose-spec.json``), then every command,
port, healthcheck, environment variable, volume, scrape target, Grafana provisioning file and
dashboard query is checked against the code it refers to (settings classes, ``__main__``
modules, the CLI, the metric definitions in ``services/``).

The checks are functions that return a list of problems, so the tests at the end can also
feed them a deliberately broken deployment and see them fail.
"""

from __future__ import annotations

import ast
import copy
import fnmatch
import importlib
import json
import os
import re
import shlex
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml
from pydantic_settings import BaseSettings

from services.kit.configdoc import DOMAIN_VARIABLES
from services.kit.settings import CommonSettings, ServiceSettings

ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = ROOT / "compose.yaml"
SCHEMA_FILE = ROOT / "tests" / "data" / "compose-spec.json"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
PROMETHEUS_FILE = ROOT / "deploy" / "prometheus" / "prometheus.yml"
GRAFANA_DIR = ROOT / "deploy" / "grafana"
DASHBOARD_FILE = GRAFANA_DIR / "dashboards" / "aoi3d.json"

SERVICES = ("camera", "network", "scheduler", "trainer", "metrics")
"""The five services; each runs as ``python -m services.<name>``."""

PROMETHEUS_BUILTIN_METRICS = {"up"}
"""Series Prometheus itself writes for every target (not defined in our code)."""

PROMETHEUS_TARGET_LABELS = {"job", "instance", "le", "quantile", "__name__"}
"""Labels every scraped series may carry besides those our code declares."""

_INTERPOLATION = re.compile(
    r"\$\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?-)(?P<default>[^}]*))?\}")


# ---------------------------------------------------------------------------------- loading
def _yaml(path: Path) -> Any:
    with path.open(encoding="utf-8") as f:
        return yaml.safe_load(f)  # resolves anchors and `<<` merge keys, as Compose does


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return _yaml(COMPOSE_FILE)


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))


def interpolate(value: object) -> str:
    """Resolve Compose ``${VAR:-default}`` with its default (never the caller's environment).

    A variable without a default would make the deployment depend on the shell, so it is an
    error here.
    """
    text = str(value)

    def repl(m: re.Match[str]) -> str:
        if m["op"] is None:
            raise ValueError(f"${{{m['name']}}} has no default in {text!r}")
        return m["default"]

    return _INTERPOLATION.sub(repl, text).replace("$$", "$")


def environment(service: dict[str, Any]) -> dict[str, str]:
    """A service's environment (map or list form), interpolated."""
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) if "=" in item else (item, "") for item in env)
    return {str(k): interpolate(v) for k, v in env.items()}


def command(service: dict[str, Any]) -> list[str]:
    cmd = service.get("command") or []
    return [interpolate(c) for c in (shlex.split(cmd) if isinstance(cmd, str) else cmd)]


def published_ports(service: dict[str, Any]) -> set[tuple[int, int]]:
    """``(published, target)`` pairs from short (``[ip:]host:container``) or long syntax."""
    pairs = set()
    for entry in service.get("ports") or []:
        if isinstance(entry, dict):
            pairs.add((int(entry.get("published", entry["target"])), int(entry["target"])))
            continue
        spec = str(entry).split("/")[0]
        parts = spec.rsplit(":", 2) if spec.count(":") >= 2 else spec.split(":")
        if len(parts) == 1:
            pairs.add((int(parts[0]), int(parts[0])))
        else:
            pairs.add((int(parts[-2]), int(parts[-1])))
    return pairs


def healthcheck_code(service: dict[str, Any]) -> str:
    """The Python source a ``["CMD", "python", "-c", code]`` healthcheck runs ("" if none)."""
    test = (service.get("healthcheck") or {}).get("test") or []
    if isinstance(test, list) and test[:3] == ["CMD", "python", "-c"] and len(test) == 4:
        return test[3]
    return ""


def module_file(module: str) -> Path | None:
    """The file ``python -m module`` runs, if it exists in the repository."""
    rel = Path(*module.split("."))
    for candidate in (ROOT / rel / "__main__.py", ROOT / rel.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def settings_classes(module: str) -> list[type[BaseSettings]]:
    """The ``BaseSettings`` classes a ``python -m module`` process reads its environment with.

    ``module.settings`` if it exists (the services), else ``module`` itself (the router); a
    class derived from ``ServiceSettings`` also reads ``CommonSettings`` (prefix ``AOI3D_``).
    """
    name = f"{module}.settings" if (ROOT / Path(*module.split(".")) / "settings.py").is_file() \
        else module
    mod = importlib.import_module(name)
    found: list[type[BaseSettings]] = [
        obj for obj in vars(mod).values()
        if isinstance(obj, type) and issubclass(obj, BaseSettings) and obj.__module__ == name]
    if any(issubclass(cls, ServiceSettings) for cls in found):
        found.append(CommonSettings)
    return found


def env_names(cls: type[BaseSettings]) -> set[str]:
    """The environment variables a settings class reads (nested models excluded)."""
    prefix = cls.model_config.get("env_prefix", "")
    return {f"{prefix}{field}".upper() for field, info in cls.model_fields.items()
            if not (isinstance(info.annotation, type)
                    and issubclass(info.annotation, BaseSettings))}


def default_port(name: str) -> int:
    cls = importlib.import_module(f"services.{name}.settings").Settings
    return int(cls.model_fields["port"].default)


def kit_routes() -> set[str]:
    """Paths ``service_app`` serves on every service (``/healthz``, ``/readyz``, ``/metrics``)."""
    from services.kit.app import service_app

    app = service_app(title="probe", description="", settings=ServiceSettings(),
                      build_worker=lambda bus, registry: None)
    return {route.path for route in app.routes}


# ------------------------------------------------------------------------- compose checks
def schema_problems(doc: dict[str, Any], schema: dict[str, Any]) -> list[str]:
    """Violations of the Compose Specification schema, plus its image-or-build constraint."""
    validator_cls = jsonschema.validators.validator_for(schema)
    validator_cls.check_schema(schema)
    problems = [f"{'/'.join(map(str, e.absolute_path)) or '<root>'}: {e.message}"
                for e in validator_cls(schema).iter_errors(doc)]
    constraint = {"definitions": schema["definitions"],
                  "$ref": "#/definitions/constraints/service"}
    for name, service in (doc.get("services") or {}).items():
        problems += [f"services/{name}: {e.message}"
                     for e in validator_cls(constraint).iter_errors(service)]
    return problems


def service_problems(doc: dict[str, Any], name: str) -> list[str]:
    """One of the five services: module, port (env, published, healthcheck), dependencies."""
    service = doc["services"].get(name)
    if service is None:
        return [f"{name}: missing from compose.yaml"]
    problems = []
    module = f"services.{name}"
    if command(service) != ["python", "-m", module]:
        problems.append(f"{name}: command {command(service)} is not python -m {module}")
    if module_file(module) is None or module_file(module).name != "__main__.py":
        problems.append(f"{name}: services/{name}/__main__.py does not exist")
    port = default_port(name)
    env = environment(service)
    prefix = f"AOI3D_{name.upper()}_"
    if env.get(f"{prefix}PORT") != str(port):
        problems.append(f"{name}: {prefix}PORT={env.get(f'{prefix}PORT')} but Settings.port "
                        f"defaults to {port}")
    if env.get(f"{prefix}HOST") != "0.0.0.0":
        problems.append(f"{name}: {prefix}HOST must be 0.0.0.0 in a container")
    if (port, port) not in published_ports(service):
        problems.append(f"{name}: port {port} is not published as {port}:{port} "
                        f"(found {sorted(published_ports(service))})")
    code = healthcheck_code(service)
    urls = re.findall(r"http://(?:127\.0\.0\.1|localhost):(\d+)(/\w*)", code)
    if not urls:
        problems.append(f"{name}: no python urllib healthcheck on 127.0.0.1")
    for url_port, path in urls:
        if int(url_port) != port:
            problems.append(f"{name}: healthcheck probes port {url_port}, service on {port}")
        if path not in {"/readyz", "/healthz"}:
            problems.append(f"{name}: healthcheck probes {path}, not /readyz or /healthz")
    if code:
        try:
            compile(code, f"<{name} healthcheck>", "exec")
        except SyntaxError as err:
            problems.append(f"{name}: healthcheck is not valid Python: {err}")
    if (service.get("depends_on") or {}).get("router", {}).get("condition") != "service_healthy":
        problems.append(f"{name}: must depend on router with condition service_healthy")
    return problems


def env_problems(doc: dict[str, Any]) -> list[str]:
    """Every ``AOI3D_*`` variable given to an aoi3d process is read by its settings."""
    problems = []
    for name, service in doc["services"].items():
        cmd = command(service)
        env = {k: v for k, v in environment(service).items() if k.startswith("AOI3D_")}
        if cmd[:2] == ["python", "-m"] and len(cmd) >= 3:
            if module_file(cmd[2]) is None:
                problems.append(f"{name}: module {cmd[2]} does not exist")
                continue
            classes = settings_classes(cmd[2])
        elif cmd[:1] == ["aoi3d"]:
            classes = [CommonSettings]
        else:
            classes = []
        known = set().union(*(env_names(cls) for cls in classes)) if classes else set()
        for var in sorted(set(env) - known):
            problems.append(f"{name}: {var} is not a field of "
                            f"{[c.__name__ for c in classes] or 'any settings class'}")
    return problems


def shared_env_problems(doc: dict[str, Any]) -> list[str]:
    """The five services agree on the run (CommonSettings) and reach the router."""
    problems = []
    common_vars = env_names(CommonSettings)
    envs = {n: environment(doc["services"][n]) for n in SERVICES if n in doc["services"]}
    for var in sorted(common_vars):
        values = {n: env.get(var) for n, env in envs.items()}
        if len(set(values.values())) > 1:
            problems.append(f"{var} differs between services: {values}")
    router = doc["services"].get("router", {})
    listen = environment(router).get("AOI3D_ROUTER_LISTEN", "")
    m = re.fullmatch(r"tcp/0\.0\.0\.0:(\d+)", listen)
    if m is None:
        problems.append(f"router: AOI3D_ROUTER_LISTEN={listen!r}, want tcp/0.0.0.0:<port>")
        return problems
    zenoh_port = int(m[1])
    if f"('127.0.0.1', {zenoh_port})" not in healthcheck_code(router):
        problems.append(f"router: healthcheck does not connect to 127.0.0.1:{zenoh_port}")
    for n, env in envs.items():
        if env.get("AOI3D_ZENOH_CONNECT") != f"tcp/router:{zenoh_port}":
            problems.append(f"{n}: AOI3D_ZENOH_CONNECT={env.get('AOI3D_ZENOH_CONNECT')!r}, "
                            f"want tcp/router:{zenoh_port}")
        if env.get("AOI3D_ZENOH_MODE") != "client":
            problems.append(f"{n}: AOI3D_ZENOH_MODE must be client (the router is separate)")
    return problems


def dataset_problems(doc: dict[str, Any]) -> list[str]:
    """The one-shot dataset job writes where camera and trainer read, and they wait for it."""
    services = doc["services"]
    job = services.get("dataset")
    if job is None:
        return ["dataset: missing from compose.yaml"]
    problems = []
    cmd = command(job)
    if cmd[:3] != ["aoi3d", "scene", "generate"] or "--out" not in cmd:
        return [f"dataset: command {cmd} is not `aoi3d scene generate --out DIR`"]
    out = cmd[cmd.index("--out") + 1]
    if job.get("restart", "no") != "no":
        problems.append("dataset: a one-shot job must not restart")
    job_mounts = {str(v).split(":")[1]: str(v).split(":")[0] for v in job.get("volumes", [])}
    for name in ("camera", "trainer"):
        service = services.get(name, {})
        dataset = environment(service).get("AOI3D_DATASET")
        if dataset != out:
            problems.append(f"{name}: AOI3D_DATASET={dataset!r} but the job writes {out!r}")
        cond = (service.get("depends_on") or {}).get("dataset", {}).get("condition")
        if cond != "service_completed_successfully":
            problems.append(f"{name}: must wait for dataset (service_completed_successfully)")
        mounts = {str(v).split(":")[1]: str(v).split(":")[0] for v in service.get("volumes", [])}
        shared = [t for t, src in mounts.items()
                  if job_mounts.get(t) == src and out.startswith(t.rstrip("/") + "/")]
        if not shared:
            problems.append(f"{name}: does not mount the dataset job's volume above {out}")
    return problems


# ------------------------------------------------------------------------------ Dockerfile
def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` with line continuations joined and comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        full = (pending + line).strip()
        pending = ""
        word, _, args = full.partition(" ")
        out.append((word.upper(), args.strip()))
    return out


def dockerignore_excludes(rel: str, patterns: list[str]) -> bool:
    """Whether a path is left out of the build context (last matching pattern wins)."""
    parts = rel.split("/")
    excluded = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        pat = pattern.lstrip("!").strip("/")
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if any(fnmatch.fnmatchcase(p, pat) or fnmatch.fnmatchcase(p, pat.removeprefix("**/"))
               for p in prefixes):
            excluded = not negate
    return excluded


def project() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def dockerfile_problems(doc: dict[str, Any]) -> list[str]:
    """The image builds from files that exist and runs commands that exist."""
    problems = []
    builds = {json.dumps(s["build"], sort_keys=True) for s in doc["services"].values()
              if "build" in s}
    if len(builds) != 1:
        return [f"expected one image build for all aoi3d processes, found {len(builds)}"]
    build = json.loads(builds.pop())
    context = (ROOT / build["context"]).resolve()
    dockerfile = context / build["dockerfile"]
    if dockerfile != DOCKERFILE:
        problems.append(f"compose builds {dockerfile}, expected {DOCKERFILE}")
    ignore_file = dockerfile.with_name(dockerfile.name + ".dockerignore")
    if not ignore_file.is_file():
        ignore_file = context / ".dockerignore"
    ignore = [ln.strip() for ln in ignore_file.read_text(encoding="utf-8").splitlines()
              if ln.strip() and not ln.startswith("#")] if ignore_file.is_file() else []
    instructions = dockerfile_instructions(dockerfile)
    scripts = project().get("scripts", {})
    for word, args in instructions:
        if word == "FROM" and not re.fullmatch(r"python:3\.11-slim-bookworm( AS \w+)?", args):
            problems.append(f"FROM {args}: want python:3.11-slim-bookworm (requires-python)")
        if word == "COPY":
            tokens = [t for t in shlex.split(args) if not t.startswith("--")]
            if any(t.startswith("--from") for t in shlex.split(args)):
                continue
            for src in tokens[:-1]:
                path = context / src
                if not path.exists():
                    problems.append(f"COPY {src}: {path.relative_to(ROOT)} does not exist")
                    continue
                files = [path] if path.is_file() else [
                    f for f in path.rglob("*.py") if "__pycache__" not in f.parts]
                for f in files:
                    rel = f.relative_to(context).as_posix()
                    if dockerignore_excludes(rel, ignore):
                        problems.append(f"COPY {src}: {rel} is excluded by {ignore_file.name}")
        if word in {"CMD", "ENTRYPOINT"}:
            argv = json.loads(args)
            if argv[:2] == ["python", "-m"]:
                if module_file(argv[2]) is None:
                    problems.append(f"{word} {argv}: module {argv[2]} does not exist")
            elif argv[0] in scripts:
                target = scripts[argv[0]].split(":")[0]
                if module_file(target) is None and not (
                        ROOT / Path(*target.split(".")) / "__init__.py").is_file():
                    problems.append(f"{word} {argv}: script target {target} does not exist")
            else:
                problems.append(f"{word} {argv}: neither python -m nor a project script")
        if word == "ENV":
            for var in re.findall(r"\b(AOI3D_[A-Z0-9_]+)=", args):
                if var not in env_names(CommonSettings) and var not in DOMAIN_VARIABLES:
                    problems.append(f"ENV {var} is neither a CommonSettings field nor a "
                                    "documented domain variable")
    runs = " ".join(args for word, args in instructions if word == "RUN")
    torch_pin = next(d for d in project()["dependencies"] if d.startswith("torch"))
    if not re.search(r"pip install --index-url https://download\.pytorch\.org/whl/cpu "
                     + re.escape(torch_pin) + r"(\s|$)", runs):
        problems.append(f"torch must be installed first as {torch_pin} from the CPU index")
    if not re.search(r"pip install \.(\s|$)", runs):
        problems.append("the project is not installed with `pip install .`")
    return problems


# ------------------------------------------------------------- Prometheus and Grafana checks
def prometheus_problems(doc: dict[str, Any], prom: dict[str, Any]) -> list[str]:
    """Prometheus scrapes exactly the five services' /metrics on their ports."""
    problems = []
    targets: dict[str, int] = {}
    for job in prom.get("scrape_configs", []):
        if job.get("metrics_path", "/metrics") not in kit_routes():
            problems.append(f"job {job['job_name']}: metrics_path is not served")
        for group in job.get("static_configs", []):
            for target in group["targets"]:
                host, _, port = target.rpartition(":")
                targets[host] = int(port)
                if group.get("labels", {}).get("service") != host:
                    problems.append(f"target {target}: label service should be {host!r}")
    want = {name: default_port(name) for name in SERVICES}
    if targets != want:
        problems.append(f"scrape targets {targets} != services {want}")
    prometheus = doc["services"].get("prometheus", {})
    mounts = [str(v) for v in prometheus.get("volumes", [])]
    if "./deploy/prometheus/prometheus.yml:/etc/prometheus/prometheus.yml:ro" not in mounts:
        problems.append("prometheus: deploy/prometheus/prometheus.yml is not mounted")
    return problems


def image_problems(doc: dict[str, Any]) -> list[str]:
    """Pinned images: ours tagged with the project version, third-party ones with X.Y.Z."""
    problems = []
    pins = {"prometheus": r"prom/prometheus:v\d+\.\d+\.\d+",
            "grafana": r"grafana/grafana:\d+\.\d+\.\d+"}
    for name, service in doc["services"].items():
        image = service.get("image", "")
        if "build" in service:
            if image != f"aoi3d:{project()['version']}":
                problems.append(f"{name}: image {image!r}, want aoi3d:{project()['version']}")
        elif not re.fullmatch(pins.get(name, r"\S+:\d[\w.\-]*"), image):
            problems.append(f"{name}: image {image!r} is not pinned to a concrete version")
    return problems


def grafana_problems(doc: dict[str, Any], dashboard: dict[str, Any]) -> list[str]:
    """Provisioned datasource and dashboards line up with compose and the dashboard JSON."""
    problems = []
    grafana = doc["services"].get("grafana", {})
    mounts = {str(v).split(":")[0]: str(v).split(":")[1] for v in grafana.get("volumes", [])}
    env = environment(grafana)
    if env.get("GF_AUTH_ANONYMOUS_ENABLED") != "true" or \
            env.get("GF_AUTH_ANONYMOUS_ORG_ROLE") != "Viewer":
        problems.append("grafana: anonymous viewer access is not enabled")
    if mounts.get("./deploy/grafana/provisioning") != "/etc/grafana/provisioning":
        problems.append("grafana: deploy/grafana/provisioning is not mounted")
    sources = [ds for f in sorted((GRAFANA_DIR / "provisioning" / "datasources").glob("*.yaml"))
               for ds in _yaml(f)["datasources"]]
    uids = {ds["uid"] for ds in sources if ds["type"] == "prometheus"}
    prom_port = {t for _, t in published_ports(doc["services"].get("prometheus", {}))}
    for ds in sources:
        m = re.fullmatch(r"http://([\w-]+):(\d+)", ds["url"])
        if not m or m[1] not in doc["services"] or int(m[2]) not in prom_port:
            problems.append(f"datasource {ds['name']}: {ds['url']} is not the prometheus service")
    providers = [p for f in sorted((GRAFANA_DIR / "provisioning" / "dashboards").glob("*.yaml"))
                 for p in _yaml(f)["providers"]]
    paths = {p["options"]["path"] for p in providers}
    if mounts.get("./deploy/grafana/dashboards") not in paths:
        problems.append(f"grafana: dashboards mounted at "
                        f"{mounts.get('./deploy/grafana/dashboards')}, providers read {paths}")
    home = env.get("GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH")
    if home and home != f"{mounts.get('./deploy/grafana/dashboards')}/{DASHBOARD_FILE.name}":
        problems.append(f"grafana: home dashboard {home} is not the mounted {DASHBOARD_FILE.name}")
    for node in _walk(dashboard):
        ds = node.get("datasource")
        if isinstance(ds, dict) and ds.get("type") == "prometheus" and ds.get("uid") not in uids:
            problems.append(f"dashboard uses datasource uid {ds.get('uid')!r}, "
                            f"provisioned: {sorted(uids)}")
    return problems


# ------------------------------------------------------------------------ dashboard metrics
METRIC_TYPES = {"Counter", "Gauge", "Histogram", "Summary", "Info", "Enum"}
EXPOSED_SUFFIXES = {
    "Counter": ("_total", "_created"),
    "Gauge": ("",),
    "Histogram": ("_bucket", "_sum", "_count", "_created"),
    "Summary": ("", "_sum", "_count", "_created"),
    "Info": ("_info",),
    "Enum": ("",),
}


def defined_metrics(root: Path = ROOT / "services") -> dict[str, set[str]]:
    """Exposed series names → label names, from the prometheus_client calls in ``root``.

    prometheus_client strips ``_total`` from a counter's name and exposes ``<name>_total``;
    a histogram exposes ``_bucket``/``_sum``/``_count``.
    """
    exposed: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        if "pb" in path.relative_to(root).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Call):
                continue
            kind = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
            if kind not in METRIC_TYPES:
                continue
            kwargs = {k.arg: k.value for k in node.keywords}
            name_node = node.args[0] if node.args else kwargs.get("name")
            if not (isinstance(name_node, ast.Constant) and isinstance(name_node.value, str)
                    and name_node.value.startswith("aoi3d_")):
                continue
            labels_node = node.args[2] if len(node.args) > 2 else kwargs.get("labelnames")
            labels = {e.value for e in getattr(labels_node, "elts", [])
                      if isinstance(e, ast.Constant)}
            base = name_node.value
            if kind == "Counter":
                base = base.removesuffix("_total")
            for suffix in EXPOSED_SUFFIXES[kind]:
                exposed.setdefault(base + suffix, set()).update(labels)
    return exposed


def _walk(node: Any) -> Iterator[dict[str, Any]]:
    if isinstance(node, dict):
        yield node
        for value in node.values():
            yield from _walk(value)
    elif isinstance(node, list):
        for value in node:
            yield from _walk(value)


def dashboard_queries(dashboard: dict[str, Any]) -> list[str]:
    """Every PromQL expression of the panels and the template variables."""
    queries = [t["expr"] for p in _walk(dashboard.get("panels", []))
               for t in p.get("targets", []) if "expr" in t]
    for var in dashboard.get("templating", {}).get("list", []):
        query = var.get("query")
        queries.append(query.get("query", "") if isinstance(query, dict) else str(query or ""))
    return queries


def dashboard_problems(dashboard: dict[str, Any], metrics: dict[str, set[str]],
                       service_labels: set[str]) -> list[str]:
    """Queries only name metrics (and labels) that the code defines."""
    problems = []
    labels_known = set().union(*metrics.values(), PROMETHEUS_TARGET_LABELS, service_labels)
    queries = dashboard_queries(dashboard)
    if not queries:
        problems.append("the dashboard has no queries")
    for expr in queries:
        names = set(re.findall(r"(?<![\w:])aoi3d_[A-Za-z0-9_]+", expr))
        names |= {n for n in PROMETHEUS_BUILTIN_METRICS if re.search(rf"(?<![\w:]){n}\{{", expr)}
        if not names:
            problems.append(f"query names no aoi3d metric: {expr}")
        for name in sorted(names - set(metrics) - PROMETHEUS_BUILTIN_METRICS):
            problems.append(f"{name} is not defined in services/ (query: {expr})")
        used = set(re.findall(r"\b(?:by|without)\s*\(([^)]*)\)", expr))
        label_names = {lbl.strip() for group in used for lbl in group.split(",") if lbl.strip()}
        label_names |= set(re.findall(r"[{,]\s*([A-Za-z_]\w*)\s*(?:=~|!~|!=|=)", expr))
        label_names |= set(re.findall(r"label_values\([^,]+,\s*(\w+)\)", expr))
        label_names |= set(re.findall(r"\{\{\s*(\w+)\s*\}\}", expr))
        for label in sorted(label_names - labels_known):
            problems.append(f"label {label!r} is neither declared in services/ nor a target "
                            f"label (query: {expr})")
    for panel in _walk(dashboard.get("panels", [])):
        for target in panel.get("targets", []):
            for label in re.findall(r"\{\{\s*(\w+)\s*\}\}", target.get("legendFormat", "")):
                if label not in labels_known:
                    problems.append(f"panel {panel.get('title')!r}: legend uses unknown "
                                    f"label {label!r}")
    return problems


def scrape_labels(prom: dict[str, Any]) -> set[str]:
    return {label for job in prom.get("scrape_configs", [])
            for group in job.get("static_configs", []) for label in group.get("labels", {})}


# ------------------------------------------------------------------------------------ tests
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
    assert env_problems(compose) == []


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


def test_dataset_job_feeds_camera_and_trainer(compose):
    assert dataset_problems(compose) == []


def test_dataset_job_runs_a_real_cli_command(compose):
    """`aoi3d scene generate --out DIR` exists in the CLI (typer app → click command)."""
    import typer

    from aoi3d.cli import app

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
    (the rotor close-up at 6 rpm) where camera and trainer read it, as `aoi3d up` does."""
    import typer

    from aoi3d.cli import app
    from aoi3d.cli.scene import scene_config
    from aoi3d.experiment.config import EXPERIMENT_SCENE
    from aoi3d.scene import SceneConfig
    from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_SCENES

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
    broken["services"]["trainer"]["command"] = ["python", "-m", "services.trainr"]
    broken["services"]["network"]["environment"]["AOI3D_RUN_ID"] = "other"
    broken["services"]["scheduler"]["healthcheck"]["test"][3] = (
        "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8103/ready')")
    broken["services"]["metrics"]["depends_on"] = {"router": {"condition": "service_started"}}
    broken["services"]["trainer"]["depends_on"].pop("dataset")

    assert any("AOI3D_CAMERA_PORT=8199" in p for p in service_problems(broken, "camera"))
    assert any("services.trainr" in p for p in service_problems(broken, "trainer"))
    assert any("/ready," in p for p in service_problems(broken, "scheduler"))
    assert any("service_healthy" in p for p in service_problems(broken, "metrics"))
    assert any("AOI3D_CAMERA_PERIOD" in p for p in env_problems(broken))
    assert any("AOI3D_RUN_ID differs" in p for p in shared_env_problems(broken))
    assert any("trainer: must wait for dataset" in p for p in dataset_problems(broken))

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
    assert not dockerignore_excludes("aoi3d/cli/__init__.py", ignore)
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
