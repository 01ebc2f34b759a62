"""compose.rig.yaml run for real (``make compose-test``): real cameras in the compose stack.

A robot on its own network side — a Zenoh router of its own (plain TCP, as a robot's LAN) and
the pure-Python robot (``aoi3d ros2 publish``, four cameras of the stack's rendered turbine on
rmw_zenoh keys) in containers of the same image — and the stack with compose.rig.yaml on top:
the camera slot runs the ingest on the rig file, which reaches the robots' router
(``source.connect``) from a second session, while the services keep their mutual-TLS router.
Checked through the published ports, as an operator would: every healthcheck passes, the
ingest takes every camera's frames with nothing refused, and Quality flows. The rig file is
written by the robot itself (``--write-rig --rig-only``) from the stack's dataset volume.
"""

from __future__ import annotations

import math
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from tests.support.compose_stack import HTTP, ROOT, SCALE, Stack, url, wait_for

pytestmark = [
    pytest.mark.containers,
    pytest.mark.slow,
    pytest.mark.skipif(os.environ.get("AOI3D_COMPOSE_TEST") != "1",
                       reason="runs containers: `make compose-test` (sets AOI3D_COMPOSE_TEST=1)"),
]

PROJECT = f"aoi3d-rig-{os.getpid()}"
CAMERAS = 4
PUBLISH = ["aoi3d", "ros2", "publish", "/data/turbine-rotor", "--cameras", str(CAMERAS),
           "--time-scale", "1", "--connect", "tcp/robot-router:7447"]
ROBOT = {
    "services": {
        "robot-router": {
            "image": "aoi3d:0.1.0", "init": True, "cpus": 0.5, "mem_limit": "512m",
            "command": ["python", "-m", "services.router"],
            "environment": {"AOI3D_ROUTER_LISTEN": "tcp/0.0.0.0:7447"},
            "healthcheck": {"test": ["CMD", "python", "-c", "import socket; socket."
                                     "create_connection(('127.0.0.1', 7447), timeout=2)"
                                     ".close()"],
                            "interval": "5s", "timeout": "10s", "retries": 3,
                            "start_period": "60s"},
        },
        "robot": {
            "image": "aoi3d:0.1.0", "init": True, "cpus": 1, "mem_limit": "1g",
            "command": PUBLISH,
            "volumes": ["dataset:/data:ro"],
            "depends_on": {"robot-router": {"condition": "service_healthy"},
                           "dataset": {"condition": "service_completed_successfully"}},
        },
    },
}
SERVICES = ["router", "dataset", "camera", "network", "scheduler", "dispatcher", "recon",
            "metrics", "robot-router", "robot"]


class RigStack(Stack):
    """The stack of compose.yaml + compose.rig.yaml + the robot's override, as PROJECT."""

    def __init__(self, secrets_dir: Path, workdir: Path) -> None:
        override = workdir / "compose.robot.yaml"
        override.write_text(yaml.safe_dump(ROBOT))
        super().__init__(secrets_dir, PROJECT, (ROOT / "compose.yaml",
                                                ROOT / "compose.rig.yaml", override))
        self.rig = workdir / "rig.yaml"
        self.env.update(AOI3D_RIG_FILE=str(self.rig), AOI3D_CAMERAS=str(CAMERAS),
                        AOI3D_TIME_SCALE="1", AOI3D_TRUTH_PERIOD_MS="30")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RigStack]:
    secrets_dir = tmp_path_factory.mktemp("secrets")
    subprocess.run([str(ROOT / "deploy" / "secrets.sh"), str(secrets_dir)], check=True)
    workdir = tmp_path_factory.mktemp("rig")
    workdir.chmod(0o777)  # the robot's container (not root) writes the rig file there
    s = RigStack(secrets_dir, workdir)
    s.run("docker", "info", timeout_s=30)
    t0 = time.monotonic()
    try:
        # the robot writes the rig file that reads what it publishes, from the stack's dataset
        s.compose("up", "--no-build", "dataset", timeout_s=600)
        s.compose("run", "--rm", "--no-deps", "-v", f"{workdir}:/rig", "robot", *PUBLISH,
                  "--write-rig", "/rig/rig.yaml", "--rig-only", timeout_s=120)
        doc = yaml.safe_load(s.rig.read_text())
        doc["source"]["connect"] = ["tcp/robot-router:7447"]  # the robots' own router
        s.rig.write_text(yaml.safe_dump(doc))
    except AssertionError:
        s.report_and_down()
        raise
    s.up_wait(*SERVICES)
    print(f"\ncompose rig up --wait: healthy after {time.monotonic() - t0:.0f} s")
    try:
        yield s
    finally:
        s.compose("down", "-v", "--remove-orphans", check=False)
        assert not any(s.leftovers().values()), s.leftovers()


def test_the_ingest_runs_in_the_camera_slot_and_takes_the_robots_frames(stack) -> None:
    for service in SERVICES:
        state = stack.inspect(service)["State"]
        if service == "dataset":
            assert state["Status"] == "exited" and state["ExitCode"] == 0, state
        elif service != "robot":  # (no healthcheck: it only publishes)
            assert state["Health"]["Status"] == "healthy", (service, state["Health"])
    assert stack.inspect("robot")["State"]["Status"] == "running"

    def all_cameras() -> dict | None:
        status = HTTP.get(url("camera", "/status")).json()
        cams = {c["name"]: c for c in status["cameras"]}
        return status if len(cams) == CAMERAS + 1 and all(
            c["published"] >= 10 for c in cams.values()) else None

    status = wait_for("every camera's frames through the ingest", all_cameras, timeout_s=120)
    assert status["truth"] == "cam00" and "steps aside" in status["link"]
    # The robot runs before the ingest is up, so the ingest can hear a camera's first images
    # before its first pose or CameraInfo: those are refused (no_pose, no_intrinsics), as a
    # real robot's would be. After that start, nothing more is refused while frames flow.
    start = {c["name"]: c for c in status["cameras"]}
    for cam in start.values():
        assert set(cam["rejected"]) <= {"no_pose", "no_intrinsics"}, cam
    time.sleep(10 * SCALE)
    later = {c["name"]: c for c in HTTP.get(url("camera", "/status")).json()["cameras"]}
    for name, cam in later.items():
        assert cam["published"] > start[name]["published"], (start[name], cam)
        assert cam["rejected"] == start[name]["rejected"], (start[name], cam)


def test_quality_flows_from_the_robots_frames(stack) -> None:
    history = wait_for("quality history",
                       lambda: HTTP.get(url("metrics", "/quality")).json()["history"],
                       timeout_s=240)
    assert all(math.isfinite(q["psnr_db"]) for q in history)
