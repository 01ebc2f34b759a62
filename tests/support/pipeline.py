"""A real pipeline (`aoi3d up`) as the live tests drive it (tests/integration/, tests/browser/,
tests/monitoring/), on the one pipeline handle (:class:`aoi3d_cli.pipeline.Pipeline`): a handle
on a test file's block of ports (:func:`handle`, tests/support/ports.py), the REST client,
/metrics, a Zenoh tap of the decisions and Quality, and a clean stop."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import httpx
import pytest

from aoi3d_cli.pipeline import Pipeline
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.ports import PortBlock
from tests.support import waits
from tests.support.metrics import total
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
"""Every wait and timeout of the live tests is multiplied by this (a slow or busy machine:
set AOI3D_TEST_TIMEOUT_SCALE=3)."""
HTTP = httpx.Client(timeout=30 * SCALE)
"""The tests' REST client: never httpx's default 5 s timeout."""


def handle(name: str) -> Pipeline:
    """A handle on the pipeline of the test block ``name`` (tests/support/ports.py), its
    timeout scaled: its URLs, REST, /metrics; :meth:`~Pipeline.start` runs ``aoi3d up`` there."""
    b = block(name)
    return Pipeline(PortBlock(b.rest_offset, b.zenoh), timeout_s=30 * SCALE)


PIPE = handle("pipeline")
"""tests/integration/test_pipeline.py's and test_ppo_live.py's pipeline."""
PORT_OFFSET = PIPE.block.offset
ZENOH_PORT = PIPE.block.zenoh
SERVICES = ("camera", "network", "scheduler", "dispatcher", "metrics")


def wait_for(what: str, check, timeout_s: float = 60.0, every_s: float = 0.25):
    """:func:`tests.support.waits.wait_for` for a live pipeline: every 0.25 s, up to 60 s
    (scaled), a service not answering yet (an HTTP error, a series not exported yet) is
    "not yet"."""
    return waits.wait_for(check, timeout_s, what=what, every_s=every_s,
                          tolerate=(httpx.HTTPError, KeyError, ValueError))


def metric(service: str, name: str, default: float | None = None) -> float:
    """Sum of a metric's samples (all label sets) from a service's /metrics on the pipeline's
    ports; ``default`` when it has none, else :class:`tests.support.metrics.MissingSeries`
    (a KeyError: a live wait keeps waiting)."""
    return total(HTTP.get(PIPE.url(service, "/metrics")).text, name, default)


def stop_pipeline(up: Pipeline) -> str:
    """Stop the ``aoi3d up`` that ``up`` started (SIGTERM, SIGKILL to its session after 40 s,
    scaled); its output. Safe in a ``finally``: it asserts nothing, so a failure of the test
    body is not masked."""
    return up.stop(40 * SCALE)


def assert_clean_exit(up: Pipeline, out: str, run_id: str) -> None:
    """``aoi3d up`` exited 0 and left no process of the run behind."""
    assert up.proc is not None and up.proc.returncode == 0, out[-3000:]
    wait_for("no process of the run left", lambda: not processes_of_run(run_id), timeout_s=10)


def processes_of_run(run_id: str) -> list[int]:
    """PIDs of live processes whose environment carries this run id."""
    needle = f"AOI3D_RUN_ID={run_id}".encode()
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if needle in (entry / "environ").read_bytes().split(b"\0"):
                stat = (entry / "stat").read_text()
                if stat.split(") ", 1)[1].split()[0] != "Z":
                    pids.append(int(entry.name))
        except OSError:
            continue
    return pids


class Tap:
    """A Zenoh client session that records the run's decisions and quality messages."""

    def __init__(self, run_id: str, zenoh_port: int = ZENOH_PORT) -> None:
        import zenoh

        from services.kit.settings import CommonSettings, zenoh_config

        keys = Keys(run_id)
        conf = zenoh_config(CommonSettings(zenoh_connect=[f"tcp/127.0.0.1:{zenoh_port}"]))
        self.session = zenoh.open(conf)
        self.lock = threading.Lock()
        self.decisions: list[tuple[float, pb.Decision]] = []
        self.qualities: list[pb.Quality] = []
        self.quality_times: list[float] = []  # when each Quality arrived (monotonic)
        self.keys = keys
        self.subs = [
            self.session.declare_subscriber(keys.decision, self._on_decision),
            self.session.declare_subscriber(keys.quality, self._on_quality),
        ]

    def _on_decision(self, sample) -> None:
        msg = pb.Decision.FromString(sample.payload.to_bytes())
        with self.lock:
            self.decisions.append((time.monotonic(), msg))

    def _on_quality(self, sample) -> None:
        msg = pb.Quality.FromString(sample.payload.to_bytes())
        with self.lock:
            self.qualities.append(msg)
            self.quality_times.append(time.monotonic())

    def decisions_after(self, t: float) -> list[pb.Decision]:
        with self.lock:
            return [d for ts, d in self.decisions if ts > t]

    def publish(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def small_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The live tests' 48×36 turbine of 2 s (the ``small_dataset`` fixture, tests/conftest.py)."""
    from aoi3d.scene import SceneConfig, generate_dataset

    path = tmp_path_factory.mktemp("scene") / "turbine"
    generate_dataset(path, SceneConfig(width=48, height=36, duration_s=2.0, spp=2))
    return path
