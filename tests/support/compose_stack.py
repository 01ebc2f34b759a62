"""The compose stack as tests/containers/ bring it up: its own project, published ports (the
"compose" block of tests/support/ports.py) and secrets, the marks that skip it unless
`make compose-test`, and the waits of a stack that takes minutes."""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from aoi3d_cli.pipeline import Pipeline
from tests.support import waits
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

ROOT = Path(__file__).resolve().parents[2]
SCALE = timeout_scale()
"""Every wait is multiplied by this (a busy machine: AOI3D_TEST_TIMEOUT_SCALE=3)."""
HTTP = httpx.Client(timeout=30 * SCALE)
COMPOSE_MARKS = [
    pytest.mark.containers,
    pytest.mark.slow,
    pytest.mark.skipif(os.environ.get("AOI3D_COMPOSE_TEST") != "1",
                       reason="runs containers: `make compose-test` (sets AOI3D_COMPOSE_TEST=1)"),
]
TARGET_PORTS = {"ZENOH": 7447, "CAMERA": 8101, "NETWORK": 8102, "SCHEDULER": 8103,
                "DISPATCHER": 8104, "METRICS": 8105, "CONSOLE": 8106, "RECORDER": 8107,
                "PROMETHEUS": 9090, "GRAFANA": 3000}
PORTS = dict(zip(TARGET_PORTS, block("compose").ports(), strict=False))
"""Published ports of this run (compose.yaml's AOI3D_PORT_<NAME>)."""
PROJECT = f"aoi3d-test-{os.getpid()}"
HAS_CONSOLE = (ROOT / "services" / "console" / "__main__.py").is_file()
SERVICES = ["router", "dataset", "camera", "network", "scheduler", "dispatcher", "recon",
            "metrics", "recorder", "prometheus", *(["console"] if HAS_CONSOLE else [])]
"""What `up` starts: everything but Grafana; the console once it exists in the code."""


STACK = Pipeline(ports={name.lower(): port for name, port in PORTS.items()},
                 timeout_s=30 * SCALE)
"""The stack's services on their published ports, as the one pipeline handle sees them."""
url = STACK.url


def wait_for(what: str, check: Callable[[], Any], timeout_s: float = 60.0,
             every_s: float = 1.0) -> Any:
    """:func:`tests.support.waits.wait_for` for the stack: every second, up to a minute
    (scaled); a service not answering yet is "not yet"."""
    return waits.wait_for(check, timeout_s, what=what, every_s=every_s,
                          tolerate=(httpx.HTTPError, KeyError, ValueError, IndexError))


class Stack:
    """`docker compose` on ``files`` (compose.yaml) as ``project`` (PROJECT), with this run's
    environment."""

    def __init__(self, secrets_dir: Path, project: str = PROJECT,
                 files: tuple[Path, ...] = (ROOT / "compose.yaml",)) -> None:
        self.project, self.files = project, files
        self.env = {**os.environ,
                    **{f"AOI3D_PORT_{name}": str(port) for name, port in PORTS.items()},
                    "AOI3D_SECRETS_DIR": str(secrets_dir),
                    "AOI3D_RUN_ID": project,
                    "COMPOSE_PROJECT_NAME": project}
        self.env.setdefault("AOI3D_PROMETHEUS_IMAGE", "aoi3d-prometheus:debian")
        self.secrets_dir = secrets_dir
        self.token = (secrets_dir / "control_token").read_text(encoding="utf-8").strip()

    def compose(self, *args: str, timeout_s: float = 120.0,
                check: bool = True) -> subprocess.CompletedProcess[str]:
        files = [a for f in self.files for a in ("-f", str(f))]
        return self.run("docker", "compose", *files, "-p", self.project, *args,
                        timeout_s=timeout_s, check=check)

    def up_wait(self, *services: str) -> float:
        """``up -d --wait`` (every healthcheck passing); on a failure the state and the logs
        are printed and the stack taken down. Returns the seconds it took."""
        t0 = time.monotonic()
        try:
            self.compose("up", "-d", "--no-build", "--wait", "--wait-timeout",
                         str(int(600 * SCALE)), *services, timeout_s=660)
        except AssertionError:
            self.report_and_down()
            raise
        return time.monotonic() - t0

    def report_and_down(self) -> None:
        """After a failure: print the containers' state and logs, take the stack down."""
        print(self.compose("ps", "-a", check=False).stdout)
        print(self.compose("logs", "--tail", "40", check=False).stdout[-8000:])
        self.compose("down", "-v", "--remove-orphans", check=False)

    def run(self, *argv: str, timeout_s: float = 120.0,
            check: bool = True) -> subprocess.CompletedProcess[str]:
        proc = subprocess.run(argv, env=self.env, capture_output=True, text=True,
                              timeout=timeout_s * SCALE)
        if check and proc.returncode != 0:
            raise AssertionError(f"{' '.join(argv)} exited {proc.returncode}:\n"
                                 f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        return proc

    def container(self, service: str) -> str:
        return self.compose("ps", "-aq", service).stdout.strip()

    def inspect(self, service: str) -> dict[str, Any]:
        return json.loads(self.run("docker", "inspect", self.container(service)).stdout)[0]

    def leftovers(self) -> dict[str, list[str]]:
        """Containers, networks and volumes still labelled with this project."""
        label = f"label=com.docker.compose.project={self.project}"
        return {kind: self.run("docker", *cmd, "--filter", label, "-q").stdout.split()
                for kind, cmd in {"containers": ["ps", "-a"], "networks": ["network", "ls"],
                                  "volumes": ["volume", "ls"]}.items()}
