"""bench/chaos.py's multi-host target, as far as it runs without a Docker engine: its compose
override follows the Compose Specification and names real settings, its fault draw hits only
services compose.multihost.yaml has (routers on the mesh, workers, edge services) and draws
every kind, its ports are the ones compose.multihost.yaml publishes, and the judge counts
recoveries and stalls as documented. The 10-minute run itself needs the images and an engine
(`make bench-multihost`)."""

from __future__ import annotations

import json
import random
import re
from pathlib import Path

import jsonschema
import yaml

from bench import chaos
from services.metrics.settings import Settings as MetricsSettings

ROOT = Path(__file__).resolve().parents[3]
MULTIHOST = yaml.safe_load((ROOT / "compose.multihost.yaml").read_text())


def test_override_follows_the_spec_and_names_real_settings() -> None:
    override = chaos.multihost_override()
    schema = json.loads((ROOT / "tests/data/compose-spec.json").read_text())
    jsonschema.validate(override, schema)
    assert set(override["services"]) <= set(MULTIHOST["services"])
    env = override["services"]["metrics"]["environment"]
    fields = {f"AOI3D_METRICS_{name.upper()}" for name in MetricsSettings.model_fields}
    assert set(env) <= fields, set(env) - fields
    # the ledger's state folder is on the volume the override adds
    (mount,) = override["services"]["metrics"]["volumes"]
    volume, path = mount.split(":")
    assert volume in override["volumes"] and env["AOI3D_METRICS_STATE_DIR"].startswith(path)
    assert float(env["AOI3D_METRICS_LEDGER_OPEN_S"]) == chaos.LEDGER_OPEN_S


def test_fault_draw_hits_what_the_stack_has() -> None:
    rng = random.Random(1)
    draws = [chaos.fault_plan(rng) for _ in range(2000)]
    assert {k for k, _ in draws} == {"cut", "router_restart", "edge_restart", "worker_kill"}
    services = MULTIHOST["services"]
    for kind, target in draws:
        assert target in services, target
        if kind == "cut":  # a worker host's router, on the mesh (its only link to the edge)
            assert "mesh" in services[target]["networks"] and target != "router-edge"
        if kind == "worker_kill":
            assert services[target]["command"] == ["python", "-m", "services.recon"]
        if kind == "edge_restart":
            assert "edge" in services[target]["networks"]
    # every worker host in MH_HOSTS is a (router, worker) pair on one host network
    for host, (router, worker) in chaos.MH_HOSTS.items():
        assert services[worker]["hostname"] == host
        assert set(services[worker]["networks"]) < set(services[router]["networks"])
    compile(chaos.KILL_WORKER, "kill_worker", "exec")


def test_ports_are_the_ones_the_stack_publishes() -> None:
    text = (ROOT / "compose.multihost.yaml").read_text()
    published = set(re.findall(r"AOI3D_PORT_(\w+):-", text))
    assert set(chaos.MH_PORTS) == published
    assert len(set(chaos.MH_PORTS.values())) == len(chaos.MH_PORTS)


def test_judge_counts_recoveries_and_stalls() -> None:
    class FakeTap:
        def quality_times(self, site: str) -> list[float]:
            return [1.0, 2.0, 20.0, 21.0, 25.0]

    faults = [{"kind": "cut", "end": 2.5}, {"kind": "worker_kill", "end": 30.0}]
    stalls, longest = chaos.judge(FakeTap(), ["site1"], faults, 0.0, 28.0)
    assert [f["recovery_s"] for f in faults] == [17.5, None]
    assert "end" not in faults[0]
    assert stalls == 1 and longest == 18.0


def test_fault_loop_spaces_the_faults_and_stops_at_the_end(monkeypatch) -> None:
    """The one fault loop of both targets: pauses drawn from --every, a fault after each, none
    that would start past --minutes; each fault stamped with its start and end."""
    import argparse

    clock = [0.0]
    monkeypatch.setattr(chaos.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(chaos.time, "sleep", lambda s: clock.__setitem__(0, clock[0] + s))
    args = argparse.Namespace(minutes=1.0, every=(20.0, 20.0))
    done = []

    def inject() -> dict:
        clock[0] += 2.0  # the fault takes 2 s
        done.append(clock[0])
        return {"kind": "kill", "target": "scheduler"}

    faults, t_start, t_end = chaos.fault_loop(args, random.Random(0), inject)
    assert [f["t_s"] for f in faults] == [20.0, 42.0]  # a third would start at 64 s > 60 s
    assert [f["end"] for f in faults] == done and t_start == 0.0 and t_end == 60.0
    assert all(f["kind"] == "kill" for f in faults)
