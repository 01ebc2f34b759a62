"""/readyz tells the truth (issue 11): a service alive but not doing its job for
AOI3D_STALL_S answers 503 with the reason, and turns ready again once it works."""

from __future__ import annotations

import time

from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from services.kit.codec import with_delivery
from services.kit.keys import Keys
from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from services.metrics.app import create_app as metrics_app
from services.metrics.settings import Settings as MetricsSettings
from services.scheduler.app import create_app as scheduler_app
from services.scheduler.settings import Settings as SchedulerSettings
from tests.support.network import frame
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
STALL_S = 2.0 * SCALE


def wait_status(client: TestClient, code: int) -> dict:
    deadline = time.monotonic() + 10 * SCALE
    while time.monotonic() < deadline:
        r = client.get("/readyz")
        if r.status_code == code:
            return r.json()
        time.sleep(0.05)
    raise AssertionError(f"/readyz never answered {code}: {r.status_code} {r.text}")


def test_scheduler_without_delivered_frames_is_not_ready_then_recovers() -> None:
    bus = MemoryBus()
    keys = Keys("ready")
    common = CommonSettings(run_id="ready", cameras=3, stall_s=STALL_S)
    clock = SimClock(time.time(), 1.0)
    started = time.monotonic()
    with TestClient(scheduler_app(SchedulerSettings(common=common), bus=bus,
                                  clock=clock)) as client:
        first = client.get("/readyz").status_code
        if time.monotonic() - started < STALL_S:  # (a busy machine may start it later)
            assert first == 200  # within the grace after start
        body = wait_status(client, 503)
        assert "no frame delivered" in body["reason"]
        now = clock.now_ms()
        f = frame(1, now)
        bus.publish(keys.edge_frame(1), with_delivery(f, now + 1.0))
        wait_status(client, 200)


def test_metrics_without_quality_is_not_ready() -> None:
    common = CommonSettings(run_id="ready", stall_s=STALL_S)
    with TestClient(metrics_app(MetricsSettings(common=common), bus=MemoryBus())) as client:
        body = wait_status(client, 503)
        assert "no Quality" in body["reason"]
