"""A pipeline on real cameras (``aoi3d up --rig``) as the ROS 2 live tests drive it
(tests/integration/test_ros2.py on Zenoh, test_ros2_dds.py on DDS): its ports (the ``ros2``
block of tests/support/ports.py; the ingest takes the camera emulator's REST port), its start,
the services' health, /metrics, and a Zenoh tap of its Quality."""

from __future__ import annotations

import os
import subprocess
import threading
import uuid
from pathlib import Path

from aoi3d_cli.pipeline import Pipeline
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.metrics import total
from tests.support.pipeline import HTTP, handle, wait_for
from tests.support.ports import block

__all__ = ["PIPE", "PORTS", "PORT_OFFSET", "ZENOH_PORT", "QualityTap", "metric", "up_rig",
           "wait_healthy"]

PIPE = handle("ros2")
"""The rig pipeline's handle (``PIPE.url("ingest", …)``: the camera emulator's port)."""
PORTS = block("ros2")
PORT_OFFSET = PORTS.rest_offset
ZENOH_PORT = PORTS.zenoh
RIG_SERVICES = ("ingest", "network", "scheduler", "dispatcher", "metrics")


def metric(service: str, name: str, default: float | None = None) -> float:
    """Sum of a metric's samples (all label sets) from a service's /metrics; ``default`` when
    it has none, else :class:`tests.support.metrics.MissingSeries` (a live wait keeps
    waiting)."""
    return total(HTTP.get(PIPE.url(service, "/metrics")).text, name, default)


def up_rig(rig: Path, tmp_path: Path, prefix: str, *up_args: str) -> tuple[Pipeline, str]:
    """``aoi3d up --rig`` on these ports (30 steps per render), and its run id."""
    run_id = f"{prefix}{uuid.uuid4().hex[:8]}"
    env = dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="30")
    up = PIPE.start(["--rig", str(rig), *up_args], run_id=run_id, log_dir=tmp_path / "logs",
                    env=env, output=subprocess.PIPE)
    return up, run_id


def wait_healthy() -> None:
    for name in RIG_SERVICES:
        wait_for(f"{name} /healthz",
                 lambda n=name: HTTP.get(PIPE.url(n, "/healthz")).status_code == 200, 120)


class QualityTap:
    """A Zenoh client session on the pipeline's router that records the run's Quality."""

    def __init__(self, run_id: str) -> None:
        import zenoh

        from services.kit.settings import CommonSettings, zenoh_config

        self.session = zenoh.open(zenoh_config(CommonSettings(
            zenoh_connect=[f"tcp/127.0.0.1:{ZENOH_PORT}"])))
        self.lock = threading.Lock()
        self.quality: list[pb.Quality] = []
        self.sub = self.session.declare_subscriber(Keys(run_id).quality, self._on)

    def _on(self, sample) -> None:
        with self.lock:
            self.quality.append(pb.Quality.FromString(sample.payload.to_bytes()))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()
