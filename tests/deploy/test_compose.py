"""The container deployment matches the code it runs.

Static: no container engine is needed (``make compose-test``, tests/containers/, builds and
runs the stack for real).  ``compose.yaml`` is validated against the Compose
Specification JSON schema (vendored as ``tests/data/compose-spec.json``), then every command,
port, healthcheck, environment variable, volume, scrape target, Grafana provisioning file and
dashboard query is checked against the code it refers to (settings classes, ``__main__``
modules, the CLI, the metric definitions in ``services/``).

The checks are functions that return a list of problems, so the tests at the end can also
feed them a deliberately broken deployment and see them fail.
"""

from __future__ import annotations

import copy
import fnmatch
import importlib
import json
import os
import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from pydantic_settings import BaseSettings

from services.configdoc import DOMAIN_VARIABLES
from services.kit.settings import CommonSettings, ServiceSettings
from tests.support.compose_file import (
    _INTERPOLATION,
    ROOT,
    _yaml,
    command,
    defined_metrics,
    environment,
    interpolate,
    project,
)

COMPOSE_FILE = ROOT / "compose.yaml"
SCHEMA_FILE = ROOT / "tests" / "data" / "compose-spec.json"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
LOCK_FILE = ROOT / "deploy" / "requirements.lock"
SECRETS_SCRIPT = ROOT / "deploy" / "secrets.sh"
PROMETHEUS_DIR = ROOT / "deploy" / "prometheus"
PROMETHEUS_FILE = PROMETHEUS_DIR / "prometheus.yml"
GRAFANA_DIR = ROOT / "deploy" / "grafana"
DASHBOARD_FILE = GRAFANA_DIR / "dashboards" / "aoi3d.json"

SERVICES = ("camera", "network", "scheduler", "trainer", "metrics")
"""The five pipeline services; each runs as ``python -m services.<name>``."""

HTTP_SERVICES = (*SERVICES, "console", "recorder")
"""Every service with a REST API in compose.yaml (the console calls the others by name)."""

AWAITED: dict[str, str] = {}
"""Names compose.yaml already uses for code not in this tree yet. Each is checked like any
other as soon as the code has it; until then its absence is tolerated, and only for these
names (test_awaited_names_report lists them)."""

SECRET_FIELDS = {"AOI3D_CONTROL_TOKEN", "AOI3D_ZENOH_PASSWORD"}
"""Settings whose value may come from a file: ``<NAME>_FILE`` holds its path (compose secrets)."""

PROMETHEUS_BUILTIN_METRICS = {"up"}
"""Series Prometheus itself writes for every target (not defined in our code)."""

PROMETHEUS_TARGET_LABELS = {"job", "instance", "le", "quantile", "__name__"}
"""Labels every scraped series may carry besides those our code declares."""



# ---------------------------------------------------------------------------------- loading


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return _yaml(COMPOSE_FILE)


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))








def published_ports(service: dict[str, Any]) -> set[tuple[int, int]]:
    """``(published, target)`` pairs from short (``[ip:]host:container``) or long syntax,
    with ``${VAR:-default}`` at its default."""
    pairs = set()
    for entry in service.get("ports") or []:
        if isinstance(entry, dict):
            pairs.add((int(interpolate(entry.get("published", entry["target"]))),
                       int(entry["target"])))
            continue
        spec = interpolate(entry).split("/")[0]
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
    class derived from ``ServiceSettings`` (or holding a ``common`` field, as the
    reconstruction worker's) also reads ``CommonSettings`` (prefix ``AOI3D_``),
    and so does the router for the Zenoh credentials (``router_config``).
    """
    name = f"{module}.settings" if (ROOT / Path(*module.split(".")) / "settings.py").is_file() \
        else module
    mod = importlib.import_module(name)
    found: list[type[BaseSettings]] = [
        obj for obj in vars(mod).values()
        if isinstance(obj, type) and issubclass(obj, BaseSettings) and obj.__module__ == name]
    if any(issubclass(cls, ServiceSettings) or "common" in cls.model_fields for cls in found) \
            or module == "services.router":
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


def awaited_missing() -> list[str]:
    """The AWAITED names the code does not have yet."""
    missing = []
    for name in AWAITED:
        if name.startswith("services."):
            if module_file(name) is None:
                missing.append(name)
            continue
        known = set().union(*(env_names(cls) for cls in all_settings_classes()))
        if name not in known and not (name.endswith("_FILE") and name[:-5] in known):
            missing.append(name)
    return missing


def all_settings_classes() -> list[type[BaseSettings]]:
    """The settings classes of the router and of every service in the code."""
    classes: list[type[BaseSettings]] = []
    for module in ["services.router", *(f"services.{n}" for n in HTTP_SERVICES)]:
        if module_file(module) is not None:
            classes += settings_classes(module)
    return classes


def env_problems(doc: dict[str, Any], tolerate: frozenset[str] = frozenset()) -> list[str]:
    """Every ``AOI3D_*`` variable given to an aoi3d process is read by its settings
    (``<NAME>_FILE`` for a secret field ``<NAME>``). Names in ``tolerate`` (awaited code) are
    not reported."""
    problems = []
    for name, service in doc["services"].items():
        cmd = command(service)
        env = {k: v for k, v in environment(service).items() if k.startswith("AOI3D_")}
        if cmd[:2] == ["python", "-m"] and len(cmd) >= 3:
            if module_file(cmd[2]) is None:
                if cmd[2] not in tolerate:
                    problems.append(f"{name}: module {cmd[2]} does not exist")
                continue
            classes = settings_classes(cmd[2])
        elif cmd[:1] == ["aoi3d"]:
            classes = [CommonSettings]
        else:
            classes = []
        known = set().union(*(env_names(cls) for cls in classes)) if classes else set()
        known |= {f"{field}_FILE" for field in known & SECRET_FIELDS}
        for var in sorted(set(env) - known - tolerate):
            problems.append(f"{name}: {var} is not a field of "
                            f"{[c.__name__ for c in classes] or 'any settings class'}")
    return problems


def shared_env_problems(doc: dict[str, Any]) -> list[str]:
    """The five services agree on the run (CommonSettings) and reach the router over TLS."""
    problems = []
    common_vars = env_names(CommonSettings)
    envs = {n: environment(doc["services"][n]) for n in SERVICES if n in doc["services"]}
    for var in sorted(common_vars):
        values = {n: env.get(var) for n, env in envs.items()}
        if len(set(values.values())) > 1:
            problems.append(f"{var} differs between services: {values}")
    router = doc["services"].get("router", {})
    listen = environment(router).get("AOI3D_ROUTER_LISTEN", "")
    m = re.fullmatch(r"tls/0\.0\.0\.0:(\d+)", listen)
    if m is None:
        problems.append(f"router: AOI3D_ROUTER_LISTEN={listen!r}, want tls/0.0.0.0:<port>")
        return problems
    zenoh_port = int(m[1])
    if f"('127.0.0.1', {zenoh_port})" not in healthcheck_code(router):
        problems.append(f"router: healthcheck does not connect to 127.0.0.1:{zenoh_port}")
    for n, env in envs.items():
        if env.get("AOI3D_ZENOH_CONNECT") != f"tls/router:{zenoh_port}":
            problems.append(f"{n}: AOI3D_ZENOH_CONNECT={env.get('AOI3D_ZENOH_CONNECT')!r}, "
                            f"want tls/router:{zenoh_port}")
        if env.get("AOI3D_ZENOH_MODE") != "client":
            problems.append(f"{n}: AOI3D_ZENOH_MODE must be client (the router is separate)")
    return problems


TLS_SECRETS = {"AOI3D_ZENOH_TLS_ROOT_CA": "zenoh_tls_ca",
               "AOI3D_ZENOH_TLS_CERT": "zenoh_tls_{}_cert",
               "AOI3D_ZENOH_TLS_KEY": "zenoh_tls_{}_key"}
"""The TLS files of a Zenoh peer in compose (``{}``: ``router`` for the router, ``client``
for the services), as deploy/secrets.sh names them."""


def tls_problems(doc: dict[str, Any]) -> list[str]:
    """Every Zenoh peer runs mutual TLS with the secrets `make secrets` writes: the router
    its own certificate (its service name is in its SANs), the services the client one."""
    problems = []
    for name, service in aoi3d_services(doc).items():
        env = environment(service)
        who = "router" if name == "router" else "client"
        for var, secret in TLS_SECRETS.items():
            want = f"/run/secrets/{secret.format(who)}"
            if env.get(var) != want:
                problems.append(f"{name}: {var}={env.get(var)!r}, want {want}")
        if env.get("AOI3D_ZENOH_TLS_MTLS") != "true":
            problems.append(f"{name}: AOI3D_ZENOH_TLS_MTLS is not true")
    script = SECRETS_SCRIPT.read_text(encoding="utf-8")
    defaults = re.search(r"\$\{AOI3D_ZENOH_ROUTERS:-([^}]*)\}", script)
    made = set(defaults[1].split(",")) if defaults else set()
    for router in (n for n in doc["services"] if n == "router" or n.startswith("router-")):
        if router not in made:
            problems.append(f"deploy/secrets.sh does not make a certificate for the {router} "
                            "service")
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


# ------------------------------------------------------- volumes, limits, secrets, ports
def aoi3d_services(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The long-running aoi3d processes (built from deploy/Dockerfile; not the one-shot job)."""
    return {n: s for n, s in doc["services"].items()
            if "build" in s and s.get("restart", "no") != "no"}


def workdir() -> str:
    return [a for w, a in dockerfile_instructions(DOCKERFILE) if w == "WORKDIR"][-1]


def runs_volume_problems(doc: dict[str, Any]) -> list[str]:
    """runs/ (relative to the image's working folder) is a named volume in every aoi3d
    service, so checkpoints, PPO runs and logs outlive the containers."""
    problems = []
    runs = f"{workdir().rstrip('/')}/runs"
    named = set(doc.get("volumes") or {})
    for name, service in aoi3d_services(doc).items():
        if name == "router":
            continue
        mounts = {str(v).split(":")[1]: str(v).split(":")[0] for v in service.get("volumes", [])}
        if mounts.get(runs) not in named:
            problems.append(f"{name}: {runs} is not a named volume (runs/ dies with the container)")
    return problems


def _cpus(value: object) -> float:
    return float(interpolate(value))


def limits_problems(doc: dict[str, Any]) -> list[str]:
    """Every container has a CPU and a memory limit; a worker's torch threads = its CPUs."""
    problems = []
    for name, service in doc["services"].items():
        if "cpus" not in service or "mem_limit" not in service:
            problems.append(f"{name}: no cpus/mem_limit")
            continue
        if not 0 < _cpus(service["cpus"]) <= 2:
            problems.append(f"{name}: cpus {_cpus(service['cpus'])} (the default must fit a "
                            "2-core machine: the engine refuses more CPUs than it has)")
        if not re.fullmatch(r"\d+[kmg]", interpolate(service["mem_limit"])):
            problems.append(f"{name}: mem_limit {service['mem_limit']!r} is not like 512m")
    recon = doc["services"].get("recon", {})
    threads = environment(recon).get("AOI3D_RECON_TORCH_THREADS")
    if "cpus" in recon and threads != interpolate(recon["cpus"]):
        problems.append(f"recon: AOI3D_RECON_TORCH_THREADS={threads} but cpus="
                        f"{interpolate(recon['cpus'])}")
    cpus_var = re.fullmatch(_INTERPOLATION, str(recon.get("cpus", "")))
    threads_var = re.fullmatch(_INTERPOLATION, str(
        (recon.get("environment") or {}).get("AOI3D_RECON_TORCH_THREADS", "")))
    if not (cpus_var and threads_var and cpus_var["name"] == threads_var["name"]):
        problems.append("recon: cpus and AOI3D_RECON_TORCH_THREADS must come from one variable")
    return problems


def secret_file_problems(doc: dict[str, Any], name: str, path: str) -> list[str]:
    """``path`` is /run/secrets/<secret> of a secret the service lists and compose defines."""
    m = re.fullmatch(r"/run/secrets/([\w-]+)", path)
    if m is None:
        return [f"{name}: {path} is not a compose secret (/run/secrets/<name>)"]
    listed = {s if isinstance(s, str) else s["source"]
              for s in doc["services"][name].get("secrets", [])}
    problems = []
    if m[1] not in listed:
        problems.append(f"{name}: reads {path} but does not list secret {m[1]!r}")
    if m[1] not in (doc.get("secrets") or {}):
        problems.append(f"{name}: secret {m[1]!r} is not defined in compose.yaml")
    return problems


def secrets_problems(doc: dict[str, Any]) -> list[str]:
    """Secrets come from files `make secrets` writes; *_FILE variables name listed secrets;
    every aoi3d HTTP service gets the control token, every Zenoh peer the Zenoh password."""
    problems = []
    script = SECRETS_SCRIPT.read_text(encoding="utf-8")
    for secret, spec in (doc.get("secrets") or {}).items():
        file = interpolate(spec.get("file", ""))
        if file != f"./deploy/secrets/{secret}":
            problems.append(f"secret {secret}: file {file!r}, want ./deploy/secrets/{secret}")
        if secret not in script:
            problems.append(f"secret {secret}: deploy/secrets.sh does not write it")
    for name, service in doc["services"].items():
        for value in environment(service).values():
            if value.startswith("/run/secrets/"):
                problems += secret_file_problems(doc, name, value)
    for name, service in aoi3d_services(doc).items():
        env = environment(service)
        if name != "router" and env.get("AOI3D_CONTROL_TOKEN_FILE") != "/run/secrets/control_token":
            problems.append(f"{name}: AOI3D_CONTROL_TOKEN_FILE is not the control_token secret")
        if env.get("AOI3D_ZENOH_PASSWORD_FILE") != "/run/secrets/zenoh_password":
            problems.append(f"{name}: AOI3D_ZENOH_PASSWORD_FILE is not the zenoh_password secret")
        if "AOI3D_CONTROL_TOKEN" in env or "AOI3D_ZENOH_PASSWORD" in env:
            problems.append(f"{name}: a secret is written into compose.yaml")
    users = {environment(s).get("AOI3D_ZENOH_USER") for s in aoi3d_services(doc).values()}
    if len(users) != 1 or None in users:
        problems.append(f"the Zenoh peers disagree on AOI3D_ZENOH_USER: {users}")
    return problems


def ports_problems(doc: dict[str, Any]) -> list[str]:
    """Every published port is on 127.0.0.1 and movable by its own AOI3D_PORT_<NAME>."""
    problems = []
    seen: dict[str, str] = {}
    for name, service in doc["services"].items():
        for entry in service.get("ports") or []:
            m = re.fullmatch(r"127\.0\.0\.1:\$\{(AOI3D_PORT_[A-Z]+):-(\d+)\}:(\d+)",
                             str(entry))
            if m is None:
                problems.append(f"{name}: port {entry!r} is not "
                                "127.0.0.1:${AOI3D_PORT_<NAME>:-<port>}:<port>")
                continue
            if m[2] != m[3]:
                problems.append(f"{name}: publishes {m[3]} as {m[2]} by default")
            if m[1] in seen:
                problems.append(f"{name}: {m[1]} also moves {seen[m[1]]}'s port")
            seen[m[1]] = name
    return problems


def allowed_hosts_problems(doc: dict[str, Any]) -> list[str]:
    """AOI3D_ALLOWED_HOSTS admits localhost and every name the services are called by."""
    problems = []
    callers_use = {n for n in HTTP_SERVICES if n in doc["services"]}
    for name in callers_use:
        hosts = set(environment(doc["services"][name]).get("AOI3D_ALLOWED_HOSTS", "").split(","))
        missing = (callers_use | {"127.0.0.1", "localhost"}) - hosts
        if missing:
            problems.append(f"{name}: AOI3D_ALLOWED_HOSTS lacks {sorted(missing)}")
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
    s["trainer"]["secrets"] = ["control_token", "zenoh_password"]
    assert any("want tls/0.0.0.0" in p for p in shared_env_problems(broken))
    assert any("camera: AOI3D_ZENOH_TLS_CERT" in p for p in tls_problems(broken))
    assert any("metrics: AOI3D_ZENOH_TLS_MTLS" in p for p in tls_problems(broken))
    assert any("trainer: reads /run/secrets/zenoh_tls_ca" in p for p in secrets_problems(broken))


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
    (the rotor close-up at 6 rpm) where camera and trainer read it, as `aoi3d up` does."""
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
    assert not dockerignore_excludes("aoi3d/ports.py", ignore)
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


# ---------------------------------------------------------------- compose.multihost.yaml
MULTIHOST_FILE = ROOT / "compose.multihost.yaml"


def multihost_problems(doc: dict[str, Any]) -> list[str]:
    """Three hosts joined router to router only: every aoi3d process reaches its own host's
    router, the workers run on worker hosts only, only routers are on the mesh, and every
    router but the edge's connects to the edge router."""
    problems = []
    services = doc["services"]
    hosts = {"edge": "router-edge", "host-a": "router-a", "host-b": "router-b"}
    for name, service in services.items():
        nets = set(service.get("networks") or [])
        if name.startswith("router-"):
            if "mesh" not in nets or len(nets) != 2:
                problems.append(f"{name}: a router is on its host's network and the mesh only")
            connect = environment(service).get("AOI3D_ROUTER_CONNECT")
            if name != "router-edge" and connect != "tls/router-edge:7447":
                problems.append(f"{name}: must connect to tls/router-edge:7447, not {connect}")
            continue
        if "mesh" in nets:
            problems.append(f"{name}: only routers are on the mesh")
        if len(nets) != 1:
            problems.append(f"{name}: on one host's network, not {sorted(nets)}")
            continue
        (net,) = nets
        if name == "dataset":
            continue
        connect = environment(service).get("AOI3D_ZENOH_CONNECT")
        if connect != f"tls/{hosts[net]}:7447":
            problems.append(f"{name}: on {net} but connects to {connect}")
        if command(service)[2:3] == ["services.recon"] and net == "edge":
            problems.append(f"{name}: a reconstruction worker on the edge host")
    return problems


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
