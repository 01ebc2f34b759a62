"""The compose deployment's checks: each returns a list of problems, so that a test can feed it
the real ``compose.yaml`` and expect none, or a deliberately broken one and see it fail.

Services, environment, TLS, the dataset job, volumes, limits, secrets, ports, allowed hosts and the
three-host file; the image's and the monitoring's checks are in :mod:`tests.support.deploy_checks`.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path
from typing import Any

import jsonschema
from pydantic_settings import BaseSettings

from services.kit.settings import CommonSettings, ServiceSettings
from tests.support.compose_file import (
    _INTERPOLATION,
    ROOT,
    command,
    environment,
    interpolate,
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

SERVICES = ("camera", "network", "scheduler", "dispatcher", "metrics")
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
    """The one-shot dataset job writes where camera and dispatcher read, and they wait for it."""
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
    for name in ("camera", "dispatcher"):
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


