"""deploy/k8s, checked offline: no cluster, no network.

Every overlay is rendered with kubectl's own kustomize (the kubectl of the machine image; CI
setup, .ci/setup/40-kubectl.sh, fails where there is none) and each resource is validated
against the Kubernetes 1.32 JSON schemas that the ``kubernetes-validate`` package ships
(strict: an unknown field fails too). The project's own checks then run on the rendered
resources: every container has requests and limits, every long-running one its probes (HTTP
services: /readyz and /healthz), every pod runs as non-root on a read-only root filesystem,
every image is pinned, every container's environment is compose's (the one source:
deploy/k8s/generate.py), the secrets the environment names are mounted from the Secrets that
deploy/k8s/secrets.sh makes, and the NetworkPolicies allow exactly the flows that keep Zenoh
between routers. Each check returns a list of problems, so the tests at the end feed it broken
manifests and see it fail - and one renders a broken copy of the tree and sees the schema
validation fail.
"""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.support.compose_file import command as compose_command
from tests.support.compose_file import environment as compose_env
from tests.support.compose_file import project
from tests.support.deploy_modules import load

ROOT = Path(__file__).resolve().parents[2]
K8S = ROOT / "deploy" / "k8s"
OVERLAYS = sorted(p.name for p in (K8S / "overlays").iterdir() if p.is_dir())
KUBERNETES_VERSION = "1.32"
"""The schemas the manifests are validated against (kubectl on the machine image is 1.32)."""
KUBECTL = shutil.which("kubectl")
NAMESPACE = "aoi3d"

gen = load("k8s/generate")
mon = load("monitoring")

pytestmark = pytest.mark.skipif(
    KUBECTL is None, reason="kubectl (with kustomize) not installed; CI's machine image has it "
                            "(.ci/setup/40-kubectl.sh fails the CI run without it)")

COMPOSE_OF: dict[str, tuple[str, str]] = {
    "router": ("compose.yaml", "router"),
    "router-edge": ("compose.multihost.yaml", "router-edge"),
    **{n: ("compose.yaml", n) for n in ("camera", "network", "scheduler", "dispatcher",
                                         "metrics", "console", "recorder", "recon", "dataset",
                                         "prometheus")},
}
"""Kubernetes workload → the compose service whose command and limits it has."""

NO_PROBES = {
    "recon": "no port: a worker only pulls work over Zenoh; Kubernetes restarts it when its "
             "process exits, and its health is its liveliness token (aoi3d_pool_workers)",
}
"""Long-running containers without probes, and why."""

HTTP_PROBED = {"camera", "network", "scheduler", "dispatcher", "metrics", "console"}


# ----------------------------------------------------------------------------- rendering
def kustomize(path: Path) -> list[dict[str, Any]]:
    out = subprocess.run([KUBECTL, "kustomize", str(path)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return [d for d in yaml.safe_load_all(out.stdout) if d]


@pytest.fixture(scope="module")
def rendered() -> dict[str, list[dict[str, Any]]]:
    return {name: kustomize(K8S / "overlays" / name) for name in OVERLAYS}


@pytest.fixture(scope="module")
def secrets_manifest(tmp_path_factory) -> list[dict[str, Any]]:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make the secrets (deploy/secrets.sh)")
    folder = tmp_path_factory.mktemp("secrets") / "s"
    subprocess.run(["bash", str(ROOT / "deploy" / "secrets.sh"), str(folder)], check=True,
                   capture_output=True, timeout=120)
    out = subprocess.run(["bash", str(K8S / "secrets.sh"), str(folder)], capture_output=True,
                         text=True, timeout=120, check=True)
    return [d for d in yaml.safe_load_all(out.stdout) if d]


def workloads(docs: list[dict]) -> list[dict]:
    return [d for d in docs if d["kind"] in ("Deployment", "StatefulSet", "DaemonSet", "Job")]


def pod_spec(workload: dict) -> dict:
    return workload["spec"]["template"]["spec"]


def containers(workload: dict, init: bool = True) -> list[dict]:
    spec = pod_spec(workload)
    return [*(spec.get("initContainers", []) if init else []), *spec["containers"]]


def by_kind(docs: list[dict], kind: str) -> dict[str, dict]:
    return {d["metadata"]["name"]: d for d in docs if d["kind"] == kind}


def name_of(workload: dict) -> str:
    return workload["metadata"]["name"]


# ----------------------------------------------------------------------------- checks
def schema_problems(docs: list[dict]) -> list[str]:
    import kubernetes_validate

    problems = []
    for doc in docs:
        what = f"{doc.get('kind')}/{doc.get('metadata', {}).get('name')}"
        try:
            kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)
        except kubernetes_validate.ValidationError as e:
            path = ".".join(str(p) for p in e.path)
            problems.append(f"{what}: {path}: {e.message}")
        except kubernetes_validate.SchemaNotFoundError as e:
            problems.append(f"{what}: no Kubernetes {KUBERNETES_VERSION} schema ({e.message})")
    return problems


def quantity(text: str | int | float) -> float:
    """A Kubernetes quantity as a number (cores, bytes)."""
    text = str(text)
    units = {"m": 1e-3, "Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "k": 1e3, "M": 1e6, "G": 1e9}
    for unit, factor in units.items():
        if text.endswith(unit):
            return float(text[: -len(unit)]) * factor
    return float(text)


def compose_bytes(text: str) -> float:
    """Compose's mem_limit ("512m" is 512 MiB there, 0.512 bytes to Kubernetes)."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([bkmg]?)", str(text).lower())
    assert m, text
    return float(m[1]) * {"": 1, "b": 1, "k": 2**10, "m": 2**20, "g": 2**30}[m[2]]


def compose_service(workload: str) -> dict:
    file, service = COMPOSE_OF[workload]
    return yaml.safe_load((ROOT / file).read_text())["services"][service]


def hardening_problems(docs: list[dict]) -> list[str]:
    """Probes, resources, non-root, read-only root filesystem, pinned images."""
    problems = []
    version = project()["version"]
    for w in workloads(docs):
        name, spec = name_of(w), pod_spec(w)
        pod_sc = spec.get("securityContext", {})
        if pod_sc.get("runAsNonRoot") is not True or pod_sc.get("runAsUser", 0) == 0:
            problems.append(f"{name}: the pod may run as root (runAsNonRoot, runAsUser)")
        if pod_sc.get("seccompProfile", {}).get("type") != "RuntimeDefault":
            problems.append(f"{name}: no RuntimeDefault seccomp profile")
        if spec.get("automountServiceAccountToken") is not False:
            problems.append(f"{name}: mounts a service account token it does not use")
        for c in containers(w):
            where = f"{name}/{c['name']}"
            sc = c.get("securityContext", {})
            if sc.get("runAsUser") == 0 or sc.get("runAsNonRoot") is False:
                problems.append(f"{where}: runs as root")
            if sc.get("readOnlyRootFilesystem") is not True:
                problems.append(f"{where}: the root filesystem is writable")
            if sc.get("allowPrivilegeEscalation") is not False:
                problems.append(f"{where}: allows privilege escalation")
            if "ALL" not in sc.get("capabilities", {}).get("drop", []):
                problems.append(f"{where}: keeps Linux capabilities")
            res = c.get("resources", {})
            for kind in ("requests", "limits"):
                for r in ("cpu", "memory"):
                    if r not in res.get(kind, {}):
                        problems.append(f"{where}: no {r} {kind[:-1]}")
            image = c.get("image", "")
            if image.startswith("aoi3d:") or image == "aoi3d":
                if image != f"aoi3d:{version}":
                    problems.append(f"{where}: image {image!r}, want aoi3d:{version}")
            elif not re.fullmatch(r"[\w./-]+(:v?\d+\.\d+\.\d+[\w.-]*)?(@sha256:[0-9a-f]{64})?",
                                  image) or ":" not in image.rsplit("/", 1)[-1]:
                problems.append(f"{where}: image {image!r} is not pinned to a version")
            if c.get("imagePullPolicy") == "Always":
                problems.append(f"{where}: imagePullPolicy Always (a pinned image needs none)")
        if w["kind"] == "Job":
            continue
        for c in containers(w, init=False):
            where = f"{name}/{c['name']}"
            if name in NO_PROBES:
                if any(k in c for k in ("readinessProbe", "livenessProbe")):
                    problems.append(f"{where}: probes, though NO_PROBES says why it has none")
                continue
            for probe in ("readinessProbe", "livenessProbe"):
                if probe not in c:
                    problems.append(f"{where}: no {probe}")
            if name in HTTP_PROBED:
                for probe, path in (("readinessProbe", "/readyz"), ("livenessProbe", "/healthz"),
                                    ("startupProbe", "/healthz")):
                    get = c.get(probe, {}).get("httpGet", {})
                    if get.get("path") != path:
                        problems.append(f"{where}: {probe} is not GET {path}")
                    hosts = {h["value"] for h in get.get("httpHeaders", [])
                             if h["name"].lower() == "host"}
                    if get and hosts != {"localhost"}:
                        problems.append(f"{where}: {probe} sends no Host the REST guard "
                                        f"admits (Host: localhost)")
    return problems


def environment_problems(docs: list[dict]) -> list[str]:
    """Every container's environment is exactly compose's (through its ConfigMap), and the
    pods get compose's commands, limits and mounted secrets."""
    problems = []
    config_maps = by_kind(docs, "ConfigMap")

    def env_of(container: dict) -> dict[str, str]:
        env: dict[str, str] = {}
        for source in container.get("envFrom", []):
            ref = source.get("configMapRef", {}).get("name")
            if ref not in config_maps:
                problems.append(f"{container['name']}: envFrom {ref!r}, no such ConfigMap")
                continue
            env.update(config_maps[ref].get("data", {}))
        for item in container.get("env", []):
            env[item["name"]] = item.get("value", "<from elsewhere>")
        return env

    for w in workloads(docs):
        name = name_of(w)
        if name not in COMPOSE_OF:
            problems.append(f"{name}: no compose service says what it runs")
            continue
        service = compose_service(name)
        want_env = gen.environment(name) if name in gen.ENV_SOURCES else {}
        # the generator is one reading of compose; compose's own test helper is another
        if name in gen.ENV_SOURCES and gen.ENV_SOURCES[name][0][2] is None:
            first = compose_env(compose_service(name))
            if {k: v for k, v in want_env.items() if k in first} != first:
                problems.append(f"{name}: generate.py reads compose's environment differently")
        main = pod_spec(w)["containers"][0]
        for c in containers(w):
            got = env_of(c)
            if got != want_env and not (c is not main and not got):
                diff = sorted(set(got.items()) ^ set(want_env.items()))
                problems.append(f"{name}/{c['name']}: environment differs from compose's: "
                                f"{diff}")
        cmd = main.get("command") or []
        args = main.get("args") or []
        want_cmd = compose_command(service)
        if name == "prometheus":
            if args != want_cmd:
                problems.append(f"{name}: args {args}, compose runs {want_cmd}")
        elif cmd + args != want_cmd:
            problems.append(f"{name}: runs {cmd + args}, compose runs {want_cmd}")
        limits = main.get("resources", {}).get("limits", {})
        cpus = float(gen.interpolate(service.get("cpus", 1)))
        mem = compose_bytes(gen.interpolate(service.get("mem_limit", "1g")))
        if "cpu" in limits and quantity(limits["cpu"]) != cpus:
            problems.append(f"{name}: cpu limit {limits['cpu']}, compose's {cpus}")
        if "memory" in limits and quantity(limits["memory"]) != mem:
            problems.append(f"{name}: memory limit {limits['memory']}, compose's {mem:.0f} B")
        # every /run/secrets/<file> the environment names is mounted, from a Secret item
        mounted = set()
        for vol in pod_spec(w).get("volumes", []):
            for source in vol.get("projected", {}).get("sources", []):
                for item in source.get("secret", {}).get("items", []):
                    mounted.add((vol["name"], item["path"], source["secret"]["name"],
                                 item["key"]))
        mounts = {m["name"]: m["mountPath"] for m in main.get("volumeMounts", [])}
        for key, value in want_env.items():
            m = re.fullmatch(r"/run/secrets/([\w-]+)", value)
            if m is None:
                continue
            if not any(mounts.get(vol) == "/run/secrets" and path == m[1]
                       for vol, path, _, _ in mounted):
                problems.append(f"{name}: {key}={value} is not mounted")
        threads = want_env.get("AOI3D_RECON_TORCH_THREADS")
        if threads is not None and float(threads) != quantity(limits.get("cpu", 0)):
            problems.append(f"{name}: {threads} torch threads, CPU limit {limits.get('cpu')}")
    return problems


def secret_refs(docs: list[dict]) -> set[tuple[str, str]]:
    """(Secret, key) every pod mounts."""
    refs = set()
    for w in workloads(docs):
        for vol in pod_spec(w).get("volumes", []):
            for source in vol.get("projected", {}).get("sources", []):
                secret = source.get("secret")
                if secret:
                    refs |= {(secret["name"], item["key"]) for item in secret["items"]}
    return refs


def service_problems(docs: list[dict]) -> list[str]:
    """Services under compose's names and ports, selecting their pods; the routers'."""
    problems = []
    services = by_kind(docs, "Service")
    pods = {name_of(w): w for w in workloads(docs)}
    for name in HTTP_PROBED:
        port = int(gen.environment(name)[f"AOI3D_{name.upper()}_PORT"])
        svc = services.get(name)
        if svc is None:
            problems.append(f"no Service {name}")
            continue
        if [p["port"] for p in svc["spec"]["ports"]] != [port]:
            problems.append(f"Service {name}: ports {svc['spec']['ports']}, want {port}")
        labels = pods[name]["spec"]["template"]["metadata"]["labels"]
        if not set(svc["spec"]["selector"].items()) <= set(labels.items()):
            problems.append(f"Service {name} does not select its pods")
        declared = [p["containerPort"] for p in pods[name]["spec"]["template"]["spec"][
            "containers"][0].get("ports", [])]
        if declared != [port]:
            problems.append(f"{name}: container ports {declared}, its settings say {port}")
    router = services.get("router", {}).get("spec", {})
    if router.get("internalTrafficPolicy") != "Local":
        problems.append("Service router: clients could reach another node's router "
                        "(internalTrafficPolicy is not Local)")
    connect = {gen.environment(n)["AOI3D_ZENOH_CONNECT"] for n in gen.ENV_SOURCES
               if "AOI3D_ZENOH_CONNECT" in gen.environment(n)}
    if connect != {"tls/router:7447"}:
        problems.append(f"clients connect to {connect}, not the node's router")
    if gen.environment("router").get("AOI3D_ROUTER_CONNECT") != "tls/router-edge:7447":
        problems.append("the nodes' routers do not join the hub router-edge")
    if services.get("router-edge", {}).get("spec", {}).get("clusterIP") != "None":
        problems.append("Service router-edge is not headless")
    if pods.get("router", {}).get("kind") != "DaemonSet":
        problems.append("router is not a DaemonSet (one per node)")
    if pods.get("router-edge", {}).get("kind") != "StatefulSet" or \
            pods["router-edge"]["spec"].get("replicas") != 1:
        problems.append("router-edge is not a StatefulSet of one")
    claims = by_kind(docs, "PersistentVolumeClaim")
    metrics_env = gen.environment("metrics")
    state = metrics_env.get("AOI3D_METRICS_STATE_DIR", "")
    metrics_mounts = {m["mountPath"]: m["name"] for m in
                      pods["metrics"]["spec"]["template"]["spec"]["containers"][0][
                          "volumeMounts"]}
    vols = {v["name"]: v for v in pods["metrics"]["spec"]["template"]["spec"]["volumes"]}
    holder = next((p for p in metrics_mounts if state.startswith(p + "/")), None)
    claim = vols.get(metrics_mounts.get(holder, ""), {}).get("persistentVolumeClaim", {})
    if not state or claim.get("claimName") not in claims:
        problems.append(f"the ledger ({state or 'no AOI3D_METRICS_STATE_DIR'}) is not on a "
                        f"PersistentVolumeClaim")
    return problems


def autoscaling_problems(docs: list[dict], adapter_values: dict) -> list[str]:
    problems = []
    hpas = by_kind(docs, "HorizontalPodAutoscaler")
    recon = by_kind(docs, "Deployment")["recon"]
    if not hpas:
        return problems
    hpa = hpas.get("recon")
    if hpa is None or hpa["spec"]["scaleTargetRef"]["name"] != "recon":
        return ["no HPA scales the recon Deployment"]
    if "replicas" in recon["spec"]:
        problems.append("recon sets replicas beside its HPA: every apply resets the count")
    if hpa["spec"]["minReplicas"] < 1:
        problems.append("the HPA may scale the pool to 0 workers")
    metrics = [m["external"]["metric"]["name"] for m in hpa["spec"]["metrics"]
               if m["type"] == "External"]
    rules = adapter_values["rules"]["external"]
    served = {r["name"]["as"]: r for r in rules}
    for metric in metrics:
        if metric not in served:
            problems.append(f"HPA metric {metric} is served by no prometheus-adapter rule")
            continue
        series = served[metric]["seriesQuery"].strip("'\"")
        if series not in mon.RECORDED:
            problems.append(f"adapter rule {metric} reads {series}, no recording rule")
    url = adapter_values["prometheus"]["url"]
    services = by_kind(docs, "Service")
    host = re.fullmatch(r"http://([\w-]+)\.([\w-]+)\.svc(?:\.cluster\.local)?", url)
    if not host or host[2] != NAMESPACE or host[1] not in services or \
            adapter_values["prometheus"]["port"] not in [p["port"] for p in
                                                          services[host[1]]["spec"]["ports"]]:
        problems.append(f"prometheus-adapter reads {url}, not this namespace's Prometheus")
    return problems


# ------------------------------------------------------------------- network policies
def selects(selector: dict | None, labels: dict[str, str]) -> bool:
    if selector is None:
        return False
    for k, v in selector.get("matchLabels", {}).items():
        if labels.get(k) != v:
            return False
    for e in selector.get("matchExpressions", []):
        have = e["key"] in labels
        value = labels.get(e["key"])
        ok = {"In": have and value in e.get("values", []),
              "NotIn": not have or value not in e.get("values", []),
              "Exists": have, "DoesNotExist": not have}[e["operator"]]
        if not ok:
            return False
    return True


def pods_of(docs: list[dict]) -> dict[str, dict]:
    """Pod name → namespace, labels, ports {name: number}; plus the pods around ours."""
    pods = {}
    for w in workloads(docs):
        ports = {p.get("name", str(p["containerPort"])): p["containerPort"]
                 for c in containers(w, init=False) for p in c.get("ports", [])}
        pods[name_of(w)] = {"ns": NAMESPACE, "labels": w["spec"]["template"]["metadata"][
            "labels"], "ports": ports}
    pods["adapter"] = {"ns": "monitoring", "labels": {
        "app.kubernetes.io/name": "prometheus-adapter"}, "ports": {}}
    pods["kube-dns"] = {"ns": "kube-system", "labels": {"k8s-app": "kube-dns"},
                        "ports": {"dns": 53}}
    pods["outsider"] = {"ns": "default", "labels": {"app": "anything"}, "ports": {}}
    return pods


def peer_matches(peer: dict, policy_ns: str, pod: dict) -> bool:
    ns_labels = {"kubernetes.io/metadata.name": pod["ns"]}
    if "ipBlock" in peer:
        return True  # an address range: anything, as far as this check can tell
    if "namespaceSelector" in peer:
        if not selects(peer["namespaceSelector"], ns_labels):
            return False
    elif pod["ns"] != policy_ns:
        return False
    return selects(peer.get("podSelector", {}), pod["labels"])


def port_matches(rule_ports: list[dict] | None, dst: dict, port: int) -> bool:
    if not rule_ports:
        return True
    for p in rule_ports:
        want = p.get("port")
        if want is None or want == port or dst["ports"].get(want) == port:
            return True
    return False


def allowed_flows(docs: list[dict]) -> set[tuple[str, str, int]]:
    """(source pod, destination pod, port) the NetworkPolicies let through."""
    pods = pods_of(docs)
    policies = [d for d in docs if d["kind"] == "NetworkPolicy"]

    def side(pod_name: str, direction: str, peer_name: str, port: int) -> bool:
        pod = pods[pod_name]
        mine = [p for p in policies if p["metadata"].get("namespace", NAMESPACE) == pod["ns"]
                and selects(p["spec"]["podSelector"], pod["labels"])
                and direction in p["spec"].get("policyTypes", ["Ingress"])]
        if not mine:
            return True  # not isolated in this direction
        key, peers_key = ("ingress", "from") if direction == "Ingress" else ("egress", "to")
        dst = pods[pod_name] if direction == "Ingress" else pods[peer_name]
        for policy in mine:
            for rule in policy["spec"].get(key, []):
                peers = rule.get(peers_key)
                if (peers is None or any(peer_matches(peer, pod["ns"], pods[peer_name])
                                         for peer in peers)) and \
                        port_matches(rule.get("ports"), dst, port):
                    return True
        return False

    ours = {name_of(w) for w in workloads(docs)}
    flows = set()
    for src in pods:
        for dst, info in pods.items():
            if src == dst and dst not in ("router", "router-edge"):
                continue
            if src not in ours and dst not in ours:
                continue  # between other namespaces' pods: not this deployment's business
            for port in set(info["ports"].values()):
                if side(src, "Egress", dst, port) and side(dst, "Ingress", src, port):
                    flows.add((src, dst, port))
    return flows


EDGE = ("camera", "network", "scheduler", "dispatcher", "metrics", "console", "recorder")
EXPECTED_FLOWS = {
    # Zenoh: every client to the node routers (its own node's, through the Service)
    *((c, "router", 7447) for c in (*EDGE, "recon")),
    # the mesh: routers to routers (the same DaemonSet on other nodes, and the hub)
    ("router", "router", 7447), ("router", "router-edge", 7447),
    ("router-edge", "router", 7447), ("router-edge", "router-edge", 7447),
    # REST: the console and Prometheus to the services
    *((caller, svc, port) for caller in ("console", "prometheus")
      for svc, port in zip(EDGE, range(8101, 8108), strict=True) if caller != svc),
    # prometheus-adapter to Prometheus; every pod of ours to the cluster DNS
    ("adapter", "prometheus", 9090),
    *((p, "kube-dns", 53) for p in (*EDGE, "recon", "router", "router-edge", "dataset",
                                    "prometheus")),
}


def network_problems(docs: list[dict]) -> list[str]:
    flows = allowed_flows(docs)
    problems = [f"allowed, not wanted: {f}" for f in sorted(flows - EXPECTED_FLOWS)]
    problems += [f"wanted, not allowed: {f}" for f in sorted(EXPECTED_FLOWS - flows)]
    routers = {"router", "router-edge"}
    for src, dst, port in flows:
        if port == 7447 and dst not in routers:
            problems.append(f"Zenoh to a non-router: {src} → {dst}")
        if src not in routers and dst == "router-edge":
            problems.append(f"{src} reaches the hub router-edge directly (another node's)")
    return problems


# -------------------------------------------------------------------------------- tests
def adapter_values() -> dict:
    return yaml.safe_load((K8S / "overlays" / "autoscaled" /
                           "prometheus-adapter.values.yaml").read_text())


def test_generated_files_are_current() -> None:
    assert gen.main(["--check"]) == 0, "run `make k8s` and commit deploy/k8s/base/generated"


def test_a_drifted_environment_is_caught(tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "generated"
    shutil.copytree(gen.OUT, out)
    env = out / "env" / "camera.env"
    env.write_text(env.read_text().replace("AOI3D_TIME_SCALE=0.1", "AOI3D_TIME_SCALE=1"))
    monkeypatch.setattr(gen, "OUT", out)
    assert gen.main(["--check"]) == 1


def test_every_overlay_renders_offline(rendered) -> None:
    assert set(rendered) == {"autoscaled", "fixed-pool"}
    for docs in rendered.values():
        kinds = {d["kind"] for d in docs}
        assert {"DaemonSet", "StatefulSet", "Deployment", "Job", "Service", "NetworkPolicy",
                "PersistentVolumeClaim", "ConfigMap", "Namespace"} <= kinds
        assert all(d["metadata"].get("namespace") == NAMESPACE
                   for d in docs if d["kind"] != "Namespace")
    assert "HorizontalPodAutoscaler" in {d["kind"] for d in rendered["autoscaled"]}


def test_manifests_follow_the_kubernetes_schemas(rendered, secrets_manifest) -> None:
    for name, docs in rendered.items():
        assert schema_problems(docs) == [], name
    assert schema_problems(secrets_manifest) == []


def test_project_checks_pass(rendered) -> None:
    for name, docs in rendered.items():
        assert hardening_problems(docs) == [], name
        assert environment_problems(docs) == [], name
        assert service_problems(docs) == [], name
        assert network_problems(docs) == [], name
        assert autoscaling_problems(docs, adapter_values()) == [], name


def test_the_secrets_hold_what_the_pods_mount(rendered, secrets_manifest) -> None:
    made = {(s["metadata"]["name"], key) for s in secrets_manifest for key in s["data"]}
    for docs in rendered.values():
        assert secret_refs(docs) <= made
    assert all(s["metadata"]["namespace"] == NAMESPACE for s in secrets_manifest)
    assert not any("ca_key" in key for _, key in made), "the CA's key left the host"
    # least privilege, as compose's per-service secrets: workers get no router key
    recon = by_kind(rendered["fixed-pool"], "Deployment")["recon"]
    assert not any("router" in key for _, key in secret_refs([recon]))


def test_autoscaler_reads_the_pool_signal_the_live_test_evaluates(rendered) -> None:
    hpa = by_kind(rendered["autoscaled"], "HorizontalPodAutoscaler")["recon"]
    (metric,) = hpa["spec"]["metrics"]
    assert metric["external"]["metric"]["name"] == "aoi3d_pool_workers_wanted"
    assert "aoi3d:pool_workers_wanted" in mon.RECORDED
    assert "HorizontalPodAutoscaler" not in {d["kind"] for d in rendered["fixed-pool"]}
    assert by_kind(rendered["fixed-pool"], "Deployment")["recon"]["spec"]["replicas"] == 2


# ------------------------------------------------------------- broken manifests fail
def broken(docs: list[dict], kind: str, name: str, mutate) -> list[dict]:
    docs = copy.deepcopy(docs)
    mutate(next(d for d in docs if d["kind"] == kind and d["metadata"]["name"] == name))
    return docs


def test_a_broken_tree_fails_schema_validation(tmp_path: Path) -> None:
    """A manifest edited on disk (a port that is not a number, a field that does not exist),
    rendered by kustomize as CI renders it, fails validation."""
    tree = tmp_path / "k8s"
    shutil.copytree(K8S, tree)
    edge = tree / "base" / "edge.yaml"
    text = edge.read_text()
    assert "containerPort: 8101" in text
    edge.write_text(text.replace("containerPort: 8101", "containerPort: x8101", 1))
    problems = schema_problems(kustomize(tree / "overlays" / "fixed-pool"))
    assert any("camera" in p and "containerPort" in p for p in problems), problems
    edge.write_text(text.replace("strategy: {type: Recreate}",
                                 "strategy: {type: Recreate, surge: 1}", 1))
    problems = schema_problems(kustomize(tree / "overlays" / "fixed-pool"))
    assert any("surge" in p for p in problems), problems


def test_project_checks_catch_broken_manifests(rendered) -> None:
    docs = rendered["fixed-pool"]

    def first(w):
        return pod_spec(w)["containers"][0]

    cases = {
        "no readinessProbe": lambda w: first(w).pop("readinessProbe"),
        "no memory limit": lambda w: first(w)["resources"]["limits"].pop("memory"),
        "may run as root": lambda w: pod_spec(w)["securityContext"].update(runAsUser=0),
        "root filesystem is writable":
            lambda w: first(w)["securityContext"].update(readOnlyRootFilesystem=False),
        "want aoi3d:": lambda w: first(w).update(image="aoi3d:latest"),
        "is not GET /readyz":
            lambda w: first(w)["readinessProbe"]["httpGet"].update(path="/healthz"),
        "Host: localhost":
            lambda w: first(w)["livenessProbe"]["httpGet"].pop("httpHeaders"),
    }
    for want, mutate in cases.items():
        problems = hardening_problems(broken(docs, "Deployment", "camera", mutate))
        assert any(want in p for p in problems), (want, problems)
    problems = hardening_problems(broken(
        docs, "Deployment", "prometheus",
        lambda w: first(w).update(image="prom/prometheus:latest")))
    assert any("not pinned" in p for p in problems), problems

    # the environment drifts from compose's: a value, a variable added in Kubernetes only
    problems = environment_problems(broken(
        docs, "ConfigMap", next(n for n in by_kind(docs, "ConfigMap")
                                if n.startswith("env-dispatcher")),
        lambda cm: cm["data"].update(AOI3D_TIME_SCALE="1")))
    assert any("dispatcher" in p and "AOI3D_TIME_SCALE" in p for p in problems), problems
    problems = environment_problems(broken(
        docs, "Deployment", "recon",
        lambda w: first(w).setdefault("env", []).append({"name": "AOI3D_X", "value": "1"})))
    assert any("recon" in p and "AOI3D_X" in p for p in problems), problems
    problems = environment_problems(broken(
        docs, "Deployment", "network",
        lambda w: first(w)["resources"]["limits"].update(memory="512m")))
    assert any("memory limit" in p for p in problems), problems
    problems = environment_problems(broken(
        docs, "Deployment", "dispatcher",
        lambda w: pod_spec(w)["volumes"][0]["projected"]["sources"].pop()))
    assert any("is not mounted" in p for p in problems), problems

    # a router reachable from another node, the ledger off its claim
    problems = service_problems(broken(
        docs, "Service", "router", lambda s: s["spec"].pop("internalTrafficPolicy")))
    assert any("internalTrafficPolicy" in p for p in problems), problems
    problems = service_problems(broken(
        docs, "Deployment", "metrics",
        lambda w: pod_spec(w)["volumes"].__setitem__(
            next(i for i, v in enumerate(pod_spec(w)["volumes"]) if v["name"] == "runs"),
            {"name": "runs", "emptyDir": {}})))
    assert any("ledger" in p for p in problems), problems

    # the REST APIs open to any pod of the cluster; Zenoh opened to the hub
    problems = network_problems(broken(
        docs, "NetworkPolicy", "rest-apis",
        lambda p: p["spec"]["ingress"][0].update({"from": [{"namespaceSelector": {}}]})))
    assert any("'outsider', 'camera', 8101" in p for p in problems), problems
    # (two mistakes: either policy alone still keeps clients off the hub)
    opened = broken(docs, "NetworkPolicy", "router-mesh",
                    lambda p: p["spec"]["ingress"][0]["from"][0]["podSelector"].update(
                        matchLabels={}))
    problems = network_problems(broken(
        opened, "NetworkPolicy", "zenoh-clients",
        lambda p: p["spec"]["egress"][0]["to"][0]["podSelector"].update(
            matchLabels={"app.kubernetes.io/component": "router"})))
    assert any("reaches the hub" in p for p in problems), problems

    # the autoscaler's metric served by no adapter rule
    values = adapter_values()
    values["rules"]["external"][0]["name"]["as"] = "something_else"
    assert any("served by no" in p for p in autoscaling_problems(rendered["autoscaled"],
                                                                   values))
