"""The image's and the monitoring's checks (Dockerfile, .dockerignore, the lock, Prometheus,
Grafana and its dashboard), each returning a list of problems like
:mod:`tests.support.compose_checks`.
"""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from services.configdoc import DOMAIN_VARIABLES
from services.kit.settings import CommonSettings
from tests.support.compose_checks import (
    DASHBOARD_FILE,
    DOCKERFILE,
    GRAFANA_DIR,
    HTTP_SERVICES,
    LOCK_FILE,
    PROMETHEUS_BUILTIN_METRICS,
    PROMETHEUS_DIR,
    PROMETHEUS_TARGET_LABELS,
    SERVICES,
    default_port,
    dockerfile_instructions,
    env_names,
    kit_routes,
    module_file,
    published_ports,
    secret_file_problems,
)
from tests.support.compose_file import (
    ROOT,
    _yaml,
    command,
    environment,
    interpolate,
    project,
)

# ------------------------------------------------------------------------------ Dockerfile


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
    args_default = dict(a.split("=", 1) for w, a in instructions if w == "ARG" and "=" in a)
    base = args_default.get("BASE_IMAGE", "")
    if not re.fullmatch(r"python:3\.11-slim-bookworm@sha256:[0-9a-f]{64}", base):
        problems.append(f"ARG BASE_IMAGE={base!r}: want python:3.11-slim-bookworm pinned by "
                        "digest (requires-python; bookworm, as deploy/base-image.sh)")
    for word, args in instructions:
        if word == "FROM" and not re.fullmatch(r"\$\{BASE_IMAGE\}( AS \w+)?", args):
            problems.append(f"FROM {args}: every stage builds on ${{BASE_IMAGE}}")
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
    copies = {shlex.split(a)[-1]: shlex.split(a)[-2] for w, a in instructions if w == "COPY"}
    lock_in_image = next((dst for dst, src in copies.items()
                          if src == LOCK_FILE.relative_to(ROOT).as_posix()), None)
    if lock_in_image is None:
        problems.append(f"{LOCK_FILE.relative_to(ROOT)} is not copied into the build")
    elif not re.search(r"pip install --require-hashes .*-r " + re.escape(lock_in_image), runs):
        problems.append("the locked dependencies are not installed with --require-hashes")
    if "download.pytorch.org/whl/cpu" not in args_default.get("PIP_SOURCE", ""):
        problems.append("PIP_SOURCE must default to the PyTorch CPU index (torch's CPU build)")
    if not re.search(r"pip install --no-deps --no-build-isolation --no-index /src(\s|$)", runs):
        problems.append("the project is not installed from /src without further downloads")
    return problems


def lock_problems(lock_text: str) -> list[str]:
    """deploy/requirements.lock is current: made from today's [project] dependencies, every
    pin with a hash, torch as the CPU build of pyproject's pin."""
    problems = []
    resolved_from = re.findall(r"^#   (.+)$", lock_text, flags=re.M)
    want = [*project()["dependencies"], "setuptools>=77"]
    if resolved_from != want:
        problems.append(f"the lock was made from {resolved_from}, pyproject asks {want}: "
                        "run `make lock`")
    entries = re.findall(r"^([A-Za-z0-9._-]+)==(\S+) \\\n    --hash=sha256:([0-9a-f]{64})$",
                         lock_text, flags=re.M)
    pins = len(re.findall(r"^[A-Za-z0-9._-]+==", lock_text, flags=re.M))
    if len(entries) != pins or not entries:
        problems.append(f"{pins - len(entries)} of {pins} pins have no sha256 hash")
    versions = {name: version for name, version, _ in entries}
    torch_pin = next(d for d in project()["dependencies"] if d.startswith("torch"))
    if versions.get("torch") != torch_pin.split("==")[1] + "+cpu":
        problems.append(f"torch is locked as {versions.get('torch')}, want the CPU build of "
                        f"{torch_pin}")
    dev = {re.split(r"[<>=!~\[ ]", d)[0].lower()
           for d in project().get("optional-dependencies", {}).get("dev", [])}
    runtime = {re.split(r"[<>=!~\[ ]", d)[0].lower() for d in want}
    for name in sorted((dev - runtime) & set(versions)):
        problems.append(f"{name} (a dev extra) is in the image's lock")
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
    optional = {name: default_port(name) for name in HTTP_SERVICES[len(SERVICES):]
                if module_file(f"services.{name}.settings") is not None}
    scraped_extra = {h: p for h, p in targets.items() if h not in want}
    if {h: p for h, p in targets.items() if h in want} != want or \
            any(optional.get(h) != p for h, p in scraped_extra.items()):
        problems.append(f"scrape targets {targets} != services {want} (+ {optional})")
    prometheus = doc["services"].get("prometheus", {})
    mounts = {str(v).split(":")[0]: str(v).split(":")[1] for v in prometheus.get("volumes", [])}
    if mounts.get("./deploy/prometheus") != "/etc/prometheus":
        problems.append("prometheus: the deploy/prometheus/ folder is not mounted at "
                        "/etc/prometheus (config and rules)")
    flags = command(prometheus)
    if "--config.file=/etc/prometheus/prometheus.yml" not in flags:
        problems.append(f"prometheus: {flags} does not read /etc/prometheus/prometheus.yml")
    data = next((f.split("=", 1)[1] for f in flags if f.startswith("--storage.tsdb.path=")),
                None)
    if data is None or not any(str(v).split(":")[1] == data
                               for v in prometheus.get("volumes", [])):
        problems.append(f"prometheus: its TSDB ({data}) is not on a volume")
    for pattern in prom.get("rule_files") or []:
        if pattern.startswith("/") and not pattern.startswith("/etc/prometheus/"):
            problems.append(f"rule_files {pattern}: outside the mounted folder")
            continue
        rel = pattern.removeprefix("/etc/prometheus/")
        if not list(PROMETHEUS_DIR.glob(rel)):
            problems.append(f"rule_files {pattern}: no file in deploy/prometheus/ matches")
    return problems


def image_problems(doc: dict[str, Any]) -> list[str]:
    """Pinned images: ours tagged with the project version, third-party ones with X.Y.Z."""
    problems = []
    pins = {"prometheus": r"prom/prometheus:v\d+\.\d+\.\d+",
            "grafana": r"grafana/grafana:\d+\.\d+\.\d+"}
    for name, service in doc["services"].items():
        image = interpolate(service.get("image", ""))
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
    if "GF_SECURITY_ADMIN_PASSWORD" in env:
        problems.append("grafana: the admin password is written in compose.yaml")
    password_file = env.get("GF_SECURITY_ADMIN_PASSWORD__FILE")
    if password_file is None:
        problems.append("grafana: no admin password file (Grafana's default is admin/admin)")
    else:
        problems += secret_file_problems(doc, "grafana", password_file)
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
        records = set(re.findall(r"(?<![\w:])aoi3d:[A-Za-z0-9_:]+", expr))
        for name in sorted(records - recorded_series()):
            problems.append(f"{name} is not a recording rule of deploy/prometheus/rules/ "
                            f"(query: {expr})")
        if not names and not records:
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


def recorded_series() -> set[str]:
    """The series the recording rules of deploy/prometheus/rules/ write (``aoi3d:…``)."""
    return {r["record"] for f in sorted((PROMETHEUS_DIR / "rules").glob("*.yml"))
            for g in _yaml(f)["groups"] for r in g["rules"] if "record" in r}


def scrape_labels(prom: dict[str, Any]) -> set[str]:
    return {label for job in prom.get("scrape_configs", [])
            for group in job.get("static_configs", []) for label in group.get("labels", {})}


