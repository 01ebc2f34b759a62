"""The worker pool on a real pipeline (issue 22): `aoi3d up --workers 2`, real processes, real
Zenoh on 127.0.0.1. A worker killed with SIGKILL while it reconstructs costs exactly the
decision it held — counted lost (``worker_died``) — and the pool goes on; no decision is ever
rendered twice; the restarted worker rejoins by itself."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import uuid
from pathlib import Path

import pytest

from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.pipeline import HTTP, Tap, assert_clean_exit, handle, stop_pipeline, wait_for
from tests.support.ports import block

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PIPE = handle("pool")
_PORTS = block("pool")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh



class RenderTap(Tap):
    """The Tap, plus every Render's (incarnation, decision id, worker)."""

    def __init__(self, run_id: str) -> None:
        super().__init__(run_id, zenoh_port=ZENOH_PORT)
        self.renders: list[tuple[int, int, str]] = []
        self._rlock = threading.Lock()
        self.subs.append(self.session.declare_subscriber(Keys(run_id).render, self._on_render))

    def _on_render(self, sample) -> None:
        msg = pb.Render.FromString(sample.payload.to_bytes())
        with self._rlock:
            self.renders.append((msg.decision_incarnation, msg.decision_id, msg.worker_id))


def test_a_killed_worker_costs_only_its_decision(small_dataset: Path,
                                                 tmp_path: Path) -> None:
    run_id = f"pool{uuid.uuid4().hex[:8]}"
    log_dir = tmp_path / "logs"
    cmd = ["--dataset", str(small_dataset),
           "--run-id", run_id, "--log-dir", str(log_dir), "--time-scale", "0.1",
           "--workers", "2"]
    # enough steps that a reconstruction lasts long enough to be caught mid-way
    env = dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="150")
    up = PIPE.start(cmd, env=env, output=subprocess.PIPE)
    tap = None
    try:
        pool = wait_for("two workers in the pool", lambda: len(
            (p := HTTP.get(PIPE.url("dispatcher", "/workers")).json())["workers"]) == 2 and p,
            timeout_s=120)
        tap = RenderTap(run_id)
        wait_for("renders from both workers", lambda: len(
            {w for _, _, w in tap.renders}) == 2, timeout_s=90)
        wait_for("quality", lambda: tap.qualities, timeout_s=60)

        # a worker in the middle of a reconstruction is killed
        busy = wait_for("a worker holding a decision", lambda: next(
            (w for w in HTTP.get(PIPE.url("dispatcher", "/workers")).json()["workers"]
             if w["holding"] is not None), None), every_s=0.02)
        before = HTTP.get(PIPE.url("dispatcher", "/workers")).json()
        os.kill(busy["pid"], signal.SIGKILL)
        after = wait_for("the loss counted", lambda: (p := HTTP.get(
            PIPE.url("dispatcher", "/workers")).json())["lost"].get("worker_died") and p,
            timeout_s=30)
        assert after["lost"]["worker_died"] == before["lost"].get("worker_died", 0) + 1
        assert set(after["lost"]) == {"worker_died"}, after["lost"]
        # the held decision is the one lost: never rendered by anyone
        killed = busy["worker_id"]

        # the pool goes on: new Quality, renders from the surviving worker
        n_quality = len(tap.qualities)
        wait_for("quality after the kill", lambda: len(tap.qualities) > n_quality + 2,
                 timeout_s=60)
        # the supervisor restarts the worker; it rejoins the pool with a new id
        wait_for("the pool back to two workers", lambda: len(
            ws := HTTP.get(PIPE.url("dispatcher", "/workers")).json()["workers"]) == 2
            and killed not in {w["worker_id"] for w in ws}, timeout_s=60)
        state = json.loads((log_dir / "latest" / "up.json").read_text())
        assert sum(c["restarts"] for n, c in state["children"].items()
                   if n.startswith("recon-")) == 1

        final = HTTP.get(PIPE.url("dispatcher", "/workers")).json()
        with tap._rlock:
            done = [(i, d) for i, d, _ in tap.renders]
        assert len(done) == len(set(done)), "a decision was rendered twice"
        assert final["rendered"] + sum(final["lost"].values()) + final["in_flight"] \
            == final["assigned"]
        assert final["assigned"] + final["superseded"] + len(final["pending"]) \
            == final["decisions"]
        # a worker's device and pid are known from its first request on
        assert {w["device"] for w in final["workers"]} == {"cpu"}, final["workers"]
        assert len(pool["workers"]) == 2
    finally:
        if tap is not None:
            tap.close()
        out = stop_pipeline(up)
        print(out[-3000:])  # pytest shows it when the test fails, whatever failed
    assert_clean_exit(up, out, run_id)
    assert "recon-" in out and "restarted" in out
